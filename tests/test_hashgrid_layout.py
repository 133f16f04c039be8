"""The hash grid's lane-dense layout (compile.hashgrid_layout='lane_dense'): the same values and gradients as
the rows layout's lookup (encodings.level_gather, dense_level_matmul), the same parameters (a checkpoint
restores under either layout), and (slow, libtpu) a compiled TPU step without narrow arrays."""
import importlib.util
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import procs
from conftest import smoke_config
from nerfpod.nerf import encodings
from nerfpod.run import components

HAS_LIBTPU = importlib.util.find_spec("libtpu") is not None


def _points(n=2000, seed=0):
  """Random points in the unit cube, with grid vertices, faces and the cube's corners among them."""
  x = np.array(jax.random.uniform(jax.random.key(seed), (n, 3)))
  x[:8] = [[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
  x[8:16] = np.round(x[8:16] * 12) / 12  # vertices of a 12-cell grid
  return jnp.asarray(x, jnp.float32)


def _table(rows, features=2, seed=1):
  return jax.random.normal(jax.random.key(seed), (rows, features))


# (resolution, table rows): a dense level (one row per vertex) and a hashed one (far more vertices than rows).
LEVELS = {"dense": (12, 13**3), "hashed": (40, 2**10)}


@pytest.mark.parametrize("materialize", [False, True], ids=["take", "materialized"])
@pytest.mark.parametrize("level", LEVELS)
def test_lane_dense_gather_gives_level_gathers_values_bit_for_bit(level, materialize):
  """Op by op and compiled (jit fuses the weighted sum, in the same order for both)."""
  res, rows = LEVELS[level]
  table, x = _table(rows), _points()
  want = encodings.level_gather(table, x, res, materialize)
  got = encodings.level_gather_lane_dense(table, x.T, res, materialize)
  assert got.shape == (2, len(x))
  np.testing.assert_array_equal(np.asarray(got).T, want)
  want = jax.jit(lambda t, p: encodings.level_gather(t, p, res, materialize))(table, x)
  got = jax.jit(lambda t, p: encodings.level_gather_lane_dense(t, p.T, res, materialize).T)(table, x)
  np.testing.assert_array_equal(got, want)


def test_lane_dense_corners_and_weights_are_the_rows_layouts_transposed():
  x = _points()
  corners, weights = encodings.trilinear_corners_and_weights(x, 12)
  corners_ld, weights_ld = encodings.trilinear_corners_and_weights_lane_dense(x.T, 12)
  np.testing.assert_array_equal(np.transpose(corners_ld, (2, 1, 0)), corners)
  np.testing.assert_array_equal(np.asarray(weights_ld).T, weights)


@pytest.mark.parametrize("level", LEVELS)
def test_lane_dense_gather_gradients_equal_level_gathers(level):
  """Gradients with respect to the table and to the points, through a random linear read-out. The table's is
  the same scatter-add of the same products, accumulated in another order where corners share a row (the rows
  layout adds point by point, each point's 8 corners in turn; the lane-dense one corner by corner, all
  points in turn): float32 sums in another order, equal to a few units in the last place. The points' are
  exact."""
  res, rows = LEVELS[level]
  table, x = _table(rows), _points()
  readout = jax.random.normal(jax.random.key(2), (len(x), 2))

  def rows_loss(t, p):
    return jnp.sum(encodings.level_gather(t, p, res) * readout)

  def lane_dense_loss(t, p):
    return jnp.sum(encodings.level_gather_lane_dense(t, p.T, res).T * readout)

  # One program rather than one per operation; optimised kernels, as for every bit-for-bit claim between two
  # computations (procs.OPTIMIZED_KERNELS).
  grads = jax.jit(lambda t, p: (jax.grad(rows_loss, argnums=(0, 1))(t, p),
                                jax.grad(lane_dense_loss, argnums=(0, 1))(t, p)),
                  compiler_options=procs.OPTIMIZED_KERNELS)
  (want_t, want_x), (got_t, got_x) = grads(table, x)
  np.testing.assert_allclose(got_t, want_t, rtol=0, atol=1e-6 * float(np.abs(want_t).max()))  # (4.8e-7 of 3.5)
  np.testing.assert_array_equal(got_x, want_x)  # per point: the same products summed in the same order


def test_lane_dense_matmul_lookup_equals_the_gather_values_and_gradients():
  res, rows = LEVELS["dense"]
  table, x = _table(rows), _points(500)
  readout = jax.random.normal(jax.random.key(2), (len(x), 2))

  @jax.jit  # one program rather than one per operation
  def run(table, x):
    grads = lambda f: jax.grad(lambda t, p: jnp.sum(f(t, p) * readout), argnums=(0, 1))(table, x)  # noqa: E731
    return (encodings.level_gather(table, x, res), encodings.dense_level_matmul_lane_dense(table, x.T, res),
            encodings.dense_level_matmul(table, x, res), grads(lambda t, p: encodings.level_gather(t, p, res)),
            grads(lambda t, p: encodings.dense_level_matmul_lane_dense(t, p.T, res).T))

  want, got, rows_matmul, (want_t, want_x), (got_t, got_x) = run(table, x)
  np.testing.assert_allclose(np.asarray(got).T, want, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(got, rows_matmul.T, rtol=1e-6, atol=1e-7)
  np.testing.assert_allclose(got_t, want_t, rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(got_x, want_x, rtol=1e-4, atol=1e-4)


def _encoding(layout, matmul_max_rows=0, materialize=False):
  return encodings.HashGridEncoding(num_levels=4, features_per_level=2, log2_table_size=10, base_resolution=4,
                                    max_resolution=40, matmul_max_rows=matmul_max_rows, materialize=materialize,
                                    layout=layout)


@pytest.mark.parametrize("matmul_max_rows,materialize", [(0, False), (0, True), (10**6, False)],
                         ids=["gather", "materialized", "matmul"])
def test_the_encoding_has_the_same_parameters_and_features_in_either_layout(matmul_max_rows, materialize):
  x = _points()
  rows, lane_dense = _encoding("rows", matmul_max_rows, materialize), _encoding("lane_dense", matmul_max_rows,
                                                                                materialize)
  # One program for both initialisations and one for both encodings rather than one per operation; the
  # features' bits from optimised kernels (procs.OPTIMIZED_KERNELS), as in every bit-for-bit claim between two
  # computations.
  params, lane_dense_params = jax.jit(lambda key, x: (rows.init(key, x), lane_dense.init(key, x)))(
      jax.random.key(0), x)
  assert jax.tree.map(jnp.shape, lane_dense_params) == jax.tree.map(jnp.shape, params)
  for a, b in zip(jax.tree.leaves(lane_dense_params), jax.tree.leaves(params)):
    np.testing.assert_array_equal(a, b)
  params = jax.tree.map(lambda p: jax.random.normal(jax.random.key(3), p.shape), params)
  scales, opened = jnp.asarray(np.linspace(0.0, 0.05, len(x)), jnp.float32), jnp.array([1.0, 0.7, 0.2, 0.0])
  want, got = jax.jit(lambda *args: (rows.apply(*args), lane_dense.apply(*args)),
                      compiler_options=procs.OPTIMIZED_KERNELS)(params, x, scales, opened)
  if matmul_max_rows:  # matmuls of other shapes: the same sums, perhaps in another order
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
  else:
    np.testing.assert_array_equal(got, want)


def test_an_unknown_layout_is_refused():
  with pytest.raises(ValueError, match="unknown hash-grid layout 'columns'"):
    _encoding("columns").init(jax.random.key(0), _points(16))


def _model(layout):
  config = smoke_config(**{"compile.hashgrid_layout": layout})
  return components.make_model(config, backend="cpu")


def test_the_model_renders_the_same_in_either_layout_and_each_restores_the_others_parameters():
  """A checkpoint holds the parameters, which are the same arrays in either layout (and a workdir may change
  compile.* on resuming): a model of one layout renders the other's parameters as that one does (the smoke
  config: proposal fields and the NeRF field)."""
  from nerfpod.workdir import files as workdir_files
  saved, now = (json.loads(smoke_config(**{"compile.hashgrid_layout": layout}).to_json_best_effort())
                for layout in ("rows", "lane_dense"))
  assert workdir_files.incompatible_fields(saved, now) == []
  rows, lane_dense = _model("rows"), _model("lane_dense")
  assert (rows.grid_layout, lane_dense.grid_layout) == ("rows", "lane_dense")
  rng = np.random.default_rng(0)
  eye = rng.normal(size=(32, 3))
  eye = 4.0 * eye / np.linalg.norm(eye, axis=-1, keepdims=True)
  origins, directions = jnp.asarray(eye, jnp.float32), jnp.asarray(-eye + 0.3 * rng.normal(size=(32, 3)), jnp.float32)
  init = lambda model: jax.jit(model.init, static_argnums=(3, 4))(  # noqa: E731
      jax.random.key(0), origins, directions, 2.0, 6.0, jnp.ones(3))
  params = init(rows)
  assert jax.tree.map(jnp.shape, init(lane_dense)) == jax.tree.map(jnp.shape, params)
  apply = lambda model: jax.jit(model.apply, static_argnums=(3, 4))(  # noqa: E731
      params, origins, directions, 2.0, 6.0, jnp.ones(3))
  want, got = apply(rows), apply(lane_dense)
  assert jax.tree.structure(got) == jax.tree.structure(want)
  for w, g in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
    np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)


def test_a_checkpoint_of_one_layout_restores_under_the_other(tmp_path):
  """Through the checkpoints' own save and read-only restore: the rows model's parameters, restored onto the
  lane-dense model's parameter shapes (no differing leaf to refuse), render under it as under rows."""
  from nerfpod.workdir import checkpoints
  rows, lane_dense = _model("rows"), _model("lane_dense")
  # (NumPy inputs: no program each to build them.)
  x, dirs = np.full((4, 3), 0.1, np.float32), np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (4, 1))
  background = np.ones(3, np.float32)
  init = lambda model: jax.jit(model.init, static_argnums=(3, 4))(  # noqa: E731
      jax.random.key(0), x, dirs, 2.0, 6.0, background)
  perturb = jax.jit(lambda ps: jax.tree.map(lambda p: p + 0.01 * jax.random.normal(jax.random.key(7), p.shape), ps))
  params = perturb(init(rows))  # (jitted: one program rather than one per operation and leaf)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=1, max_to_keep=1) as ckpt:
    ckpt.save(1, {"params": params}, {"next_step": 1})
  abstract = {"params": jax.tree.map(lambda p: jax.ShapeDtypeStruct(p.shape, p.dtype, sharding=p.sharding),
                                     init(lane_dense))}
  step, restored = checkpoints.restore_newest(str(tmp_path), abstract)
  assert step == 1
  render = lambda model, p: jax.jit(model.apply, static_argnums=(3, 4))(p, x, dirs, 2.0, 6.0, background)  # noqa: E731
  for w, g in zip(jax.tree.leaves(render(rows, params)), jax.tree.leaves(render(lane_dense, restored["params"]))):
    np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)


# A step's slice of HLO as the TPU compiler writes it: a table sliced into VMEM piece by piece, a gather's
# row-major (F minor) result, and its lane-dense twin.
_HLO = """HloModule m

ENTRY %main (t: f32[524288,2]) -> f32[131072,2] {
  %t = f32[524288,2]{0,1:T(2,128)} parameter(0)
  %s = ((f32[524288,2]{0,1:T(2,128)}), f32[131072,2]{0,1:T(2,128)S(1)}, s32[]{:S(2)}) slice-start(%t), slice={[0:131072], [0:2]}
  %d = f32[131072,2]{0,1:T(2,128)S(1)} slice-done(%s)
  %narrow = f32[65536,8,2]{1,0,2:T(8,128)} copy(%t), metadata={op_name="jit(step)/grid/gather"}
  %small = f32[64,8]{1,0:T(8,128)} copy(%t)
  ROOT %dense = f32[131072,2]{0,1:T(2,128)} copy(%d)
}
"""


def test_narrow_arrays_are_those_whose_minor_dimension_fills_few_of_a_tiles_lanes():
  from tools import hlo_layout
  found = hlo_layout.narrow_arrays(_HLO, min_bytes=1 << 20)
  assert [(n.instruction, n.array, n.bytes, n.padding, n.source) for n in found] == [
      ("narrow", "f32[65536,8,2]{1,0,2:T(8,128)}", 2 * 65536 * 128 * 4, 16.0, "jit(step)/grid/gather")]
  assert [n.instruction for n in hlo_layout.narrow_arrays(_HLO, min_bytes=0)] == ["narrow", "small"]


def test_an_asynchronous_slice_moves_its_slice_not_its_whole_source():
  """slice-start's result tuple names its whole source: only the slice is read (from HBM) and written (into
  VMEM here), and its slice-done is free."""
  from nerfpod.pod import chips, hlo_cost
  chip = chips.CHIPS["v5e"]
  program = hlo_cost.HloProgram(_HLO, chip, 1)
  start, done = (next(i for i in program.computations[program.entry] if i.name == n) for n in ("s", "d"))
  piece = 131072 * 2 * 4
  cost = program._instruction(program.entry, start)  # noqa: SLF001
  assert (cost.bytes, cost.vmem_bytes) == (piece, piece)
  assert program._instruction(program.entry, done).seconds == 0  # noqa: SLF001


def _field_step_hlo(layout: str) -> str:
  """A hash-grid field's forward and gradient (blender_fast's field with 3 of its levels: the coarsest dense and
  read by matmuls, two hashed into its 2^19 rows) on 16,384 points, compiled for one TPU v5e chip."""
  from nerfpod.pod import aot, chips
  aot._quiet_libtpu()  # noqa: SLF001
  from nerfpod.nerf import fields
  from conftest import load_config
  config = load_config("blender_fast", "scene=lego")
  grid = config.model.hashgrid
  grid.num_levels = 3
  devices = aot.topology_devices(chips.lookup("v5e-4"))
  one = jax.sharding.NamedSharding(jax.sharding.Mesh(np.array(devices[:1]), ("x",)), jax.sharding.PartitionSpec())
  field = fields.make_field(config.model, jnp.float32, matmul_max_rows=30000, layout=layout)
  points = jax.ShapeDtypeStruct((16384, 3), jnp.float32, sharding=one)
  params = jax.eval_shape(field.init, jax.random.key(0), jnp.zeros((1, 3)), jnp.zeros((1, 3)))
  params = jax.tree.map(lambda p: jax.ShapeDtypeStruct(p.shape, p.dtype, sharding=one), params)

  def loss(p, x):
    rgb, sigma = field.apply(p, x, x)
    return jnp.sum(rgb) + jnp.sum(sigma)
  return jax.jit(jax.value_and_grad(loss)).lower(params, points).compile().as_text()


@pytest.mark.slow
@pytest.mark.skipif(not HAS_LIBTPU, reason="libtpu is not installed (pip install -e '.[tpu]')")
def test_on_a_tpu_the_lane_dense_lookup_leaves_no_large_array_narrow():
  """The compiled TPU program (v5e): with the rows layout XLA keeps the (N, 8) rows and weights and the
  (N, 8, 2) corner values with 8 or 2 values in each 128-lane tile row; with the lane-dense one no array of
  1 MiB or more does. (Tables small enough for XLA to keep whole in VMEM, as blender_fast's two gathered dense
  levels of 79,507 and 205,379 rows, are gathered row-major in either layout: docs/pod-compile.md.)"""
  from tools import hlo_layout
  rows = hlo_layout.narrow_arrays(_field_step_hlo("rows"), min_bytes=1 << 20)
  assert any("8,2]" in n.array for n in rows) and any(",8]" in n.array for n in rows), rows
  assert hlo_layout.narrow_arrays(_field_step_hlo("lane_dense"), min_bytes=1 << 20) == []
