"""The hash grid's row lookup on a TPU's SparseCores (compile.hashgrid_lookup='sparsecore'; v5p and v6e).

`sparsecore_take(table_RxF, rows)` is `jnp.take(table_RxF, rows, axis=0)`: the table's rows (rows.shape + (F,)),
as level_gather reads a level's 8 corners. Its gradient with respect to the table is the scatter-add of the
cotangents into a zero table, as jnp.take's is; the rows (integers) have none. Both directions are Pallas
kernels on the SparseCores' vector subcores (jax.experimental.pallas.tpu_sc): the row numbers are split over
every subcore of every SparseCore of the chip, each subcore copies a chunk of them into its own memory and
issues one indexed DMA (`table_hbm.at[rows_vmem]`: a gather of whole rows from HBM; back, `add=True` into the
gradient table in HBM). The trilinear weighting stays in plain JAX (level_gather_sparsecore).

No CPU or GPU runs these kernels, and Pallas's interpret mode cannot run a SparseCore kernel on a CPU in JAX
0.10.2 (tests/test_sparsecore.py records why): `reference=True` swaps each kernel for the jnp expression it
replaces, with the same custom_vjp around it, which is what the CPU tests check against level_gather; a trace
for a chip without SparseCores (the parameters' jax.eval_shape on the host) takes those expressions too.
Mosaic (libtpu 0.0.42.1) refuses the indexed DMA of rows this narrow (2 float32 values) for v5p and v6e:
docs/pod-compile.md ("A SparseCore lookup") quotes it.
"""
import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import tpu as pltpu
from jax.experimental.pallas import tpu_sc as plsc

# Row numbers a subcore gathers with one indexed DMA: its row numbers (4 bytes each) and the rows (F values of
# 4 bytes) sit in the subcore's own memory (256 KiB on v6e, 512 KiB on v5p), 12 KiB at F = 2.
MAX_CHUNK = 1024


def _mesh():
  """All vector subcores of every SparseCore of the chip the program is traced for (JAX reads the chip from
  the traced mesh's devices, or the default device: on a CPU this raises)."""
  return plsc.VectorSubcoreMesh(core_axis_name="core", subcore_axis_name="subcore")


def traced_for_sparsecores() -> bool:
  """Whether the program being traced is for a chip with SparseCores: JAX reads the chip from the traced mesh's
  devices (a shard_map's or jax.set_mesh's), else from the default device. A trace for shapes alone outside
  any mesh (a model's parameters initialised with jax.eval_shape on the host) is not, and takes the jnp
  expressions instead: the same values and shapes."""
  try:
    plsc.get_sparse_core_info()
  except (RuntimeError, ValueError):  # a chip without SparseCores, or no TPU at all
    return False
  return True


def _split(count: int, workers: int) -> tuple[int, int]:
  """(chunk, steps): each of `workers` subcores handles `steps` chunks of `chunk` row numbers (a multiple of
  8), together at least `count`."""
  per_worker = -(-count // workers)
  steps = max(1, -(-per_worker // MAX_CHUNK))
  chunk = 8 * -(-per_worker // (8 * steps))
  return chunk, steps


def _cost(count: int, features: int, itemsize: int) -> pl.CostEstimate:
  """The kernel's cost estimate (what nerfpod/pod/hlo_cost.py charges a Pallas call): no FLOPs; the row numbers
  read, and each row moved as a 32-byte DMA granule at least (v5p/v6e SparseCores' granule,
  tpu_info.SparseCoreInfo.dma_granule_size_bytes) read and written once."""
  row_bytes = max(32, features * itemsize)
  return pl.CostEstimate(flops=0, transcendentals=0, bytes_accessed=int(count * (4 + 2 * row_bytes)))


def _plan(count: int):
  """(mesh, chunk, steps, padded, chunk_start): the chip's vector subcores, each taking `steps` chunks of
  `chunk` row numbers (_split), `padded` of them in all, and chunk_start(step), the first row number of a
  subcore's step-th chunk (traced inside a kernel)."""
  mesh = _mesh()
  chunk, steps = _split(count, mesh.num_cores * mesh.num_subcores)

  def chunk_start(step):
    worker = jax.lax.axis_index("core") * mesh.num_subcores + jax.lax.axis_index("subcore")
    return pl.multiple_of((worker * steps + step) * chunk, 8)
  return mesh, chunk, steps, chunk * steps * mesh.num_cores * mesh.num_subcores, chunk_start


def _interpret_params(interpret: bool):
  """pl.kernel's `interpret`: the TPU interpreter (Pallas's interpret mode for TPU kernels) or none."""
  return pltpu.InterpretParams() if interpret else False


def _gather_kernel(table_RxF, rows_M, interpret: bool = False):
  """table_RxF[rows_M] (M, F) by indexed DMAs on the SparseCores (`interpret`: in Pallas's interpret mode)."""
  (count,), (_, features) = rows_M.shape, table_RxF.shape
  mesh, chunk, steps, padded, chunk_start = _plan(count)
  rows_M = jnp.pad(rows_M, (0, padded - count))  # row 0, gathered and dropped

  @functools.partial(
      pl.kernel, mesh=mesh, name="hashgrid_sparsecore_gather",
      out_type=jax.ShapeDtypeStruct((padded, features), table_RxF.dtype, manual_axis_type=jax.typeof(rows_M).mat),
      scratch_types=(pltpu.VMEM((chunk,), jnp.int32), pltpu.VMEM((chunk, features), table_RxF.dtype),
                     pltpu.SemaphoreType.DMA),
      cost_estimate=_cost(padded, features, table_RxF.dtype.itemsize), interpret=_interpret_params(interpret))
  def kernel(table_hbm, rows_hbm, out_hbm, rows_vmem, values_vmem, sem):
    @pl.loop(0, steps)
    def _(step):
      start = chunk_start(step)
      pltpu.sync_copy(rows_hbm.at[pl.ds(start, chunk)], rows_vmem)
      pltpu.async_copy(table_hbm.at[rows_vmem], values_vmem, sem).wait()
      pltpu.sync_copy(values_vmem, out_hbm.at[pl.ds(start, chunk)])

  return kernel(table_RxF, rows_M)[:count]


def _scatter_add_kernel(values_MxF, rows_M, num_rows: int, interpret: bool = False):
  """A zero (num_rows, F) table with values_MxF added at rows_M (repeated rows summed), by indexed DMAs with
  add=True on the SparseCores."""
  count, features = values_MxF.shape
  mesh, chunk, steps, padded, chunk_start = _plan(count)
  rows_M = jnp.pad(rows_M, (0, padded - count))                # row 0 ...
  values_MxF = jnp.pad(values_MxF, ((0, padded - count), (0, 0)))  # ... gets zeros added
  zeros = jnp.zeros((num_rows, features), values_MxF.dtype)
  grad = jax.new_ref(_varying_as(zeros, values_MxF, rows_M))

  @functools.partial(
      pl.kernel, mesh=mesh, name="hashgrid_sparsecore_scatter_add", out_type=(),
      scratch_types=(pltpu.VMEM((chunk,), jnp.int32), pltpu.VMEM((chunk, features), values_MxF.dtype),
                     pltpu.SemaphoreType.DMA),
      cost_estimate=_cost(padded, features, values_MxF.dtype.itemsize), interpret=_interpret_params(interpret))
  def kernel(values_hbm, rows_hbm, grad_hbm, rows_vmem, values_vmem, sem):
    @pl.loop(0, steps)
    def _(step):
      start = chunk_start(step)
      pltpu.sync_copy(rows_hbm.at[pl.ds(start, chunk)], rows_vmem)
      pltpu.sync_copy(values_hbm.at[pl.ds(start, chunk)], values_vmem)
      pltpu.async_copy(values_vmem, grad_hbm.at[rows_vmem], sem, add=True).wait()

  kernel(values_MxF, rows_M, grad)
  return grad[...]


def _varying_as(x, *others):
  """x, marked as varying over every mesh axis (of a shard_map) that `others` vary over: a kernel's inputs and
  outputs vary alike (a no-op outside shard_map)."""
  axes = frozenset().union(*(jax.typeof(o).mat.varying for o in others)) - jax.typeof(x).mat.varying
  return jax.lax.pcast(x, tuple(sorted(axes)), to="varying") if axes else x


def _gather_reference(table_RxF, rows_M):
  """What _gather_kernel computes, in jnp."""
  return jnp.take(table_RxF, rows_M, axis=0)


def _scatter_add_reference(values_MxF, rows_M, num_rows: int):
  """What _scatter_add_kernel computes, in jnp."""
  return jnp.zeros((num_rows, values_MxF.shape[1]), values_MxF.dtype).at[rows_M].add(values_MxF)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _take_rows(table_RxF, rows_M, num_rows: int, reference: bool):
  del num_rows  # the table's: for the gradient
  gather = _gather_reference if reference or not traced_for_sparsecores() else _gather_kernel
  return gather(table_RxF, rows_M)


def _take_rows_fwd(table_RxF, rows_M, num_rows: int, reference: bool):
  return _take_rows(table_RxF, rows_M, num_rows, reference), rows_M


def _take_rows_bwd(num_rows: int, reference: bool, rows_M, cotangent_MxF):
  scatter_add = _scatter_add_reference if reference or not traced_for_sparsecores() else _scatter_add_kernel
  return scatter_add(cotangent_MxF, rows_M, num_rows), None


_take_rows.defvjp(_take_rows_fwd, _take_rows_bwd)


def sparsecore_take(table_RxF, rows, reference: bool = False):
  """jnp.take(table_RxF, rows, axis=0) (rows.shape + (F,)) gathered on the SparseCores, its gradient with
  respect to the table a scatter-add there. Row numbers must lie in the table (no bounds check: the indexed
  DMA would read or add out of it). `reference`: the kernels replaced by their jnp expressions (CPU tests)."""
  rows_M = rows.reshape(-1).astype(jnp.int32)
  # In a shard_map the rows vary over the data axis and the table does not: the table is marked varying here,
  # outside the custom_vjp (its gradient, per device, is then summed over those axes by JAX, as jnp.take's).
  table_RxF, rows_M = _varying_as(table_RxF, rows_M), _varying_as(rows_M, table_RxF)
  values = _take_rows(table_RxF, rows_M, table_RxF.shape[0], reference)
  return values.reshape(*rows.shape, table_RxF.shape[1])

