"""Input encodings: NeRF's positional (Fourier) encoding and a multiresolution hash grid (Instant-NGP)."""
import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


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
  c = corners.astype(jnp.uint32)
  h = c[..., 0] * jnp.uint32(_PRIMES[0])
  h = h ^ (c[..., 1] * jnp.uint32(_PRIMES[1]))
  h = h ^ (c[..., 2] * jnp.uint32(_PRIMES[2]))
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
  side = resolution + 1
  if side**3 <= table_size:
    return corners[..., 0] * side * side + corners[..., 1] * side + corners[..., 2]
  return hash_indices(corners, table_size)


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

  @nn.compact
  def __call__(self, x_Nx3, scales_N=None, opened_L=None):
    """The features (N, num_levels * features_per_level); with `scales_N`, each point's footprint (a standard
    deviation, in the unit cube's units), each level's features weighted by level_weights (Zip-NeRF); with
    `opened_L` (num_levels,), each level's features (and so its gradients) times its weight
    (coarse_to_fine_weights)."""
    table_size = 2**self.log2_table_size
    if self.materialize:
      x_Nx3 = materialized(x_Nx3)
    outputs = []
    resolutions = level_resolutions(self.num_levels, self.base_resolution, self.max_resolution)
    for level, res in enumerate(resolutions):
      rows = min(table_size, (res + 1)**3)
      table = self.param(f"level_{level}", _symmetric_uniform(1e-4), (rows, self.features_per_level))
      if rows == (res + 1)**3 and rows <= self.matmul_max_rows:
        feats = dense_level_matmul(table, x_Nx3, res)
      else:
        feats = level_gather(table, x_Nx3, res, self.materialize)
      if scales_N is not None:
        feats = feats * level_weights(scales_N, res)[..., None]
      if opened_L is not None:
        feats = feats * opened_L[level]
      outputs.append(feats)
    return jnp.concatenate(outputs, axis=-1)


def materialized(x_NxD):
  """x itself, every bit of it, computed as the matmul x @ I (each value is 1 * x_i plus zeros, exact at full
  precision; integer arrays in integer arithmetic), so that XLA keeps it in memory.

  XLA:CPU fuses a cheap computation into every consumer, recomputing it per consumer element: a hash-grid
  level's rows and weights are computed per corner and axis, so each point and its ray were recomputed 24
  times per level, a third of a CPU train step (configs/tiny_fast.py, docs/results.md), and each corner's row
  (its hash) once per feature in the lookup and again for the gradient's scatter. A dot's output is not fused
  into its consumers, so they read it instead. A float array's gradient, the same product with the
  cotangents, is exact too; an integer array (a row number) has none."""
  eye = jnp.eye(x_NxD.shape[-1], dtype=x_NxD.dtype)
  return jnp.dot(x_NxD, eye, precision=jax.lax.Precision.HIGHEST, preferred_element_type=x_NxD.dtype)


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
