"""The NeRF renderer: hierarchical sampling, view directions, fields, mixed precision."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import procs
from conftest import smoke_config
from nerfpod.nerf import fields
from nerfpod.nerf import model as nerf_model
from nerfpod.run import components


def _rays(n=64, seed=0):
  rng = np.random.default_rng(seed)
  eye = rng.normal(size=(n, 3))
  eye = 4.0 * eye / np.linalg.norm(eye, axis=-1, keepdims=True)
  directions = -eye + 0.3 * rng.normal(size=(n, 3))
  return jnp.asarray(eye, jnp.float32), jnp.asarray(directions, jnp.float32)


def _mlp_field(**sizes):
  """An MLPField sized like the smoke config's MLP, with `sizes` overriding."""
  attributes = dict(smoke_config().model.mlp, use_viewdirs=False, dtype=jnp.float32)
  attributes.update(sizes)
  return fields.MLPField(**attributes)


def _hierarchical_model(field="mlp", dtype="float32", importance=24):
  return components.make_model(smoke_config(**{
      "model.field": field, "model.mlp.depth": 3, "model.mlp.width": 32, "model.mlp.skips": (1,),
      "model.use_viewdirs": True, "render.num_samples": 16, "render.num_importance": importance,
      "model.compute_dtype": dtype, "render.proposal_samples": ()}))


@functools.cache  # (read only, as _proposal_model)
def _hierarchical(field="mlp", dtype="float32", importance=24):
  model = _hierarchical_model(field, dtype, importance)
  origins, directions = _rays()
  params = jax.jit(model.init, static_argnums=(3, 4))(jax.random.key(0), origins, directions, 2.0, 6.0,
                                                      jnp.ones(3))
  return model, params, origins, directions


_JITTED = {}  # id(model) -> (model, its jitted apply): one trace and program per model and shapes in a worker


def _apply(model, *args):
  """model.apply, jitted (the near/far bounds are static floats)."""
  if id(model) not in _JITTED:
    _JITTED[id(model)] = model, jax.jit(model.apply, static_argnums=(3, 4))
  return _JITTED[id(model)][1](*args)


def test_hierarchical_sampling_renders_coarse_and_fine_with_union_of_samples():
  model, params, origins, directions = _hierarchical()
  assert set(params["params"]) == {"coarse", "fine"}
  u_c = jax.random.uniform(jax.random.key(1), (64, 16))
  u_f = jax.random.uniform(jax.random.key(2), (64, 24))
  coarse, fine = _apply(model, params, origins, directions, 2.0, 6.0, jnp.ones(3), u_c, u_f)
  assert coarse["t"].shape == (64, 16) and fine["t"].shape == (64, 40)
  assert (np.diff(np.asarray(fine["t"]), axis=-1) >= 0).all()
  # The fine set contains every coarse sample.
  coarse_t, fine_t = np.asarray(coarse["t"]), np.asarray(fine["t"])  # (rows read on the host: no program each)
  for ray in range(4):
    assert np.isin(coarse_t[ray], fine_t[ray]).all()
  for out in (coarse, fine):
    assert out["rgb"].shape == (64, 3) and out["depth"].shape == (64,)


def test_fine_loss_sends_no_gradient_to_the_coarse_network_through_sample_positions():
  model, params, origins, directions = _hierarchical()
  u_c = jax.random.uniform(jax.random.key(1), (64, 16))
  u_f = jax.random.uniform(jax.random.key(2), (64, 24))

  def fine_rgb_sum(p):
    return jnp.sum(model.apply(p, origins, directions, 2.0, 6.0, jnp.ones(3), u_c, u_f)[-1]["rgb"])

  grads = jax.jit(jax.grad(fine_rgb_sum))(params)["params"]
  assert all(np.all(np.asarray(g) == 0) for g in jax.tree.leaves(grads["coarse"]))
  assert any(np.any(np.asarray(g) != 0) for g in jax.tree.leaves(grads["fine"]))


def test_view_directions_change_colour_but_not_density():
  field = _mlp_field(depth=3, width=32, skips=(1,), use_viewdirs=True)
  dirs_a = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (10, 1))
  dirs_b = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (10, 1))

  # One program rather than one per operation, its bits from optimised kernels (procs.OPTIMIZED_KERNELS), as in
  # every claim that two computations give the same bits.
  @functools.partial(jax.jit, compiler_options=procs.OPTIMIZED_KERNELS)
  def run(dirs_a, dirs_b):
    points = jax.random.normal(jax.random.key(0), (10, 3))
    params = field.init(jax.random.key(1), points, dirs_a)
    return field.apply(params, points, dirs_a), field.apply(params, points, dirs_b)

  (rgb_a, sigma_a), (rgb_b, sigma_b) = jax.tree.map(np.asarray, run(dirs_a, dirs_b))
  np.testing.assert_array_equal(sigma_a, sigma_b)
  assert not np.allclose(rgb_a, rgb_b)


def test_tutorial_mlp_has_the_tutorial_shapes():
  field = _mlp_field(depth=8, width=256, skips=(4,), num_frequencies=6)
  params = jax.eval_shape(field.init, jax.random.key(0), jnp.zeros((1, 3)))["params"]
  assert params["trunk_0"]["kernel"].shape == (39, 256)
  assert params["trunk_5"]["kernel"].shape == (256 + 39, 256)  # input rejoins after layer 4
  assert params["trunk_4"]["kernel"].shape == (256, 256)
  assert params["output"]["kernel"].shape == (256, 4)
  assert len([k for k in params if k.startswith("trunk_")]) == 8


@pytest.mark.parametrize("field", ["mlp", "hashgrid"])
def test_bfloat16_matmuls_keep_float32_parameters_and_close_outputs(field):
  model32, params, origins, directions = _hierarchical(field, "float32", importance=0)
  model16 = _hierarchical_model(field, "bfloat16", importance=0)  # (model32's parameters: no init of its own)
  assert all(p.dtype == jnp.float32 for p in jax.tree.leaves(params))
  out32 = _apply(model32, params, origins, directions, 2.0, 6.0, jnp.ones(3))[-1]

  @jax.jit  # the bfloat16 model's output and gradients: one program
  def run16(p):
    rgb = lambda p: model16.apply(p, origins, directions, 2.0, 6.0, jnp.ones(3))[-1]["rgb"]  # noqa: E731
    return rgb(p), jax.grad(lambda p: jnp.sum(rgb(p)))(p)
  rgb16, grads = run16(params)
  assert rgb16.dtype == jnp.float32
  np.testing.assert_allclose(rgb16, out32["rgb"], atol=0.05)
  assert all(g.dtype == jnp.float32 for g in jax.tree.leaves(grads))


@functools.cache  # (read only: the tests share the model, its parameters and its programs)
def _proposal_model(field="hashgrid", proposal_samples=(12, 8), num_samples=6):
  config = smoke_config(**{"model.field": field, "model.mlp.depth": 2, "model.mlp.width": 16,
                           "model.mlp.skips": (), "model.use_viewdirs": True,
                           "render.num_samples": num_samples, "render.proposal_samples": proposal_samples})
  model = components.make_model(config)
  origins, directions = _rays(32)
  # Unit directions (one program): near 2 .. far 6 crosses the box.
  directions = jax.jit(lambda d: d / jnp.linalg.norm(d, axis=-1, keepdims=True))(directions)
  params = jax.jit(model.init, static_argnums=(3, 4))(jax.random.key(0), origins, directions, 2.0, 6.0,
                                                      jnp.ones(3))
  return model, params, origins, directions


def _uniforms(model, rays=32, seed=5):
  return [jax.random.uniform(jax.random.key(seed + i), (rays, n)) for i, n in enumerate(model.sample_counts())]


@pytest.mark.parametrize("field", ["mlp", "hashgrid"])
def test_proposal_rounds_feed_the_field_few_intervals_inside_the_ray(field):
  model, params, origins, directions = _proposal_model(field)
  assert model.sample_counts() == (12, 8, 6)
  assert set(params["params"]) == {"proposal_0", "proposal_1", "coarse"}
  for uniforms in (_uniforms(model), []):  # training (jittered) and evaluation (deterministic)
    (out,) = _apply(model, params, origins, directions, 2.0, 6.0, jnp.ones(3), *uniforms)
    assert out["rgb"].shape == (32, 3) and out["weights"].shape == (32, 6) and out["t"].shape == (32, 6)
    assert out["s_edges"].shape == (32, 7)
    assert [p["s_edges"].shape for p in out["proposals"]] == [(32, 13), (32, 9)]
    assert [p["weights"].shape for p in out["proposals"]] == [(32, 12), (32, 8)]
    s = np.asarray(out["s_edges"])
    assert (np.diff(s, axis=-1) >= 0).all() and (s >= 0).all() and (s <= 1).all()
    t = np.asarray(out["t"])
    assert (t >= 2.0 - 1e-5).all() and (t <= 6.0 + 1e-5).all()  # inside [near, far] (and the box)
    weights = np.asarray(out["weights"])
    np.testing.assert_allclose(weights.sum(-1), out["acc"], rtol=1e-5, atol=1e-6)
    assert (weights.sum(-1) > 0.01).mean() > 0.5  # most rays cross density


def test_photometric_loss_reaches_only_the_nerf_and_interlevel_loss_only_the_proposals():
  from nerfpod.nerf import stepfun
  model, params, origins, directions = _proposal_model()
  uniforms = _uniforms(model)
  run = lambda p: model.apply(p, origins, directions, 2.0, 6.0, jnp.ones(3), *uniforms)[-1]

  def photometric(p):
    return jnp.sum(run(p)["rgb"])

  def interlevel(p):
    out = run(p)
    target = jax.lax.stop_gradient(out["weights"])
    return sum(jnp.sum(stepfun.interlevel_loss(out["s_edges"], target, q["s_edges"], q["weights"]))
               for q in out["proposals"])

  nonzero = lambda tree: any(np.any(np.asarray(g) != 0) for g in jax.tree.leaves(tree))
  both = jax.jit(lambda p: (jax.grad(photometric)(p)["params"], jax.grad(interlevel)(p)["params"]))  # one program
  grads, grads_interlevel = both(params)
  assert nonzero(grads["coarse"])
  assert not nonzero(grads["proposal_0"]) and not nonzero(grads["proposal_1"])  # positions carry none
  assert not nonzero(grads_interlevel["coarse"])
  assert nonzero(grads_interlevel["proposal_0"]) and nonzero(grads_interlevel["proposal_1"])


def test_near_gradient_scaling_leaves_outputs_and_scales_their_gradients_by_squared_distance():
  rng = np.random.default_rng(0)
  # (NumPy float32 inputs, as jnp.asarray made them: no program each.)
  rgb, sigma = rng.uniform(size=(4, 5, 3)).astype(np.float32), rng.uniform(size=(4, 5)).astype(np.float32)
  t = np.sort(rng.uniform(0.1, 3.0, size=(4, 5)), -1).astype(np.float32)
  directions = rng.normal(size=(4, 3)).astype(np.float32)  # not unit: the distance is t |d|

  @jax.jit  # one program rather than one per operation
  def run(rgb, sigma, t, directions):
    outs, vjp = jax.vjp(lambda a, b: nerf_model.near_gradients(a, b, t, directions, 2.0), rgb, sigma)
    return outs, vjp((jnp.ones_like(rgb), jnp.ones_like(sigma)))

  (out_rgb, out_sigma), (grad_rgb, grad_sigma) = run(rgb, sigma, t, directions)
  np.testing.assert_array_equal(out_rgb, rgb)
  np.testing.assert_array_equal(out_sigma, sigma)
  want = np.minimum(1.0, (t * np.linalg.norm(directions, axis=-1, keepdims=True) / 2.0) ** 2)
  assert 0.0 < want.min() < 0.1 and want.max() == 1.0
  np.testing.assert_allclose(grad_sigma, want, rtol=1e-6)
  np.testing.assert_allclose(grad_rgb, np.broadcast_to(want[..., None], rgb.shape), rtol=1e-6)
  off = nerf_model.near_gradients(rgb, sigma, t, directions, 0.0)  # 0: the very arrays, nothing added
  assert off[0] is rgb and off[1] is sigma


def test_near_gradient_scaling_renders_the_same_and_only_the_nerf_fields_gradients_change():
  model, params, origins, directions = _proposal_model()
  scaled = model.clone(near_gradient_distance=8.0)  # every sample (2 to 6 from its origin) is scaled
  uniforms = _uniforms(model)

  def rendered_and_grads(m):  # one program per model: its rendering and the gradients of its colours' sum
    def rgb_sum(p):
      out = m.apply(p, origins, directions, 2.0, 6.0, jnp.ones(3), *uniforms)[-1]
      return jnp.sum(out["rgb"]), out
    (_, out), grads = jax.jit(jax.value_and_grad(rgb_sum, has_aux=True))(params)
    return out, grads["params"]
  (out_plain, grads_plain), (out_near, grads_near) = rendered_and_grads(model), rendered_and_grads(scaled)
  for key in ("rgb", "depth", "acc", "weights"):
    np.testing.assert_array_equal(out_plain[key], out_near[key])
  plain, near = (np.concatenate([np.ravel(g) for g in jax.tree.leaves(g["coarse"])]) for g in (grads_plain, grads_near))
  assert np.abs(near).sum() < 0.6 * np.abs(plain).sum()  # scaled by (t / 8)^2 <= 0.56
