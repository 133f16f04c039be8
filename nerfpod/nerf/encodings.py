"""Input encodings: NeRF's positional (Fourier) encoding and a multiresolution hash grid (Instant-NGP)."""
import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental.layout import Layout, with_layout_constraint

from nerfpod.nerf import sparsecore


def positional_encoding(x_Nx3, num_frequencies: int):
  """[x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(2^(L-1) x)], the Tiny NeRF tutorial's layout.

  num_frequencies = 0 switches the encoding off (the raw coordinates, the tutorial's comparison).
  Output width: 3 * (1 + 2 L).
  """
  parts = [x_Nx3]
  for k in range(num_frequencies):
    parts += [jnp.sin(2.0**k * x_Nx3), jnp.cos(2.0**k * x_Nx3)]
  return jnp.concatenate(parts, axis=-1)


# Instant-NGP's spatial hash primes; the first is 1 so that level-0 neighbours stay coherent in memory.
_PRIMES = (1, 2654435761, 805459861)


def hash_indices(corners, table_size: int):
  """Instant-NGP's spatial hash of integer grid corners (..., 3): XOR of coordinate * prime, modulo the
  table size. uint32 arithmetic wraps around, as in the reference implementation. Returns int32 indices
  (...) in [0, table_size).
  """
  return _spatial_hash(corners[..., 0], corners[..., 1], corners[..., 2], table_size)


def _spatial_hash(c0, c1, c2, table_size: int):
  """hash_indices of corners given as their three coordinate arrays (any one shape)."""
  h = c0.astype(jnp.uint32) * jnp.uint32(_PRIMES[0])
  h = h ^ (c1.astype(jnp.uint32) * jnp.uint32(_PRIMES[1]))
  h = h ^ (c2.astype(jnp.uint32) * jnp.uint32(_PRIMES[2]))
  return (h % jnp.uint32(table_size)).astype(jnp.int32)


def level_resolutions(num_levels: int, base_resolution: int, max_resolution: int) -> list[int]:
  """Grid resolution of each level, growing geometrically from base to max (Instant-NGP eq. 2-3)."""
  if num_levels == 1:
    return [base_resolution]
  growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (num_levels - 1))
  return [int(math.floor(base_resolution * growth**level + 1e-6)) for level in range(num_levels)]


def trilinear_corners_and_weights(x_Nx3, resolution: int):
  """The 8 grid corners around points x in [0, 1]^3 on a grid of `resolution` cells, and their weights.

  Returns corners (N, 8, 3) int32 and weights (N, 8) that sum to 1. At a grid vertex all weight falls on
  that vertex.
  """
  scaled = x_Nx3 * resolution
  base = jnp.clip(jnp.floor(scaled), 0, resolution - 1)
  frac = scaled - base
  offsets = jnp.asarray(np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]), jnp.int32)
  corners = base.astype(jnp.int32)[..., None, :] + offsets
  w = jnp.where(offsets == 1, frac[..., None, :], 1.0 - frac[..., None, :])
  return corners, jnp.prod(w, axis=-1)


def grid_indices(corners, resolution: int, table_size: int):
  """Table rows (...) of grid corners (..., 3): dense (one row per vertex) where the level fits, else the
  spatial hash."""
  return _grid_rows(corners[..., 0], corners[..., 1], corners[..., 2], resolution, table_size)


def _grid_rows(c0, c1, c2, resolution: int, table_size: int):
  """grid_indices of corners given as their three coordinate arrays (any one shape)."""
  side = resolution + 1
  if side**3 <= table_size:
    return c0 * side * side + c1 * side + c2
  return _spatial_hash(c0, c1, c2, table_size)


# compile.hashgrid_layout's values: how a hash grid's lookup lays out its arrays (HashGridEncoding.layout).
LAYOUTS = ("rows", "lane_dense")
# How a hash grid reads the levels it does not read by matmuls (HashGridEncoding.lookup): XLA's gather (and
# scatter-add), or Pallas kernels on a TPU's SparseCores (nerf/sparsecore.py: v5p and v6e only).
LOOKUPS = ("gather", "sparsecore")


def _symmetric_uniform(scale):
  """Initialiser drawing from U(-scale, scale), Instant-NGP's table initialisation."""
  return lambda key, shape, dtype=jnp.float32: jax.random.uniform(key, shape, dtype, -scale, scale)


class HashGridEncoding(nn.Module):
  """A multiresolution hash encoding of points in [0, 1]^3 (Mueller et al. 2022).

  Each level is a table of `2**log2_table_size` rows of `features_per_level` features, indexed densely while
  the level's grid fits and by the spatial hash beyond; features are trilinearly interpolated and the levels
  concatenated: output width num_levels * features_per_level.
  """
  num_levels: int
  features_per_level: int
  log2_table_size: int
  base_resolution: int
  max_resolution: int

  matmul_max_rows: int = 0  # dense levels of at most this many rows are read by matmuls, not gathers
  materialize: bool = False  # the points, and each level's corner rows, kept in memory (materialized: CPUs)
  layout: str = "rows"  # compile.hashgrid_layout: 'rows' or 'lane_dense' (per-sample arrays sample-minor)
  lookup: str = "gather"  # levels not read by matmuls: 'gather' (XLA) or 'sparsecore' (Pallas, TPU v5p/v6e)

  @nn.compact
  def __call__(self, x_Nx3, scales_N=None, opened_L=None):
    """The features (N, num_levels * features_per_level); with `scales_N`, each point's footprint (a standard
    deviation, in the unit cube's units), each level's features weighted by level_weights (Zip-NeRF); with
    `opened_L` (num_levels,), each level's features (and so its gradients) times its weight
    (coarse_to_fine_weights).

    `layout` 'lane_dense' computes the same features with every per-sample array sample-minor and each table
    read features-major: the parameters are the same (rows, F) arrays in either layout (a TPU lays a (rows, 2)
    array out features-major already, `{0,1:T(2,128)}`), so a checkpoint restores under either
    (docs/pod-compile.md, "Lane-dense hash-grid lookups")."""
    if self.layout not in LAYOUTS:
      raise ValueError(f"unknown hash-grid layout {self.layout!r}; one of {', '.join(LAYOUTS)}")
    if self.lookup not in LOOKUPS:
      raise ValueError(f"unknown hash-grid lookup {self.lookup!r}; one of {', '.join(LOOKUPS)}")
    sparsecore = self.lookup == "sparsecore"
    table_size = 2**self.log2_table_size
    if self.materialize:
      x_Nx3 = materialized(x_Nx3)
    lane_dense = self.layout == "lane_dense"
    x_3xN = x_Nx3.T if lane_dense else None
    outputs = []
    resolutions = level_resolutions(self.num_levels, self.base_resolution, self.max_resolution)
    for level, res in enumerate(resolutions):
      rows = min(table_size, (res + 1)**3)
      table = self.param(f"level_{level}", _symmetric_uniform(1e-4), (rows, self.features_per_level))
      by_matmul = rows == (res + 1)**3 and rows <= self.matmul_max_rows
      if lane_dense:  # features (F, N)
        feats = (dense_level_matmul_lane_dense(table, x_3xN, res) if by_matmul else
                 level_gather_lane_dense(table, x_3xN, res, self.materialize, sparsecore))
        if scales_N is not None:
          feats = feats * level_weights(scales_N, res)[None, :]
      else:  # features (N, F)
        feats = (dense_level_matmul(table, x_Nx3, res) if by_matmul else
                 level_gather_sparsecore(table, x_Nx3, res) if sparsecore else
                 level_gather(table, x_Nx3, res, self.materialize))
        if scales_N is not None:
          feats = feats * level_weights(scales_N, res)[..., None]
      if opened_L is not None:
        feats = feats * opened_L[level]
      outputs.append(feats)
    if lane_dense:
      return jnp.concatenate(outputs, axis=0).T
    return jnp.concatenate(outputs, axis=-1)


def materialized(x_NxD, axis: int = -1):
  """x itself, every bit of it, computed as the matmul x @ I (each value is 1 * x_i plus zeros, exact at full
  precision; integer arrays in integer arithmetic), so that XLA keeps it in memory.

  XLA:CPU fuses a cheap computation into every consumer, recomputing it per consumer element: a hash-grid
  level's rows and weights are computed per corner and axis, so each point and its ray were recomputed 24
  times per level, a third of a CPU train step (configs/tiny_fast.py, docs/results.md), and each corner's row
  (its hash) once per feature in the lookup and again for the gradient's scatter. A dot's output is not fused
  into its consumers, so they read it instead. A float array's gradient, the same product with the
  cotangents, is exact too; an integer array (a row number) has none. `axis`: the dimension the identity
  multiplies, the last (x @ I) or the first (I @ x, for the sample-minor arrays of the lane-dense layout)."""
  if axis not in (-1, 0, x_NxD.ndim - 1):
    raise ValueError(f"materialized multiplies the first or the last dimension, not {axis}")
  dot = functools.partial(jnp.dot, precision=jax.lax.Precision.HIGHEST, preferred_element_type=x_NxD.dtype)
  if axis == 0 and x_NxD.ndim > 1:
    return dot(jnp.eye(x_NxD.shape[0], dtype=x_NxD.dtype), x_NxD)
  return dot(x_NxD, jnp.eye(x_NxD.shape[-1], dtype=x_NxD.dtype))


def level_weights(scales_N, resolution: int):
  """Zip-NeRF's feature downweighting (Barron et al. 2023, eq. 8): erf(1 / sqrt(8 sigma^2 n^2)) for a point
  whose footprint has standard deviation sigma (unit-cube units) on a level of n cells a side: near 1 where the
  footprint spans less than a cell (the level resolves it), falling towards 0 where it spans many (there the
  level's features would alias: detail no pixel of that size resolves). sigma = 0 gives exactly 1."""
  return jax.scipy.special.erf(1.0 / jnp.maximum(jnp.sqrt(8.0) * scales_N * resolution, 1e-30))


def coarse_to_fine_weights(step, start_step: int, end_step: int, num_levels: int):
  """BARF's coarse-to-fine weights (Lin et al. 2021, eq. 14) of a hash grid's levels at training `step`:
  alpha rises linearly from 0 at `start_step` to num_levels - 1 at `end_step`, and level l >= 1 has weight
  (1 - cos(pi * clip(alpha - l + 1, 0, 1))) / 2, so the levels open one after another, each smoothly; level 0
  (the coarsest) is always open, as BARF keeps its raw input. (num_levels,) float32: all 0 but level 0 up to
  `start_step`, exactly 1 from `end_step` on."""
  progress = jnp.clip((jnp.asarray(step, jnp.float32) - start_step) / max(end_step - start_step, 1), 0.0, 1.0)
  alpha = progress * (num_levels - 1)
  x = jnp.clip(alpha - jnp.arange(num_levels, dtype=jnp.float32) + 1.0, 0.0, 1.0)
  return jnp.where(x >= 1.0, 1.0, (1.0 - jnp.cos(jnp.pi * x)) / 2.0)


def level_gather(table_RxF, x_Nx3, resolution: int, materialize: bool = False):
  """A level's trilinearly interpolated features (N, F) by gathering its 8 corners' rows (Instant-NGP's
  formulation; its gradient is a scatter-add into the table).

  `materialize` (CPUs): the corners' rows computed once into memory (materialized), read by the lookup and by
  its gradient's scatter, and the lookup told that they lie in the table (they do: corners are clipped to the
  grid, hashes taken modulo the table's size), which spares a bounds test per value. The same values either
  way, bit for bit."""
  corners, weights = trilinear_corners_and_weights(x_Nx3, resolution)
  rows = grid_indices(corners, resolution, len(table_RxF))
  if materialize:
    feats = table_RxF.at[materialized(rows)].get(mode="promise_in_bounds")
  else:
    feats = jnp.take(table_RxF, rows, axis=0)
  return jnp.sum(weights[..., None] * feats, axis=-2)


def level_gather_sparsecore(table_RxF, x_Nx3, resolution: int, reference: bool = False):
  """level_gather with the 8 corners' rows gathered on a TPU's SparseCores (nerf/sparsecore.py:
  sparsecore_take, a Pallas kernel whose gradient is a scatter-add kernel into a zero table); the rows and the
  trilinear weighting are level_gather's, in plain JAX. `reference`: the kernels replaced by jnp.take and a
  scatter-add (what a CPU can run; tests/test_sparsecore.py)."""
  corners, weights = trilinear_corners_and_weights(x_Nx3, resolution)
  rows = grid_indices(corners, resolution, len(table_RxF))
  feats = sparsecore.sparsecore_take(table_RxF, rows, reference=reference)
  return jnp.sum(weights[..., None] * feats, axis=-2)


def axis_weights(x_Nx3, resolution: int):
  """Per-axis linear-interpolation weights (N, 3, side) over a grid's side = resolution + 1 vertices: at
  most two non-zero per axis, (1 - frac) at the lower vertex and frac at the upper. Their outer product over
  the three axes is exactly the trilinear weights of trilinear_corners_and_weights."""
  scaled = x_Nx3 * resolution
  base = jnp.clip(jnp.floor(scaled), 0, resolution - 1)
  frac = scaled - base
  vertex = jnp.arange(resolution + 1, dtype=x_Nx3.dtype)
  lower = (vertex == base[..., None]).astype(x_Nx3.dtype)
  upper = (vertex == base[..., None] + 1).astype(x_Nx3.dtype)
  return lower * (1.0 - frac[..., None]) + upper * frac[..., None]


def dense_level_matmul(table_RxF, x_Nx3, resolution: int):
  """The same interpolated features as level_gather for a dense level, with no gather or scatter.

  The trilinear weights factor over the axes, so the lookup is three contractions with per-axis weight
  rows: first a matmul (N, side) @ (side, side^2 F) over the last axis, then two small per-point
  reductions. Its gradient with respect to the table is again a matmul (weights^T @ cotangents) instead of
  a scatter-add. It costs 2 N side^3 F FLOPs and an (N, side^2 F) intermediate, so it pays where matmuls are
  cheap and gathers dear (TPUs: multinerf and Zip-NeRF avoid gathers there for the same reason), on the
  coarse levels only.
  """
  side = resolution + 1
  features = table_RxF.shape[-1]
  w = axis_weights(x_Nx3, resolution)                       # (N, 3, side)
  grid = table_RxF.reshape(side, side, side, features)      # rows are c0 side^2 + c1 side + c2
  # Full float32 precision: on TPU a float32 matmul otherwise runs as one bfloat16 pass, which would round
  # the table's values; the cost model counts the extra passes.
  einsum = functools.partial(jnp.einsum, precision=jax.lax.Precision.HIGHEST)
  by_last = einsum("nk,ijkf->nijf", w[:, 2], grid)       # the matmul
  by_middle = einsum("nj,nijf->nif", w[:, 1], by_last)
  return einsum("ni,nif->nf", w[:, 0], by_middle)


# The lane-dense layout (compile.hashgrid_layout='lane_dense'). A TPU lays an array out in tiles of 8 x 128
# values over its two minor dimensions: a minor dimension of 2 (a (rows, 2) table, the (N, 8, 2) corner values)
# or of 8 (the (N, 8) rows and weights) fills 2 or 8 of each tile row's 128 lanes wherever XLA keeps that
# order. Here the samples are the minor dimension of every per-sample array (points (3, N), rows and weights
# (8, N), corner values (F, 8, N), features (F, N)) and the tables are read features-major. The parameters stay
# (rows, F) arrays: a TPU lays them out features-major already (`{0,1:T(2,128)}`: each feature's column
# contiguous), and a checkpoint serves either layout. The values are the rows layout's: the same products and
# sums of the same numbers (tests/test_hashgrid_layout.py compares both, values and gradients).


def trilinear_corners_and_weights_lane_dense(x_3xN, resolution: int):
  """trilinear_corners_and_weights, sample-minor: corners (3, 8, N) int32 (axis, corner, sample) and weights
  (8, N), in the same corner order and by the same arithmetic (each weight the product of its three axis
  weights, in axis order)."""
  scaled = x_3xN * resolution
  base = jnp.clip(jnp.floor(scaled), 0, resolution - 1)
  frac = scaled - base
  offsets = jnp.asarray(np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]).T[:, :, None],
                        jnp.int32)                                   # (3, 8, 1)
  corners = base.astype(jnp.int32)[:, None, :] + offsets
  w = jnp.where(offsets == 1, frac[:, None, :], 1.0 - frac[:, None, :])
  return corners, jnp.prod(w, axis=0)


def features_major(x_RxF):
  """x (rows, F), laid out features-major: its dims pinned major to minor as (F, rows), so that XLA stores each
  feature's column contiguously, the rows across the lanes (jax.experimental.layout; the cotangent is pinned
  alike). Values are untouched: on any backend it is x."""
  return with_layout_constraint(x_RxF, Layout(major_to_minor=(1, 0)))


def level_gather_lane_dense(table_RxF, x_3xN, resolution: int, materialize: bool = False,
                            sparsecore_lookup: bool = False):
  """level_gather in the lane-dense layout: a level's features (F, N) from its table (rows, F) and sample-minor
  points (3, N).

  The corner rows (8, N) are gathered as one list of 8 N row numbers (the TPU's own gather form: whole rows of
  the table), the values pinned features-major, (F, 8 N), that is (F, 8, N) (features_major), weighted by the
  (8, N) trilinear weights and summed over the corners; the gradient is the same scatter-add of (F, 8, N)
  cotangents, pinned alike. Without the pin XLA re-orders the transposes into the gather's (8 N, F) form with F
  minor (2 values in each 128-lane tile row). Row numbers lie in the table by construction (corners clipped to
  the grid, hashes modulo its size), and the gather is told so (`promise_in_bounds`: no bounds mask).
  `materialize` as level_gather's (the rows computed once into memory). `sparsecore_lookup`: the 8 N rows
  gathered on the SparseCores (sparsecore.sparsecore_take), as level_gather_sparsecore's."""
  corners, weights = trilinear_corners_and_weights_lane_dense(x_3xN, resolution)
  rows = _grid_rows(corners[0], corners[1], corners[2], resolution, table_RxF.shape[0])  # (8, N)
  if materialize:
    rows = materialized(rows, axis=0)
  if sparsecore_lookup:
    values = sparsecore.sparsecore_take(table_RxF, rows.reshape(-1))                # (8 N, F)
  else:
    values = table_RxF.at[rows.reshape(-1)].get(mode="promise_in_bounds")      # (8 N, F)
  values = features_major(values).T.reshape(table_RxF.shape[1], *rows.shape)  # (F, 8, N)
  return jnp.sum(weights[None] * values, axis=1)


def axis_weights_lane_dense(x_3xN, resolution: int):
  """axis_weights, sample-minor: (3, side, N), by the same arithmetic."""
  scaled = x_3xN * resolution
  base = jnp.clip(jnp.floor(scaled), 0, resolution - 1)
  frac = scaled - base
  vertex = jnp.arange(resolution + 1, dtype=x_3xN.dtype)[:, None]
  lower = (vertex == base[:, None, :]).astype(x_3xN.dtype)
  upper = (vertex == base[:, None, :] + 1).astype(x_3xN.dtype)
  return lower * (1.0 - frac[:, None, :]) + upper * frac[:, None, :]


def dense_level_matmul_lane_dense(table_RxF, x_3xN, resolution: int):
  """dense_level_matmul in the lane-dense layout: features (F, N) of a dense level from its table (rows, F),
  read features-major, by the matmul (F side^2, side) @ (side, N) over the last axis and two per-point
  reductions; the gradient again matmuls."""
  side = resolution + 1
  w = axis_weights_lane_dense(x_3xN, resolution)                        # (3, side, N)
  grid = table_RxF.T.reshape(table_RxF.shape[1], side, side, side)      # rows are c0 side^2 + c1 side + c2
  einsum = functools.partial(jnp.einsum, precision=jax.lax.Precision.HIGHEST)
  by_last = einsum("kn,fijk->fijn", w[2], grid)       # the matmul
  by_middle = einsum("jn,fijn->fin", w[1], by_last)
  return einsum("in,fin->fn", w[0], by_middle)


def spherical_harmonics_deg4(dirs_Nx3):
  """Real spherical harmonics up to degree 3 (16 values) of unit directions: Instant-NGP's view encoding."""
  x, y, z = dirs_Nx3[..., 0], dirs_Nx3[..., 1], dirs_Nx3[..., 2]
  xx, yy, zz = x * x, y * y, z * z
  return jnp.stack([
      jnp.full_like(x, 0.28209479177387814),
      -0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x,
      1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
      0.94617469575755997 * zz - 0.31539156525251999,
      -1.0925484305920792 * x * z, 0.54627421529603959 * (xx - yy),
      0.59004358992664352 * y * (-3.0 * xx + yy), 2.8906114426405538 * x * y * z,
      0.45704579946446572 * y * (1.0 - 5.0 * zz), 0.3731763325901154 * z * (5.0 * zz - 3.0),
      0.45704579946446572 * x * (1.0 - 5.0 * zz), 1.4453057213202769 * z * (xx - yy),
      0.59004358992664352 * x * (-xx + 3.0 * yy),
  ], axis=-1)
