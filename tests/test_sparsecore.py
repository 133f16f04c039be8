"""The SparseCore hash-grid lookup (compile.hashgrid_lookup='sparsecore', nerf/sparsecore.py): its custom_vjp
gives level_gather's values and gradients; the option is refused in one sentence where it cannot run (a CPU or
GPU run, a pod without SparseCores) and never picked by 'auto'.

The kernels themselves cannot run on a CPU in JAX 0.10.2, not even in Pallas's interpret mode (the two tests
marked xfail record how each interpreter fails; they pass, and must then be un-marked, once it can): here the
custom_vjp around them is tested with each kernel replaced by the jnp expression it computes. The kernels are
compiled for v5p and v6e by `nerfpod aot` (docs/pod-compile.md, "A SparseCore lookup")."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod import schema
from nerfpod.nerf import encodings, sparsecore
from nerfpod.run import components


def _points(n=2000, seed=0):
  """Random points in the unit cube, with the cube's corners and grid vertices among them."""
  x = np.array(jax.random.uniform(jax.random.key(seed), (n, 3)))
  x[:8] = [[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
  x[8:16] = np.round(x[8:16] * 12) / 12
  return jnp.asarray(x, jnp.float32)


def _table(rows, features=2, seed=1):
  return jax.random.normal(jax.random.key(seed), (rows, features))


# (resolution, table rows): a dense level and a hashed one (many corners share each row: repeated indices).
LEVELS = {"dense": (12, 13**3), "hashed": (40, 2**10)}


@pytest.mark.parametrize("level", LEVELS)
def test_the_custom_vjp_gives_level_gathers_values_and_gradients(level):
  """Values bit for bit (the same rows, weighted and summed alike); the gradients with respect to the points
  bit for bit (they flow through the weights only), the table's to float32 rounding (one scatter-add of the
  (8 N, F) cotangents instead of jnp.take's transpose: where corners share a row, another order of the sum)."""
  res, rows = LEVELS[level]
  table, x = _table(rows), _points()
  cotangent = jax.random.normal(jax.random.key(2), (len(x), 2))

  def loss(lookup):
    return lambda t, p: jnp.sum(lookup(t, p) * cotangent)
  ours = lambda t, p: encodings.level_gather_sparsecore(t, p, res, reference=True)  # noqa: E731
  theirs = lambda t, p: encodings.level_gather(t, p, res)  # noqa: E731
  np.testing.assert_array_equal(jax.jit(ours)(table, x), jax.jit(theirs)(table, x))
  g_ours = jax.jit(jax.grad(loss(ours), argnums=(0, 1)))(table, x)
  g_theirs = jax.jit(jax.grad(loss(theirs), argnums=(0, 1)))(table, x)
  np.testing.assert_allclose(g_ours[0], g_theirs[0], rtol=1e-6, atol=1e-6)
  np.testing.assert_array_equal(g_ours[1], g_theirs[1])
  assert float(jnp.abs(g_ours[0]).sum()) > 0


def test_the_take_is_jnp_take_and_its_gradient_a_scatter_add_into_zeros():
  table = _table(37)
  rows = jnp.asarray([[0, 5, 36, 5], [7, 7, 7, 0]], jnp.int32)  # repeated rows add up
  take = jax.jit(lambda t, r: sparsecore.sparsecore_take(t, r, reference=True))  # one program, not one per op
  np.testing.assert_array_equal(take(table, rows), np.asarray(table)[np.asarray(rows)])
  cot = jax.random.normal(jax.random.key(3), (2, 4, 2))
  grad = jax.jit(jax.grad(lambda t: jnp.sum(take(t, rows) * cot)))(table)
  expected = np.zeros((37, 2), np.float32)
  np.add.at(expected, np.asarray(rows).reshape(-1), np.asarray(cot).reshape(-1, 2))
  np.testing.assert_allclose(grad, expected, rtol=1e-6)


@pytest.mark.parametrize("layout", encodings.LAYOUTS)
def test_the_encoding_with_the_sparsecore_lookup_equals_the_gather_one(layout, monkeypatch):
  """HashGridEncoding(lookup='sparsecore') reads every level that is not a matmul through sparsecore_take
  (here with the kernels swapped for their jnp expressions): the same parameters, features and gradients."""
  monkeypatch.setattr(sparsecore, "_gather_kernel", lambda t, r: sparsecore._gather_reference(t, r))
  monkeypatch.setattr(sparsecore, "_scatter_add_kernel", sparsecore._scatter_add_reference)
  x = _points(500)
  make = lambda lookup: encodings.HashGridEncoding(4, 2, 10, 4, 40, matmul_max_rows=200, layout=layout,  # noqa: E731
                                                   lookup=lookup)
  params = jax.jit(make("gather").init)(jax.random.key(0), x)  # one program, not one per operation
  assert jax.tree.map(jnp.shape, jax.eval_shape(make("sparsecore").init, jax.random.key(0), x)) == \
      jax.tree.map(jnp.shape, params)
  f_gather, f_sc = (jax.jit(make(k).apply)(params, x) for k in ("gather", "sparsecore"))
  np.testing.assert_allclose(f_sc, f_gather, rtol=1e-6, atol=1e-7)
  grads = [jax.jit(jax.grad(lambda p, k=k: jnp.sum(make(k).apply(p, x) ** 2)))(params)
           for k in ("gather", "sparsecore")]
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7), *grads)


def test_an_unknown_lookup_is_refused():
  with pytest.raises(ValueError, match="unknown hash-grid lookup 'nope'"):
    encodings.HashGridEncoding(2, 2, 8, 4, 8, lookup="nope").init(jax.random.key(0), _points(8))


def test_the_kernels_split_every_row_number_over_the_subcores_in_chunks_of_8():
  for count in (1, 7, 8, 255, 3072, 98_304, 196_608, 1_000_003):
    for workers in (32, 64):
      chunk, steps = sparsecore._split(count, workers)  # noqa: SLF001
      assert chunk % 8 == 0 and 0 < chunk <= sparsecore.MAX_CHUNK
      assert chunk * steps * workers >= count
      assert chunk * steps * workers - count < workers * (8 * steps + 1)  # at most 8 a chunk and 1 a subcore


# --- where it runs: the schema's refusals ---------------------------------------------------------------------


def test_the_schema_accepts_sparsecore_and_refuses_it_on_a_cpu_or_gpu_run_in_one_sentence():
  config = smoke_config(**{"compile.hashgrid_lookup": "sparsecore"})
  assert schema.problems(config) == []  # the field alone is valid (a workdir's config, a pod's)
  for backend in ("cpu", "gpu"):
    found = schema.problems(config, 1, backend=backend)
    assert found == [f"compile.hashgrid_lookup=sparsecore runs the hash grid's lookups on the SparseCores of TPU "
                     f"v5p and v6e, and this run's backend is {backend}; use "
                     f"--config.compile.hashgrid_lookup=auto."]
  assert schema.problems(config, 1) == schema.problems(config, 1, backend=jax.default_backend())
  with pytest.raises(schema.ConfigError, match="this run's backend is cpu"):
    components.make_model(config, backend="cpu")


@pytest.mark.parametrize("generation, pod", [("v5e", "v5litepod-8"), ("v4", "v4-8")])
def test_the_schema_refuses_sparsecore_for_a_pod_without_sparsecores(generation, pod):
  config = smoke_config(**{"compile.hashgrid_lookup": "sparsecore", "train.batch_size": 64})
  assert schema.problems(config, 8, backend="tpu", tpu_generation=generation, pod=pod) == [
      f"compile.hashgrid_lookup=sparsecore runs the hash grid's lookups on the SparseCores of TPU v5p and v6e, "
      f"and {pod} ({generation}) has none that Pallas reaches; use --config.compile.hashgrid_lookup=auto, or "
      f"compile for a v5p or v6e pod."]
  for generation in ("v5p", "v6e"):
    assert schema.problems(config, 8, backend="tpu", tpu_generation=generation, pod="x") == []


def test_auto_never_picks_sparsecore_and_sparsecore_keeps_the_matmul_levels():
  for backend in ("cpu", "gpu", "tpu"):
    assert components.make_model(smoke_config(), backend=backend).grid_lookup == "gather"
  model = components.make_model(smoke_config(**{"compile.hashgrid_lookup": "sparsecore"}), backend="tpu")
  assert model.grid_lookup == "sparsecore"
  assert model.grid_matmul_max_rows == smoke_config().compile.matmul_max_rows


# --- Pallas's interpret mode on a CPU ---------------------------------------------------------------------------


def _on_a_v6e_trace():
  """A trace that JAX takes for a TPU v6e's (the SparseCore mesh reads the chip from the abstract mesh; on a
  CPU's own trace `VectorSubcoreMesh()` raises "ValueError: Unsupported TPU device kind: cpu")."""
  from jax._src import mesh as mesh_lib
  device = mesh_lib.AbstractDevice(device_kind="TPU v6 lite", num_cores=1, platform="tpu")
  return jax.sharding.use_abstract_mesh(mesh_lib.AbstractMesh((1,), ("d",), abstract_device=device))


@pytest.mark.xfail(strict=True, raises=Exception, reason=(
    "JAX 0.10.2's TPU interpreter (pltpu.InterpretParams) runs a DMA with scalar offsets only: an indexed DMA "
    "`table_hbm.at[rows_vmem]` reads the index ref's buffer number as the row ('IndexError: Out-of-bounds read "
    "of (0 0 hbm 100): reading [(103, slice(0, 2, 1))] but buffer has shape (32, 2).'; the scatter-add's: "
    "'ValueError: Out-of-bounds write of (0 0 hbm 102): writing [(103, slice(0, 2, 1))] ...'), and with the rows as "
    "values `jax.tree.map(int, src_transforms)` fails ('TypeError: Only scalar arrays can be converted to Python "
    "scalars; got arr.ndim=1'); the discharge interpreter (interpret=True) cannot bind the subcore mesh's axes "
    "('NameError: Found an unbound axis name: core') nor discharge add=True ('NotImplementedError: DMA partial "
    "discharge add=True not yet implemented.')"))
@pytest.mark.parametrize("direction", ["gather", "scatter_add"])
def test_the_kernels_in_interpret_mode_equal_their_references(direction):
  table = jnp.arange(64.0).reshape(32, 2)
  rows = jnp.asarray([1, 5, 31, 0, 5], jnp.int32)
  values = jnp.ones((5, 2))
  with _on_a_v6e_trace():
    if direction == "gather":
      out = jax.jit(lambda t, r: sparsecore._gather_kernel(t, r, interpret=True))(table, rows)
      expected = sparsecore._gather_reference(table, rows)
    else:
      out = jax.jit(lambda v, r: sparsecore._scatter_add_kernel(v, r, 32, interpret=True))(values, rows)
      expected = sparsecore._scatter_add_reference(values, rows, 32)
  np.testing.assert_array_equal(out, expected)


def test_nerfpod_aot_explains_mosaics_refusal_of_the_kernels_in_its_one_sentence():
  from nerfpod.pod import aot, chips
  pod = chips.lookup("v6e-8")
  reason = ("INTERNAL: Failed to run MLO pass pipeline.hashgrid_sparsecore_gather.13:60:1: error: "
            "'tpu.enqueue_indirect_dma' op Not implemented: expected slice size (2) to be aligned with source "
            "(gather operand) tiling (128).")
  refusal = aot.CompileError("step", pod, reason)
  explained = aot._explained(refusal, smoke_config(**{"compile.hashgrid_lookup": "sparsecore"}), pod, 1)  # noqa: SLF001
  assert str(explained).startswith(f"the train step does not compile for v6e-8 (8 chips on 1 hosts): {reason} (")
  assert "use --config.compile.hashgrid_lookup=auto" in str(explained) and "\n" not in str(explained)
  assert aot._explained(refusal, smoke_config(), pod, 1) is refusal  # noqa: SLF001
