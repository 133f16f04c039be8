import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import procs
from nerfpod.nerf import encodings

# One program each rather than one per operation (the numbers that shape them static).
_positional_encoding = jax.jit(encodings.positional_encoding, static_argnums=1)
_hash_indices = jax.jit(encodings.hash_indices, static_argnums=1)
_coarse_to_fine_weights = jax.jit(encodings.coarse_to_fine_weights, static_argnums=(1, 2, 3))


def test_positional_encoding_layout_and_switch_off():
  x = np.array([[0.1, -0.2, 0.3]], np.float32)
  enc = np.asarray(_positional_encoding(x, 6))
  assert enc.shape == (1, 3 + 3 * 2 * 6)
  np.testing.assert_allclose(enc[0, :3], x[0])
  np.testing.assert_allclose(enc[0, 3:6], np.sin(x[0]), rtol=1e-6)
  np.testing.assert_allclose(enc[0, 6:9], np.cos(x[0]), rtol=1e-6)
  np.testing.assert_allclose(enc[0, -3:], np.cos(32.0 * x[0]), rtol=1e-5)
  np.testing.assert_array_equal(_positional_encoding(x, 0), x)  # the tutorial's "without"


def test_hash_indices_stay_in_range_and_use_the_table():
  corners = jax.random.randint(jax.random.key(0), (20000, 3), 0, 4096)
  idx = np.asarray(_hash_indices(corners, 2**14))
  assert idx.min() >= 0 and idx.max() < 2**14
  assert len(np.unique(idx)) > 0.6 * 2**14  # spreads over the table


def test_dense_levels_index_every_vertex_once():
  res = 7
  grid = np.stack(np.meshgrid(*[np.arange(res + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
  grid_indices = jax.jit(encodings.grid_indices, static_argnums=(1, 2))  # one program, not one per operation
  idx = np.asarray(grid_indices(jnp.asarray(grid)[:, None, :], res, 2**12))[:, 0]
  assert sorted(idx.tolist()) == list(range((res + 1)**3))


def _grid_and_params(res=8):
  module = encodings.HashGridEncoding(num_levels=3, features_per_level=2, log2_table_size=8,
                                      base_resolution=4, max_resolution=res)

  @jax.jit  # one program rather than one per operation
  def init(key):
    params = module.init(key, jnp.zeros((1, 3)))
    # Larger random tables than the tiny initialisation, so interpolation errors would show.
    return jax.tree.map(lambda p: jax.random.normal(jax.random.key(1), p.shape), params)
  return module, init(jax.random.key(0))


def test_trilinear_interpolation_is_exact_at_grid_vertices():
  res = 4
  corners, weights = jax.jit(encodings.trilinear_corners_and_weights, static_argnums=1)(
      jnp.array([[0.25, 0.5, 0.75], [1.0, 0.0, 1.0]]), res)
  w = np.asarray(weights)
  assert np.allclose(w.max(-1), 1.0) and np.allclose(w.sum(-1), 1.0)
  best = np.asarray(corners)[np.arange(2), w.argmax(-1)]
  np.testing.assert_array_equal(best, [[1, 2, 3], [4, 0, 4]])
  # Through the whole encoding: at a vertex of the coarsest level, level 0's output is that vertex's row.
  module, params = _grid_and_params()
  vertex = jnp.array([[0.25, 0.5, 0.75]])
  out = np.asarray(jax.jit(module.apply)(params, vertex))
  row = 1 * 25 + 2 * 5 + 3  # dense index of vertex (1, 2, 3) on the 5^3 vertices of level 0
  np.testing.assert_allclose(out[0, :2], np.asarray(params["params"]["level_0"])[row], rtol=1e-5)
  # The finest level (8 cells, 729 vertices) is hashed into 2^8 rows; (2, 4, 6) is one of its vertices.
  finest = _hash_indices(jnp.array([2, 4, 6]), 2**8)
  np.testing.assert_allclose(out[0, -2:], np.asarray(params["params"]["level_2"])[finest], rtol=1e-5)


def test_encoding_is_continuous_across_cell_faces():
  module, params = _grid_and_params()
  apply = jax.jit(module.apply)  # one program for the three axes' points, not one per operation
  for axis in range(3):
    face = np.array([0.3, 0.6, 0.45])
    face[axis] = 0.5  # a cell face on every level (resolutions 4, 5, 8: 0.5 is a face for 4 and 8)
    eps = np.zeros(3)
    eps[axis] = 1e-5
    a, b, c = (np.asarray(apply(params, jnp.asarray([face + k * eps], jnp.float32))) for k in (-1, 1, 100))
    np.testing.assert_allclose(a, b, atol=1e-3)
    assert np.abs(c - a).max() > np.abs(b - a).max()  # it does vary


@pytest.mark.parametrize("levels,base,top", [(16, 16, 2048), (8, 16, 256)])
def test_level_resolutions_grow_geometrically(levels, base, top):
  res = encodings.level_resolutions(levels, base, top)
  assert res[0] == base and res[-1] == top and len(res) == levels
  ratios = np.array(res[1:]) / np.array(res[:-1])
  assert np.allclose(ratios, ratios.mean(), atol=0.1)


def test_spherical_harmonics_are_orthonormal():
  @jax.jit  # one program rather than one per operation
  def gram_of(key):
    dirs = jax.random.normal(key, (400_000, 3))
    sh = encodings.spherical_harmonics_deg4(dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True))
    return sh.T @ sh
  gram = 4 * np.pi * np.asarray(gram_of(jax.random.key(0))) / 400_000
  np.testing.assert_allclose(gram, np.eye(16), atol=0.03)


def test_axis_weights_factor_the_trilinear_weights():
  x = np.array(jax.random.uniform(jax.random.key(3), (50, 3)))
  x[0] = [1.0, 0.0, 0.5]  # (edited in NumPy: no program per edit)
  res = 5
  corners, weights = jax.jit(encodings.trilinear_corners_and_weights, static_argnums=1)(x, res)
  w = np.asarray(jax.jit(encodings.axis_weights, static_argnums=1)(x, res))
  assert w.shape == (50, 3, res + 1)
  c = np.asarray(corners)
  outer = w[np.arange(50)[:, None], 0, c[..., 0]] * w[np.arange(50)[:, None], 1, c[..., 1]] * \
      w[np.arange(50)[:, None], 2, c[..., 2]]
  np.testing.assert_allclose(outer, weights, rtol=1e-6, atol=1e-7)
  np.testing.assert_allclose(w.sum(-1), 1.0, rtol=1e-6)


@pytest.mark.parametrize("res", [3, 6])
def test_matmul_lookup_equals_the_gather_in_values_and_gradients(res):
  """The TPU-suited formulation of a dense level: same features, same table gradient (no scatter-add)."""
  side = res + 1
  table = jax.random.normal(jax.random.key(0), (side**3, 2))
  x = jax.random.uniform(jax.random.key(1), (300, 3))
  x = x.at[:3].set(jnp.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 1.0, 0.0]]))  # edges and vertices
  cotangent = jax.random.normal(jax.random.key(2), (300, 2))
  loss = lambda f: lambda t: jnp.sum(f(t, x, res) * cotangent)
  lookup = lambda f: jax.jit(f, static_argnums=2)(table, x, res)
  np.testing.assert_allclose(lookup(encodings.dense_level_matmul), lookup(encodings.level_gather),
                             rtol=1e-5, atol=1e-6)
  grad_gather = jax.jit(jax.grad(loss(encodings.level_gather)))(table)
  grad_matmul = jax.jit(jax.grad(loss(encodings.dense_level_matmul)))(table)
  assert np.abs(np.asarray(grad_gather)).max() > 0.1  # a real gradient
  np.testing.assert_allclose(grad_matmul, grad_gather, rtol=1e-5, atol=1e-5)


def test_encoding_with_matmul_levels_equals_the_gather_encoding():
  gather, params = _grid_and_params()
  matmul = encodings.HashGridEncoding(num_levels=3, features_per_level=2, log2_table_size=8,
                                      base_resolution=4, max_resolution=8, matmul_max_rows=256)
  x = jax.random.uniform(jax.random.key(4), (200, 3))
  # Levels 0 and 1 (5^3, 6^3 rows) take the matmul; level 2 (hashed) still gathers: the jaxpr shows both.
  ops = str(jax.make_jaxpr(lambda p: matmul.apply(p, x))(params))
  assert ops.count("dot_general") >= 6 and "gather" in ops
  value_and_grad = lambda m: jax.jit(jax.value_and_grad(lambda p: jnp.sum(m.apply(p, x) ** 2)))
  (value_matmul, grads_matmul), (value_gather, grads_gather) = [value_and_grad(m)(params) for m in (matmul, gather)]
  np.testing.assert_allclose(value_matmul, value_gather, rtol=1e-5)
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), grads_matmul, grads_gather)


def _barf_weights(step, start, end, num_levels):
  """BARF's eq. 14 written out in NumPy, float64: alpha from 0 to L - 1, level 0 always open."""
  alpha = min(max((step - start) / (end - start), 0.0), 1.0) * (num_levels - 1)
  weights = [1.0]
  for level in range(1, num_levels):
    x = min(max(alpha - level + 1, 0.0), 1.0)
    weights.append((1.0 - np.cos(np.pi * x)) / 2.0)
  return np.array(weights)


@pytest.mark.parametrize("step", [0, 100, 101, 150, 237.5, 300, 399, 400, 1000])
def test_coarse_to_fine_weights_are_barfs(step):
  got = np.asarray(_coarse_to_fine_weights(step, 100, 400, 8))
  np.testing.assert_allclose(got, _barf_weights(step, 100, 400, 8), atol=1e-6)
  if step <= 100:
    np.testing.assert_array_equal(got, [1.0] + [0.0] * 7)  # before the start: the coarsest level only
  if step >= 400:
    np.testing.assert_array_equal(got, np.ones(8))  # from the end on: exactly 1, every level whole
  assert np.all(np.diff(got) <= 0)  # a finer level never opens before a coarser one


def test_coarse_to_fine_weights_rise_with_the_step():
  weights = np.stack([_coarse_to_fine_weights(s, 0, 50, 5) for s in range(0, 60, 5)])
  assert np.all(np.diff(weights, axis=0) >= 0)
  assert weights[5, 2] == pytest.approx(1.0) and weights[5, 3] == 0.0  # halfway: levels 0-2 open, 3-4 shut


def test_closed_levels_give_no_features_and_no_gradients_and_open_ones_are_the_plain_encoding():
  grid, params = _grid_and_params()
  x = jax.random.uniform(jax.random.key(5), (64, 3))
  opened = jnp.array([1.0, 0.5, 0.0])
  loss = lambda p, o: jnp.sum(grid.apply(p, x, None, o) ** 2)

  # One program rather than one per operation, its bits from optimised kernels (procs.OPTIMIZED_KERNELS), as
  # in every claim that two computations give the same bits.
  @functools.partial(jax.jit, compiler_options=procs.OPTIMIZED_KERNELS)
  def run(params, opened, all_open):
    return (grid.apply(params, x, None, opened), grid.apply(params, x), jax.grad(loss)(params, opened),
            grid.apply(params, x, None, all_open), jax.grad(loss)(params, all_open),
            jax.grad(lambda p: jnp.sum(grid.apply(p, x) ** 2))(params))

  features, plain, grads, all_open, grads_all_open, grads_plain = run(params, opened, jnp.ones(3))
  features, plain, grads = np.asarray(features), np.asarray(plain), grads["params"]
  np.testing.assert_array_equal(features[:, :2], plain[:, :2])
  np.testing.assert_allclose(features[:, 2:4], 0.5 * plain[:, 2:4], rtol=1e-6)
  np.testing.assert_array_equal(features[:, 4:], 0.0)
  assert np.abs(grads["level_0"]).max() > 0 and np.abs(grads["level_1"]).max() > 0
  np.testing.assert_array_equal(grads["level_2"], 0.0)  # a shut level does not learn
  # Every level open: the plain encoding to the bit, values and gradients.
  np.testing.assert_array_equal(all_open, plain)
  jax.tree.map(np.testing.assert_array_equal, grads_all_open, grads_plain)


def test_materialized_points_are_the_points_bit_for_bit_and_so_are_the_fields_values_and_gradients():
  """encodings.materialized (a matmul by the identity, kept in memory by XLA where the points' computation
  would be fused into every level) changes no bit: of the points, of their cotangents, of integer rows, and of
  a hash-grid field's colours, densities and every parameter's gradient (the lookup reading the kept rows,
  told they are in bounds), jitted on this backend as training is, with the points computed from rays inside
  the program (what XLA would otherwise fuse)."""
  from nerfpod.nerf import fields
  # (Inputs edited in NumPy: no program per edit.)
  x = np.array(jax.random.uniform(jax.random.key(0), (4096, 3), minval=-3.0, maxval=3.0))
  x[:3] = [[0.0, 1.0, 0.5], [1e-30, -0.0, 1e30], [1.0 / 3.0, 2.0 / 3.0, 1.0]]
  x = jnp.asarray(x)
  np.testing.assert_array_equal(jax.jit(encodings.materialized)(x), x)
  cotangent = jax.random.normal(jax.random.key(1), x.shape)
  np.testing.assert_array_equal(jax.jit(lambda c: jax.vjp(encodings.materialized, x)[1](c)[0])(cotangent), cotangent)
  rows = np.array(jax.random.randint(jax.random.key(7), (4096, 8), 0, 2**31 - 1, dtype=jnp.int32))
  rows[0] = 2**31 - 1
  rows = jnp.asarray(rows)
  kept_rows = jax.jit(encodings.materialized)(rows)
  assert kept_rows.dtype == jnp.int32
  np.testing.assert_array_equal(kept_rows, rows)

  origins = jax.random.normal(jax.random.key(2), (256, 3))
  directions = jax.random.normal(jax.random.key(3), (256, 3))
  t = jax.random.uniform(jax.random.key(4), (256, 16), minval=0.5, maxval=2.5)
  def field_of(materialize):
    return fields.HashGridField(bound=1.5, num_levels=6, features_per_level=2, log2_table_size=12,
                                base_resolution=4, max_resolution=128, hidden_width=16, geo_features=7,
                                use_viewdirs=True, dtype=jnp.float32, materialize=materialize)
  points = lambda: (origins[:, None] + t[..., None] * directions[:, None]).reshape(-1, 3)
  viewdirs = jax.jit(lambda d: jnp.repeat(d / jnp.linalg.norm(d, axis=-1, keepdims=True), 16, axis=0))(directions)
  params = jax.jit(lambda key: field_of(False).init(key, points(), viewdirs))(jax.random.key(5))
  params = jax.jit(lambda ps: jax.tree.map(lambda p: p + 0.3 * jax.random.normal(jax.random.key(6), p.shape),
                                           ps))(params)  # tables too
  def loss(materialize):
    def f(p):
      rgb, sigma = field_of(materialize).apply(p, points(), viewdirs)
      return jnp.sum(rgb * rgb) + jnp.sum(jnp.log1p(sigma)), (rgb, sigma)
    return jax.jit(jax.value_and_grad(f, has_aux=True), compiler_options=procs.OPTIMIZED_KERNELS)(params)
  (plain, (rgb, sigma)), grads = loss(False)
  (kept, (rgb_kept, sigma_kept)), grads_kept = loss(True)
  assert np.abs(np.asarray(sigma)).max() > 0 and np.abs(np.asarray(grads["params"]["grid"]["level_5"])).max() > 0
  np.testing.assert_array_equal(kept, plain)
  np.testing.assert_array_equal(rgb_kept, rgb)
  np.testing.assert_array_equal(sigma_kept, sigma)
  jax.tree.map(np.testing.assert_array_equal, grads_kept, grads)
  ops = str(jax.make_jaxpr(lambda p: field_of(True).apply(p, points(), viewdirs))(params))
  plain_ops = str(jax.make_jaxpr(lambda p: field_of(False).apply(p, points(), viewdirs))(params))
  # one matmul keeps the points for all six levels, one per level its corners' rows
  assert ops.count("dot_general") == plain_ops.count("dot_general") + 1 + 6
  assert ops.count("PROMISE_IN_BOUNDS") == 6 and "PROMISE_IN_BOUNDS" not in plain_ops
