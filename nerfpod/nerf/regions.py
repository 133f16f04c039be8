"""Space cut into K convex regions, each rendered on its own segment of a ray, and the segments composited.

NeRF-XL (Li et al. 2024, arXiv 2404.16221): a scene too big for one chip's memory is cut into K regions,
each its own field. A ray crosses each convex region at most once, on one segment [t_in_k, t_out_k]; each
region renders its segment alone, from transmittance 1, into a few per-ray partial sums, and only those
sums are combined, in the order the ray meets the regions:

    near                                                                              far
     |---- region 2 ----|------- region 0 -------|--- region 3 ---|      (region 1 missed: empty)
       C_2, T_2, D_2        C_0, T_0, D_0            C_3, T_3
    C = C_2 + T_2 C_0 + T_2 T_0 C_3 + T_2 T_0 T_3 background

This is exactly the rendering of one field that is region k's inside region k, on the union of the samples
(volume rendering's weights factor as w_i = (prod of the earlier segments' T) x (the weight within its own
segment)); tests/test_regions.py checks it, values and gradients, against that stitched field.

    Partition         the regions as half-space sets: region k = {x : n . x < b (or == b where closed)}
    grid              a grid of cells in the ground plane (x, y; z is up) over [-bound, bound]^2
    voronoi, kmeans   the Voronoi cells of points of the ground plane (k-means centres of the camera positions)
    region_of         which region each point lies in (the stitched field's choice: exports' queries too)
    cells             each region's cell in the ground plane within a square, a convex polygon (the viewer's)
    unseen            the regions that no ray of a set (the training cameras') crosses
    boxes, to_box     each region's own box (its cell's bounds, the whole height) and the map of it onto a field's
    segments          each ray's segment [t_in, t_out] in each region (the slab method, generalised);
                      segments_one_by_one, region by region as the region step cuts them
    partial_sums      a region's per-ray sums from its samples (colour, optical depth, depth, acc, distortion's)
    capacity_rows, dispatch, gather_rows, scatter_rows   a chip's rows per region within a static capacity C:
                      the rays whose segment is not empty, up to C in ray order, and their sums put back
    sample_classes, class_fractions, class_counts, scatter_classes   model.region_split: a segment's samples
                      by its share of the ray (a class of 2^-j of them), each class its own rows
    pixel_rays, segment_counts, auto_fraction   model.region_capacity=auto: rays drawn as the training batches
                      draw them, how many meet each region, and the capacity's fraction from the fullest share
    composite_regions the regions' partial sums of a ray composited in the ray's order
    interlevel_loss   mip-NeRF 360's interlevel loss of one segment, weighed by what reaches it

The regions cover all of space (the outer cells reach to infinity), so a ray's segments tile its [near, far]
with no gap; a region a ray misses gets the empty segment [far, far], where its samples weigh nothing.
"""
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from nerfpod.nerf import cameras as nerf_cameras
from nerfpod.nerf import coord, sampling, stepfun

# |n . d| below this: the ray runs parallel to the plane (it is then inside or outside along its whole length).
_PARALLEL = 1e-12


class Partition(NamedTuple):
  """K convex regions, each the intersection of P half-spaces (padded with planes that hold everything):
  region k holds x where n_kp . x < b_kp for every p, or n_kp . x == b_kp where closed_kp (a boundary shared
  by two regions is closed on exactly one side, so every point lies in exactly one region)."""
  normals_KxPx3: np.ndarray
  offsets_KxP: np.ndarray
  closed_KxP: np.ndarray

  @property
  def size(self) -> int:
    return self.normals_KxPx3.shape[0]


def _pad(planes: list[list[tuple]]) -> Partition:
  """Per region a list of (normal (3,), offset, closed) -> a Partition, padded with 0 . x <= 1."""
  count = max(1, max(len(p) for p in planes))
  padded = [p + [((0.0, 0.0, 0.0), 1.0, True)] * (count - len(p)) for p in planes]
  return Partition(np.array([[n for n, _, _ in p] for p in padded], np.float32),
                   np.array([[b for _, b, _ in p] for p in padded], np.float32),
                   np.array([[c for _, _, c in p] for p in padded], bool))


def grid_shape(count: int) -> tuple[int, int]:
  """(columns along x, rows along y) of a grid of `count` cells, as square as `count`'s divisors allow."""
  rows = max(d for d in range(1, int(np.sqrt(count)) + 1) if count % d == 0)
  return count // rows, rows


def grid(count: int, bound: float) -> Partition:
  """`count` cells of a grid in the ground plane (grid_shape), cut at even steps over [-bound, bound] along
  x and y; the cells are columns along z, and the outer ones reach to infinity. A cell holds its lower
  boundaries (x = its left cut), not its upper ones."""
  columns, rows = grid_shape(count)
  cuts = [np.linspace(-bound, bound, n + 1, dtype=np.float32)[1:-1] for n in (columns, rows)]
  planes = []
  for j in range(rows):
    for i in range(columns):
      cell = []
      for axis, index, n in ((0, i, columns), (1, j, rows)):
        unit = np.eye(3, dtype=np.float32)[axis]
        if index > 0:  # -x <= -cut: at or beyond the lower cut (closed)
          cell.append((tuple(-unit), -float(cuts[axis][index - 1]), True))
        if index < n - 1:  # x < cut: before the upper cut (open)
          cell.append((tuple(unit), float(cuts[axis][index]), False))
      planes.append(cell)
  return _pad(planes)


def voronoi(centres_Kx2) -> Partition:
  """The Voronoi cells of K points of the ground plane (x, y), as columns along z: region k holds the points
  nearer to centre k than to any other (the bisector (c_j - c_k) . x <= (|c_j|^2 - |c_k|^2) / 2 for every
  j != k), a tie going to the lower index."""
  c = np.asarray(centres_Kx2, np.float32)
  sq = np.sum(c * c, axis=-1)
  planes = []
  for k in range(len(c)):
    cell = []
    for j in range(len(c)):
      if j != k:
        normal = (float(c[j, 0] - c[k, 0]), float(c[j, 1] - c[k, 1]), 0.0)
        # 0.5 * (a - b) and 0.5 * (b - a) are exact negatives: both cells meet on the very same plane.
        cell.append((normal, float(np.float32(0.5) * (sq[j] - sq[k])), k < j))
    planes.append(cell)
  return _pad(planes)


def kmeans(points_Nx2, count: int, iterations: int = 50) -> np.ndarray:
  """`count` centres (count, 2) of the points by Lloyd's k-means, deterministic: started from the points
  farthest apart (the first the point farthest from their mean, each next the farthest from those chosen).
  A centre that loses all its points keeps its place. Needs at least `count` distinct points."""
  p = np.asarray(points_Nx2, np.float64)
  chosen = [int(np.argmax(np.sum((p - p.mean(0))**2, -1)))]
  for _ in range(count - 1):
    dist = np.min(np.sum((p[:, None] - p[chosen][None])**2, -1), axis=1)
    chosen.append(int(np.argmax(dist)))
  centres = p[chosen].copy()
  for _ in range(iterations):
    nearest = np.argmin(np.sum((p[:, None] - centres[None])**2, -1), axis=1)
    moved = np.array([p[nearest == k].mean(0) if np.any(nearest == k) else centres[k] for k in range(count)])
    if np.allclose(moved, centres):
      break
    centres = moved
  return centres.astype(np.float32)


def balanced(points_Nx2, count: int) -> Partition:
  """NeRF-XL's balanced cut (Li et al. 2024, section 4.3) of the ground plane into `count` regions, each holding
  about 1 / count of the points (N, 2) (x, y: the samples along training rays): the cloud is split by a vertical
  plane across its longer axis (its extent over the points; x on a tie), at the quantile that leaves
  count // 2 regions' share on the lower side, and each side is cut alike with count // 2 and count - count // 2
  regions, down to one. For a power of two every split is the median; for any other count the shares are
  uneven per split (3 = 1 + 2: the cut at the first third) but even per region. A region holds the points
  below each of its upper cuts (x < m, open) and at or beyond each of its lower ones (x >= m, closed), as the
  grid's cells do, so every point lies in exactly one region; the regions are the leaves in depth-first order,
  the lower side first. The cuts are computed on the points rounded to float32, at float32 values, so region_of
  (which evaluates n . x with n a unit axis: exact) assigns each point the leaf this recursion put it in."""
  p = np.asarray(points_Nx2, np.float32)
  if p.ndim != 2 or p.shape[1] != 2:
    raise ValueError(f"balanced: points must be (N, 2), got {p.shape}")
  if count < 1 or len(p) < count:
    raise ValueError(f"balanced: {count} regions need at least as many points, got {len(p)}")
  planes = []

  def split(points, k, path):
    if k == 1:
      planes.append(path)
      return
    if len(points) < 2:  # (a run of equal values took the whole side: nothing left to balance; any cut)
      axis, cut = 0, points[0, 0] if len(points) else np.float32(0.0)
    else:
      axis = int(np.ptp(points[:, 1]) > np.ptp(points[:, 0]))
      values = np.sort(points[:, axis])
      index = min(max(int(round(len(values) * (k // 2) / k)), 1), len(values) - 1)
      # midway between the last point of the lower side and the first of the upper (in float32); a run of
      # equal values at the quantile stays on one side whole
      cut = np.float32(0.5) * (values[index - 1] + values[index])
      if not values[index - 1] < cut:
        cut = values[index]
    unit = tuple(float(v) for v in np.eye(3, dtype=np.float32)[axis])
    lower = points[:, axis] < cut
    split(points[lower], k // 2, path + [(unit, float(cut), False)])
    split(points[~lower], k - k // 2, path + [(tuple(-v for v in unit), -float(cut), True)])

  split(p, count, [])
  return _pad(planes)


def stratified_points(origins_Rx3, directions_Rx3, near_R, far_R, per_ray: int, rng: np.random.Generator):
  """(R * per_ray, 3) float32: `per_ray` points along each ray, one drawn uniformly in each of per_ray equal
  strata of its [near, far] (near/far (R,) or (R, 1))."""
  near = np.reshape(np.asarray(near_R, np.float64), (-1, 1))
  far = np.reshape(np.asarray(far_R, np.float64), (-1, 1))
  s = (np.arange(per_ray) + rng.uniform(size=(len(near), per_ray))) / per_ray
  t = near + s * (far - near)
  points = np.asarray(origins_Rx3, np.float64)[:, None] + t[..., None] * np.asarray(directions_Rx3, np.float64)[:, None]
  return points.reshape(-1, 3).astype(np.float32)


def ray_samples(poses_Fx4x4, cams, near: float, far: float, bound: float | None, num_rays: int = 4096,
                per_ray: int = 32, seed: int = 0, pixel_center: float = 0.5) -> np.ndarray:
  """(at most num_rays * per_ray, 3) float32: the sample cloud the balanced cut splits: `num_rays` pixels drawn
  from the training frames (poses (F, 4, 4), their Cameras) with a fixed seed, each ray's [near, far] clipped to
  the hash grid's box [-bound, bound]^3 (where the model samples it; bound None: not clipped) and `per_ray`
  stratified points along it (a ray that misses the box: none). A pure function of its arguments: every
  process of a run, and a resumed run, draws the same cloud."""
  rng = np.random.default_rng(seed)
  frames = rng.integers(0, len(poses_Fx4x4), num_rays)
  rows = np.floor(rng.uniform(size=num_rays) * cams.height[frames]).astype(np.int64)
  cols = np.floor(rng.uniform(size=num_rays) * cams.width[frames]).astype(np.int64)
  origins, directions = nerf_cameras.frame_rays(np.asarray(poses_Fx4x4)[frames], cams, frames, rows, cols,
                                                pixel_center)
  if bound is None:
    lo, hi = np.full((num_rays, 1), near, np.float32), np.full((num_rays, 1), far, np.float32)
  else:
    clip = jax.jit(sampling.clip_to_box, static_argnums=(2, 3, 4))  # (one program, not one per operation)
    lo, hi = (np.asarray(v) for v in clip(jnp.asarray(origins), jnp.asarray(directions), near, far, bound))
  inside = (hi - lo)[:, 0] > 2e-3  # a ray that misses the box gets [near, near + 1e-3]: it samples nothing
  return stratified_points(origins[inside], directions[inside], lo[inside], hi[inside], per_ray, rng)


def _inside(value, offset, closed):
  return (value < offset) | (closed & (value == offset))


def region_of(points_Nx3, partition: Partition):
  """(N,) int32: the region each point lies in."""
  values = jnp.einsum("kpc,nc->nkp", jnp.asarray(partition.normals_KxPx3), points_Nx3)
  inside = jnp.all(_inside(values, partition.offsets_KxP, partition.closed_KxP), axis=-1)
  return jnp.argmax(inside, axis=-1).astype(jnp.int32)


def cells(partition: Partition, bound: float) -> list[np.ndarray]:
  """Each region's cell in the ground plane within the square [-bound, bound]^2: a convex polygon (M, 2),
  its corners counter-clockwise ((0, 2) where the region misses the square). The regions are columns along
  z (grid, voronoi: every plane's normal lies in the ground plane), so this polygon times any height is the
  region within a box. The square clipped by each of the region's half-planes in turn (Sutherland-Hodgman);
  which side holds a boundary does not change the polygon."""
  square = np.array([[-bound, -bound], [bound, -bound], [bound, bound], [-bound, bound]], np.float64)
  out = []
  for normals, offsets in zip(np.asarray(partition.normals_KxPx3, np.float64), np.asarray(partition.offsets_KxP,
                                                                                          np.float64)):
    if np.any(normals[:, 2]):
      raise ValueError("cells: a region plane is not vertical (its normal has a z component)")
    polygon = square
    for normal, offset in zip(normals[:, :2], offsets):
      if not np.any(normal) or len(polygon) == 0:
        continue  # padding (0 . x <= 1: all of space)
      gap = offset - polygon @ normal  # > 0 inside
      kept = []
      for i in range(len(polygon)):
        a, b, ga, gb = polygon[i], polygon[(i + 1) % len(polygon)], gap[i], gap[(i + 1) % len(polygon)]
        if ga >= 0:
          kept.append(a)
        if (ga > 0 and gb < 0) or (ga < 0 and gb > 0):  # the edge crosses the line: keep the crossing
          kept.append(a + (b - a) * (ga / (ga - gb)))
      polygon = np.array(kept).reshape(-1, 2)
    if len(polygon) < 3:
      polygon = np.zeros((0, 2))
    out.append(polygon)
  return out


def boxes(partition: Partition, bound: float, margin: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
  """(centres (K, 3), half_extents (K, 3)) float32: each region's own box, where its field lives: its cell's
  bounds in the ground plane within [-bound, bound]^2 (cells) and the whole height [-bound, bound], grown by
  `margin` x bound on every side, so that samples on a cell's boundary stay inside its box whatever the
  rounding. (A region that misses the square keeps the whole box.)"""
  centres, halves = [], []
  for polygon in cells(partition, bound):
    low, high = (polygon.min(0), polygon.max(0)) if len(polygon) else (np.full(2, -bound), np.full(2, bound))
    centres.append([*(0.5 * (low + high)), 0.0])
    halves.append([*(0.5 * (high - low) + margin * bound), (1.0 + margin) * bound])
  return np.float32(centres), np.float32(halves)


def to_box(points_Nx3, centre_3, half_3, bound: float):
  """Points of a region's box (centre, half extents) mapped onto the field's box [-bound, bound]^3, axis by
  axis: each region's field spends all its resolution on its own box (NeRF-XL: each region a field over its
  own bounds), not on the whole scene's."""
  return (points_Nx3 - centre_3) * (bound / half_3)


def unseen(partition: Partition, origins_Rx3, directions_Rx3, near, far) -> list[int]:
  """The regions that none of the rays crosses over a positive length of its [near, far] (near/far: floats or
  (R, 1)): regions whose fields no training pixel could ever teach."""
  t_in, t_out = jax.jit(segments)(jnp.asarray(origins_Rx3, jnp.float32), jnp.asarray(directions_Rx3, jnp.float32),
                                  near, far, partition)  # (one program, not each operation compiled on its own)
  crossed = np.any(np.asarray(t_out) > np.asarray(t_in), axis=-1)
  return [int(k) for k in np.flatnonzero(~crossed)]


def segments(origins_Rx3, directions_Rx3, near, far, partition: Partition):
  """(t_in, t_out), each (K, R): the part of each ray's [near, far] inside each region (near/far floats or
  (R, 1)). A convex region meets a line on one interval: the latest of the planes the ray enters through and
  the earliest it leaves through (the slab method, generalised to any planes). A region the ray misses (or
  meets on nothing longer than a point) gets [far, far]. No gradient flows through the segments."""
  normals = jnp.asarray(partition.normals_KxPx3)
  nd = jnp.einsum("kpc,rc->krp", normals, directions_Rx3)
  gap = partition.offsets_KxP[:, None, :] - jnp.einsum("kpc,rc->krp", normals, origins_Rx3)  # b - n . o
  parallel = jnp.abs(nd) < _PARALLEL
  cross = gap / jnp.where(parallel, 1.0, nd)
  inf = jnp.inf
  enter = jnp.max(jnp.where(~parallel & (nd < 0), cross, -inf), axis=-1)
  leave = jnp.min(jnp.where(~parallel & (nd > 0), cross, inf), axis=-1)
  outside = jnp.any(parallel & ~_inside(0.0, gap, partition.closed_KxP[:, None, :]), axis=-1)
  near_R = jnp.broadcast_to(jnp.reshape(jnp.asarray(near, jnp.float32), (-1,)), enter.shape[1:])
  far_R = jnp.broadcast_to(jnp.reshape(jnp.asarray(far, jnp.float32), (-1,)), enter.shape[1:])
  t_in = jnp.maximum(enter, near_R)
  t_out = jnp.minimum(leave, far_R)
  empty = outside | (t_out <= t_in)
  t_in, t_out = jnp.where(empty, far_R, t_in), jnp.where(empty, far_R, t_out)
  return jax.lax.stop_gradient(t_in), jax.lax.stop_gradient(t_out)


def segments_one_by_one(origins_Rx3, directions_Rx3, near, far, planes):
  """`segments` ((t_in, t_out), each (L, R)) of the L regions whose planes are `planes` (a Partition's three
  arrays, e.g. a device's own regions'), cut region by region (a vmap of one region's `segments`), as the region
  step cuts them: what decides which segments are present (NeRF's region rendering, `segment_counts`)."""
  return jax.vmap(lambda n, o, c: tuple(t[0] for t in segments(
      origins_Rx3, directions_Rx3, near, far, Partition(n[None], o[None], c[None]))))(*planes)


def partial_sums(rgb_RxSx3, sigma_RxS, t_RxS, deltas_RxS, directions_Rx3, s_edges_RxS1=None):
  """One region's per-ray partial sums of its S samples, each at t holding over an interval of (ray-parameter)
  length `deltas`, composited from transmittance 1 at the segment's start: a dict of
  rgb (R, 3)            sum_i w_i c_i (no background)
  optical_depth (R,)    sum_i sigma_i delta_i |d|: the segment's transmittance is exp(-optical_depth)
  depth, acc (R,)       sum_i w_i t_i, sum_i w_i
  weights (R, S)        w_i = (1 - exp(-tau_i)) exp(-sum_{j<i} tau_j), the segment's own (not gathered)
  and with `s_edges` (the samples' intervals in the normalised distance s), the distortion loss's sums:
  distortion (R,)       stepfun.distortion_loss of the segment's own weights
  moment (R,)           sum_i w_i m_i, m the intervals' midpoints in s
  """
  tau = sigma_RxS * deltas_RxS * jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
  accumulated = jnp.concatenate([jnp.zeros_like(tau[..., :1]), jnp.cumsum(tau[..., :-1], axis=-1)], axis=-1)
  weights = (1.0 - jnp.exp(-tau)) * jnp.exp(-accumulated)
  out = {"rgb": jnp.sum(weights[..., None] * rgb_RxSx3, axis=-2), "optical_depth": jnp.sum(tau, axis=-1),
         "depth": jnp.sum(weights * t_RxS, axis=-1), "acc": jnp.sum(weights, axis=-1), "weights": weights}
  if s_edges_RxS1 is not None:
    mids = 0.5 * (s_edges_RxS1[..., 1:] + s_edges_RxS1[..., :-1])
    out["distortion"] = stepfun.distortion_loss(s_edges_RxS1, weights)
    out["moment"] = jnp.sum(weights * mids, axis=-1)
  return out


# The partial sums that cross devices: per region and ray, a few numbers each (the weights stay local).
GATHERED = ("t_in", "rgb", "optical_depth", "depth", "acc", "distortion", "moment")


def capacity_rows(fraction: float, rays: int) -> int:
  """C, the static rows each region renders of `rays` rays (model.region_capacity = `fraction` in (0, 1]):
  ceil(fraction x rays) rounded up to a multiple of 8, and never more than `rays`."""
  if not 0.0 < fraction <= 1.0 or rays < 1:
    raise ValueError(f"capacity_rows: the fraction must be in (0, 1] and the rays >= 1, got {fraction}, {rays}")
  return min(rays, -(-int(np.ceil(fraction * rays)) // 8) * 8)


def pixel_rays(poses_Fx4x4, cams, num_rays: int, seed, pixel_center: float = 0.5):
  """(origins, directions), each (num_rays, 3) float32: the rays through `num_rays` pixels of the frames (poses
  (F, 4, 4), their Cameras), drawn uniformly over every pixel of every frame, with replacement, from a NumPy
  generator seeded with `seed` (an int, or a sequence: the pipeline's [seed, step] gives that step's batch):
  as the training pipeline draws a batch (nerfpod/data.py), so that what these rays show of the regions a
  batch shows too. A pure function of its arguments."""
  rng = np.random.default_rng(seed)
  offsets = np.concatenate([[0], np.cumsum(cams.num_pixels)]).astype(np.int64)
  flat = rng.integers(0, offsets[-1], num_rays, dtype=np.int64)
  frames = np.searchsorted(offsets, flat, side="right") - 1
  rows, cols = np.divmod(flat - offsets[frames], cams.width[frames])
  return nerf_cameras.frame_rays(np.asarray(poses_Fx4x4)[frames], cams, frames, rows, cols, pixel_center)


def segment_counts(origins_Rx3, directions_Rx3, near: float, far: float, partition: Partition,
                   bound: float | None = None, chunk: int = 8192, classes: int = 0,
                   spacing: str = "linear") -> np.ndarray:
  """(K,) int64: how many of the rays have a segment in each region that is not empty, cut as the region step
  cuts them (NeRF's region rendering; `dispatch`'s present): each ray's [near, far] clipped to the hash grid's
  box [-bound, bound]^3 (sampling.clip_to_box; `bound` None: a field without a box, not clipped), then each
  region's `segments`, region by region as the step's vmap cuts them. The rays go through one compiled
  program in chunks of `chunk` (the last one padded, the padding not counted). With `classes` J > 1
  (model.region_split), (K, J): the counts per sample class (`sample_classes` of `segment_shares` under the
  model's `spacing`)."""
  total = len(origins_Rx3)
  padded = -(-max(total, 1) // chunk) * chunk
  pad = lambda x: np.concatenate([np.asarray(x, np.float32), np.ones((padded - total, 3), np.float32)])  # noqa: E731
  origins, directions = pad(origins_Rx3), pad(directions_Rx3)
  valid = np.arange(padded) < total
  planes = tuple(np.asarray(a) for a in partition)  # (constants of the program below)

  @jax.jit
  def count(o, d, keep):
    lo, hi = (near, far) if bound is None else sampling.clip_to_box(o, d, near, far, bound)
    lo = jnp.broadcast_to(jnp.asarray(lo, jnp.float32), (o.shape[0], 1))
    hi = jnp.broadcast_to(jnp.asarray(hi, jnp.float32), (o.shape[0], 1))
    t_in, t_out = segments_one_by_one(o, d, lo, hi, planes)
    present = (t_out > t_in) & keep
    if classes <= 1:
      return jnp.sum(present, axis=1, dtype=jnp.int32)
    klass = sample_classes(segment_shares(t_in, t_out, lo, hi, spacing), classes)
    return jnp.stack([jnp.sum(present & (klass == j), axis=1, dtype=jnp.int32) for j in range(classes)], axis=1)

  counts = [np.asarray(count(origins[i:i + chunk], directions[i:i + chunk], valid[i:i + chunk]))
            for i in range(0, padded, chunk)]
  return np.sum(counts, axis=0, dtype=np.int64)


# model.region_capacity=auto's margin over the fullest region's share p of the training rays, for a chip's R rays
# (one micro-batch's): AUTO_SIGMAS standard deviations sqrt(p (1 - p) / R) of a batch's share (binomial), and
# AUTO_FLOOR, which also covers the measured share's own error (under 0.002 for 65,536 rays).
AUTO_SIGMAS, AUTO_FLOOR = 4.0, 0.01


def auto_fraction(share: float, rays: int) -> float:
  """model.region_capacity=auto's fraction F of `rays` R (a chip's rows per region and micro-batch) from the
  fullest region's `share` p of the training rays: p + AUTO_SIGMAS sqrt(p (1 - p) / R) + AUTO_FLOOR, rounded up
  to a thousandth, at most 1. Each of a chip's R rays meets the region with probability p, so its count is
  binomial; one 4 standard deviations over the mean comes about 3 times in 100,000 (region, chip, step)s,
  each time over capacity by a ray or so, far under the 0.1% of its rays a run may drop."""
  if not 0.0 <= share <= 1.0 or rays < 1:
    raise ValueError(f"auto_fraction: the share must be in [0, 1] and the rays >= 1, got {share}, {rays}")
  margin = AUTO_SIGMAS * np.sqrt(share * (1.0 - share) / rays) + AUTO_FLOOR
  return min(1.0, float(np.ceil(round((share + margin) * 1000, 6))) / 1000)


class Dispatch(NamedTuple):
  """Which rays each of L regions renders within a capacity of C rows (`dispatch`): the rays whose segment in
  the region is not empty, the first C of them in ray order.
  rows_LxC     the ray each row renders; R (no ray) in the rows left over
  slots_LxR    the row of each ray's segment; C where it has none (an empty segment, or one over capacity)
  present_LxR  the ray's segment in the region is not empty
  dropped_LxR  ... and found no row: over capacity"""
  rows_LxC: jax.Array
  slots_LxR: jax.Array
  present_LxR: jax.Array
  dropped_LxR: jax.Array

  @property
  def capacity(self) -> int:
    return self.rows_LxC.shape[1]


def dispatch(t_in_LxR, t_out_LxR, capacity: int) -> Dispatch:
  """The rows of L regions' segments (t_in, t_out), each (L, R) as `segments` gives them, within `capacity`
  rows per region: a static-shape compaction (each present segment's row is the count of present segments
  before it in ray order, from a cumulative sum; the rows are scattered from it)."""
  return dispatch_present(t_out_LxR > t_in_LxR, capacity)


def dispatch_present(present, capacity: int) -> Dispatch:
  """`dispatch` of the segments `present` (L, R) marks (e.g. one sample class's: `sample_classes`)."""
  count, rays = present.shape
  slots = jnp.cumsum(present, axis=1, dtype=jnp.int32) - 1
  fits = present & (slots < capacity)
  slots = jnp.where(fits, slots, capacity)
  rows = jnp.full((count, capacity), rays, jnp.int32).at[jnp.arange(count)[:, None], slots].set(
      jnp.broadcast_to(jnp.arange(rays, dtype=jnp.int32), slots.shape), mode="drop")  # (row C: none, dropped)
  return Dispatch(rows, slots, present, present & ~fits)


def gather_rows(x, d: Dispatch, per_region: bool = False):
  """Each region's rows of `x` (L, C, ...): x (R, ...), the same for every region, or with `per_region`
  (L, R, ...), each region's own. A row left over takes the last ray's values (its rendering is never put
  back)."""
  rows = jnp.minimum(d.rows_LxC, d.slots_LxR.shape[1] - 1)
  if per_region:
    return jnp.take_along_axis(x, rows.reshape(rows.shape + (1,) * (x.ndim - 2)), axis=1)
  return x[rows]


def scatter_rows(x_LxC, d: Dispatch, absent):
  """The rows' values (L, C, ...) put back into their rays (L, R, ...); a ray with no row in a region takes
  `absent` there (broadcast against (L, R, ...)): what an empty segment gives, so the rays' sums are the
  dense rendering's. (A gather of each ray's row: its transpose adds each ray's cotangent into its row.)"""
  slots = jnp.minimum(d.slots_LxR, d.capacity - 1)
  picked = jnp.take_along_axis(x_LxC, slots.reshape(slots.shape + (1,) * (x_LxC.ndim - 2)), axis=1)
  has_row = (d.slots_LxR < d.capacity).reshape(slots.shape + (1,) * (x_LxC.ndim - 2))
  return jnp.where(has_row, picked, jnp.asarray(absent, x_LxC.dtype))


def scatter_classes(x_per_class, dispatches, absent):
  """`scatter_rows` of several sample classes' rows (each (L, C_j, ...) with its Dispatch) into one (L, R, ...):
  each segment takes its own class's row (a segment is of one class only), else `absent`."""
  out = absent
  for x, d in zip(x_per_class, dispatches):
    out = scatter_rows(x, d, out)
  return out


# model.region_split=J: sample class j renders a segment with 2^-j of the configured samples (every round's, at
# least 1), and a segment takes the class of its share of the ray: the smallest 2^-j at least its share.
def class_fractions(classes: int) -> tuple:
  """The sample fractions (1, 1/2, ..., 2^-(J-1)) of `classes` J (0 or 1: one class, every sample)."""
  return tuple(2.0**-j for j in range(max(classes, 1)))


def class_counts(counts: tuple, fraction: float) -> tuple:
  """Each sampling round's count of `counts` at a class's `fraction`: ceil(count x fraction), at least 1."""
  return tuple(max(1, int(np.ceil(n * fraction))) for n in counts)


def class_samples(counts: tuple, classes: int) -> tuple:
  """A row's field samples in each of `classes` sample classes (every round's class_counts, summed)."""
  return tuple(sum(class_counts(counts, f)) for f in class_fractions(classes))


def class_capacities(capacity: float, classes: int, split_capacity: tuple = ()) -> tuple:
  """The capacity fractions of `classes` sample classes (model.region_split): `split_capacity`
  (model.region_split_capacity), or `capacity` (model.region_capacity) for every class; () without a split or
  without a capacity (dense)."""
  if classes <= 1 or not capacity:
    return ()
  return tuple(float(f) for f in split_capacity) or (float(capacity),) * classes


def final_capacities(capacities: tuple) -> tuple:
  """model.region_split_by=weights: the rows of the NeRF field's sample classes from the length classes' C_j
  (the proposal rounds'): C_j for every class but the last, which has every row of the proposal rounds (their
  sum), so that a class over its rows hands its segments down (downgrade_dispatch) and the last holds them all."""
  return tuple(capacities[:-1]) + (sum(capacities),)


def split_evals(counts: tuple, capacities: tuple, by: str = "length") -> int:
  """The field evaluations of a region's rows in the split step: `capacities` C_j rows of each length class at
  every round's class_counts (`by` 'length'), or (`by` 'weights') the proposal rounds so and the NeRF round over
  final_capacities' rows at each class's count."""
  per_class = [class_counts(counts, f) for f in class_fractions(len(capacities))]
  if by == "length":
    return sum(c * sum(n) for c, n in zip(capacities, per_class))
  return (sum(c * sum(n[:-1]) for c, n in zip(capacities, per_class))
          + sum(c * n[-1] for c, n in zip(final_capacities(capacities), per_class)))


def weight_shares(opacity_KxR, t_in_KxR):
  """Each segment's share of its ray's weight (K, R): its opacity alpha_k (the proposal's weights of the
  segment summed, from transmittance 1) times the transmittance of the segments before it in ray order
  (prod (1 - alpha_j), sorted by t_in): the part of the ray's light the segment stops. An empty segment (alpha 0,
  t_in at the far bound) takes 0 and changes no other's."""
  order = jnp.argsort(t_in_KxR, axis=0)
  alpha = jnp.take_along_axis(opacity_KxR, order, axis=0)
  through = jnp.cumprod(1.0 - alpha, axis=0)
  before = jnp.concatenate([jnp.ones_like(through[:1]), through[:-1]], axis=0)
  return jnp.take_along_axis(before * alpha, jnp.argsort(order, axis=0), axis=0)


def downgrade_dispatch(klass_LxR, rendered_LxR, capacities: tuple) -> list:
  """The NeRF round's Dispatch of each sample class (model.region_split_by=weights): class j takes the segments
  `rendered` of its class `klass` and those class j - 1 had no row for, the first C_j in ray order; the rest go
  on to class j + 1 (fewer samples, never a dropped ray). The last class's capacity must hold every rendered
  segment (final_capacities). A Dispatch's `dropped` are its segments handed down."""
  out, handed = [], jnp.zeros_like(rendered_LxR)
  for j, capacity in enumerate(capacities):
    d = dispatch_present(rendered_LxR & ((klass_LxR == j) | handed), capacity)
    out.append(d)
    handed = d.dropped_LxR
  return out


def segment_shares(t_in_LxR, t_out_LxR, near_R1, far_R1, spacing: str):
  """Each segment's share of its ray (L, R): its length in the normalised distance s of the ray's [near, far]
  (coord.t_to_s under the model's `spacing`), as the region's renderer maps it (0 for an empty segment)."""
  to_s = lambda t: jnp.clip(coord.t_to_s(t, near_R1[..., 0], far_R1[..., 0], spacing), 0.0, 1.0)  # noqa: E731
  return jnp.maximum(to_s(t_out_LxR) - to_s(t_in_LxR), 0.0)


# A share within this factor above 2^-j counts as at most 2^-j: a symmetric scene's shares fall on 1/2 exactly,
# where float rounding (another compiled program: another mesh) would otherwise pick either class.
CLASS_EDGE = 1.0 + 2.0**-10


def sample_classes(share_LxR, classes: int):
  """Each segment's sample class (L, R) int32 from its `share` of the ray (its length in the normalised distance
  s, where the first proposal round draws evenly): the largest j < `classes` with 2^-j >= share (to within
  CLASS_EDGE), so a segment gets at least about its share of the ray's samples (a segment shorter than
  2^-(J-1) takes the last class)."""
  return sum((share_LxR <= 2.0**-j * CLASS_EDGE).astype(jnp.int32) for j in range(1, classes))


def empty_sums(far_R, key: str):
  """What `partial_sums` (and the segment's start) give a ray's empty segment [far, far], per key of
  GATHERED: its start t_in = far (the ray's far bound, (R,)); every sum 0 (its samples' weights are 0: each
  interval has length 0). The interlevel loss of an empty segment is 0 too (no NeRF weight to bound)."""
  return far_R if key == "t_in" else 0.0


def composite_regions(partials, background=None):
  """The K regions' partial sums of each ray (a dict of (K, R, ...) arrays: partial_sums' and `t_in` (K, R),
  each segment's start) composited in the order the ray meets them (sorted by t_in):
  C = sum_k P_k C_k + P_K background, P_k = prod of the transmittances T_j of the segments before k, and
  depth and acc likewise. Returns rgb (R, 3), depth, acc, disparity (R,); `prefix` (K, R), each region's P_k
  in the regions' own order (what reaches region k); and with the distortion sums, `distortion` (R,): the
  whole ray's mip-NeRF 360 distortion loss, sum_k P_k^2 D_k + 2 sum_{a before b} P_a P_b (W_a M_b - M_a W_b)
  (W the segment's sum of weights, M of weights times midpoints: every midpoint of a lies before every one
  of b). `background`: (3,) or (R, 3), or None."""
  order = jnp.argsort(partials["t_in"], axis=0)
  ordered = {k: jnp.take_along_axis(v, order.reshape(order.shape + (1,) * (v.ndim - 2)), axis=0)
             for k, v in partials.items() if k in GATHERED}
  od = ordered["optical_depth"]
  before = jnp.cumsum(od, axis=0) - od  # optical depth of the segments before each, in ray order
  prefix = jnp.exp(-before)
  rgb = jnp.sum(prefix[..., None] * ordered["rgb"], axis=0)
  acc = jnp.sum(prefix * ordered["acc"], axis=0)
  depth = jnp.sum(prefix * ordered["depth"], axis=0)
  if background is not None:
    rgb = rgb + jnp.exp(-jnp.sum(od, axis=0))[..., None] * jnp.asarray(background, rgb.dtype)
  out = {"rgb": rgb, "depth": depth, "acc": acc, "disparity": acc / jnp.maximum(depth, 1e-10)}
  # Back to the regions' own order: the inverse permutation scatters each ray's k-th segment to its region.
  inverse = jnp.argsort(order, axis=0)
  out["prefix"] = jnp.take_along_axis(prefix, inverse, axis=0)
  if "distortion" in ordered:
    w, m = prefix * ordered["acc"], prefix * ordered["moment"]
    w_before = jnp.cumsum(w, axis=0) - w
    m_before = jnp.cumsum(m, axis=0) - m
    out["distortion"] = (jnp.sum(prefix**2 * ordered["distortion"], axis=0)
                         + 2.0 * jnp.sum(w_before * m - m_before * w, axis=0))
  return out


def interlevel_loss(edges_RxB1, weights_RxB, env_edges_RxK1, env_weights_RxK, prefix_R, radius: float | None = None):
  """mip-NeRF 360's interlevel loss (stepfun.interlevel_loss) of one segment, per ray (R,): the NeRF's and
  the proposal's histograms of the segment (their own weights, from transmittance 1) both scaled by
  `prefix_R`, the NeRF's transmittance before the segment (composite_regions' prefix). Summed over the
  segments, this is the whole ray's loss where each proposal's transmittance before a segment equals the
  NeRF's; docs/scale.md says what differs otherwise. Pass the NeRF's weights and the prefix through
  stop_gradient (the NeRF is the proposals' target). With `radius`, Zip-NeRF's anti-aliased form
  (stepfun.blurred_interlevel_loss) of the segment, scaled alike."""
  scale = prefix_R[..., None]
  return stepfun.interlevel_loss(edges_RxB1, scale * weights_RxB, env_edges_RxK1, scale * env_weights_RxK, radius)
