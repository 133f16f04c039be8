"""Regions (nerf/regions.py): K regions each rendering its own segment, composited in ray order, against one
rendering of the stitched field (region k's field inside region k) on the same samples."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nerfpod.nerf import compositing, regions, stepfun

# (Jitted: one program each per shape, not each of their operations compiled on its own.)
_segments, _region_of = jax.jit(regions.segments), jax.jit(regions.region_of)

NEAR, FAR, SAMPLES = 0.0, 6.0, 8


def _fields(count, seed=0):
  """Per region a small analytic field: sigma = softplus(a . x + b), rgb = sigmoid(C x + e), stacked."""
  rng = np.random.default_rng(seed)
  return {"a": jnp.asarray(rng.normal(size=(count, 3)), jnp.float32),
          "b": jnp.asarray(rng.normal(size=(count,)), jnp.float32),
          "c": jnp.asarray(rng.normal(size=(count, 3, 3)), jnp.float32),
          "e": jnp.asarray(rng.normal(size=(count, 3)), jnp.float32)}


def _field(params, points_Nx3):
  """One region's field (params unstacked)."""
  sigma = jax.nn.softplus(points_Nx3 @ params["a"] + params["b"])
  rgb = jax.nn.sigmoid(points_Nx3 @ params["c"].T + params["e"])
  return rgb, sigma


def _stitched(params, points_Nx3, partition):
  """The field that is region k's inside region k."""
  which = _region_of(points_Nx3, partition)
  picked = jax.tree.map(lambda p: p[which], params)
  return jax.vmap(_field)(picked, points_Nx3)


def _segment_edges(origins, directions, partition):
  """(K, R, S + 1) edges in t of each region's S equal intervals of its segment."""
  t_in, t_out = _segments(origins, directions, NEAR, FAR, partition)
  u = jnp.linspace(0.0, 1.0, SAMPLES + 1)
  return t_in[..., None] + u * (t_out - t_in)[..., None], t_in


def _by_regions(params, origins, directions, partition, background):
  edges, t_in = _segment_edges(origins, directions, partition)

  def one(region_params, edges_RxS1):
    mids = 0.5 * (edges_RxS1[:, 1:] + edges_RxS1[:, :-1])
    points = origins[:, None] + mids[..., None] * directions[:, None]
    rgb, sigma = _field(region_params, points.reshape(-1, 3))
    s_edges = (edges_RxS1 - NEAR) / (FAR - NEAR)
    return regions.partial_sums(rgb.reshape(points.shape), sigma.reshape(mids.shape), mids,
                                jnp.diff(edges_RxS1, axis=-1), directions, s_edges)

  partials = jax.vmap(one)(params, edges)
  partials["t_in"] = t_in
  return regions.composite_regions(partials, background)


def _stitched_render(params, origins, directions, partition, background):
  """One rendering of the stitched field over the union of the regions' samples (in ray order)."""
  edges, t_in = _segment_edges(origins, directions, partition)
  order = jnp.argsort(t_in, axis=0)
  edges = jnp.take_along_axis(edges, order[..., None], axis=0)  # (K, R, S + 1), in ray order
  union = jnp.concatenate([jnp.moveaxis(edges[:, :, :-1], 0, 1).reshape(len(origins), -1),
                           jnp.full((len(origins), 1), FAR)], axis=-1)
  mids = 0.5 * (union[:, 1:] + union[:, :-1])
  points = origins[:, None] + mids[..., None] * directions[:, None]
  rgb, sigma = _stitched(params, points.reshape(-1, 3), partition)
  out = compositing.composite_intervals(rgb.reshape(points.shape), sigma.reshape(mids.shape), union, directions,
                                        background=background)
  out["distortion"] = stepfun.distortion_loss((union - NEAR) / (FAR - NEAR), out["weights"])
  out["union"] = union
  return out


def _rays(kind):
  rng = np.random.default_rng(3)
  if kind == "random":
    origins = rng.uniform(-3, 3, (64, 3))
    directions = rng.normal(size=(64, 3))
  elif kind == "designed":
    origins = np.array([[0.5, 0.5, 3.0],      # straight down a column: parallel to every boundary, 1 region
                        [-2.0, 0.5, 0.3],     # across x = 0: 2 regions
                        [-2.0, -1.5, 0.0],    # across x = 0 and y = 0 at different places: 3 regions
                        [0.3, 0.3, 0.0],      # starts inside a region (near = 0)
                        [0.0, -2.0, 0.5],     # along the plane x = 0 itself: parallel, on the boundary
                        [-3.0, 0.1, 0.0]])    # along x through every cell of a row
    directions = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.1], [1.0, 0.8, 0.0], [0.4, 0.7, 0.2],
                           [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
  return jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32)


PARTITIONS = {"grid4": regions.grid(4, 1.0), "grid3": regions.grid(3, 1.5), "grid1": regions.grid(1, 1.0),
              "voronoi3": regions.voronoi([[0.0, 1.0], [-1.0, -0.5], [1.2, -0.4]])}


def test_grid_and_voronoi_cells_hold_every_point_once():
  points = np.random.default_rng(0).uniform(-3, 3, (2000, 3)).astype(np.float32)  # (NumPy: read on the host)
  partition = regions.grid(6, 1.5)
  assert regions.grid_shape(6) == (3, 2) and partition.size == 6
  which = np.asarray(_region_of(points, partition))
  column = np.clip(np.floor((points[:, 0] + 1.5) / 1.0), 0, 2)
  row = np.clip(np.floor((points[:, 1] + 1.5) / 1.5), 0, 1)
  np.testing.assert_array_equal(which, row * 3 + column)
  centres = np.array([[0.0, 1.0], [-1.0, -0.5], [1.2, -0.4]])
  nearest = np.argmin(np.sum((points[:, None, :2] - centres[None])**2, -1), axis=1)
  np.testing.assert_array_equal(np.asarray(_region_of(points, regions.voronoi(centres))), nearest)
  # On a shared boundary exactly, one region only (the lower cell holds nothing of its upper cut).
  on_cut = jnp.array([[0.0, 0.2, 0.0], [-0.5, 0.0, 0.0]])
  assert list(np.asarray(_region_of(on_cut, regions.grid(4, 1.0)))) == [3, 2]


def test_kmeans_finds_separated_clusters():
  rng = np.random.default_rng(0)
  centres = np.array([[5.0, 0.0], [-5.0, 0.0], [0.0, 5.0]])
  points = np.concatenate([c + 0.1 * rng.normal(size=(30, 2)) for c in centres])
  found = regions.kmeans(points, 3)
  assert sorted(map(tuple, np.round(found))) == sorted(map(tuple, centres))


@pytest.mark.parametrize("name", sorted(PARTITIONS))
@pytest.mark.parametrize("kind", ["random", "designed"])
def test_segments_tile_each_ray_and_lie_in_their_regions(name, kind):
  partition = PARTITIONS[name]
  origins, directions = _rays(kind)
  t_in, t_out = map(np.asarray, _segments(origins, directions, NEAR, FAR, partition))
  assert np.all(t_in <= t_out)
  np.testing.assert_allclose(np.sum(t_out - t_in, axis=0), FAR - NEAR, rtol=1e-5)  # no gap, no overlap
  for k in range(partition.size):
    full = t_out[k] > t_in[k]
    mids = 0.5 * (t_in[k] + t_out[k])
    points = np.asarray(origins) + mids[:, None] * np.asarray(directions)
    assert np.all(np.asarray(_region_of(jnp.asarray(points), partition))[full] == k)
  if kind == "designed" and name == "grid4":
    crossed = np.sum(t_out > t_in, axis=0)
    assert list(crossed) == [1, 2, 3, 1, 2, 2]


# Each case compiles four programs (~5 s): two stay in the quick loop (a grid and Voronoi cells, one of each
# ray kind; the grid of 4 with the designed rays, one of which runs along its cut plane x = 0), the other six
# are in the slow set.
QUICK_COMPOSITES = {("grid4", "designed"), ("voronoi3", "random")}


@pytest.mark.parametrize("name,kind", [
    (name, kind) if (name, kind) in QUICK_COMPOSITES else pytest.param(name, kind, marks=pytest.mark.slow)
    for kind in ("random", "designed") for name in sorted(PARTITIONS)])
def test_regions_composite_to_the_stitched_field_values_and_gradients(name, kind):
  partition = PARTITIONS[name]
  origins, directions = _rays(kind)
  params = _fields(partition.size)
  background = jnp.array([0.2, 0.5, 0.9])
  mine = jax.jit(lambda p: _by_regions(p, origins, directions, partition, background))(params)
  whole = jax.jit(lambda p: _stitched_render(p, origins, directions, partition, background))(params)
  for key in ("rgb", "depth", "acc", "disparity", "distortion"):
    np.testing.assert_allclose(mine[key], whole[key], rtol=2e-5, atol=2e-6, err_msg=key)

  def loss(render):
    def f(params):
      out = render(params, origins, directions, partition, background)
      return (jnp.sum(out["rgb"] * jnp.array([1.0, -2.0, 0.5])) + 0.1 * jnp.sum(out["depth"])
              + jnp.sum(out["acc"]) + jnp.sum(out["distortion"]))
    return f

  grads_mine = jax.jit(jax.grad(loss(_by_regions)))(params)
  grads_whole = jax.jit(jax.grad(loss(_stitched_render)))(params)
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5), grads_mine, grads_whole)


def test_prefix_is_what_reaches_each_region_in_its_own_order():
  partition = PARTITIONS["grid3"]
  origins = jnp.array([[3.0, 0.0, 0.0]])
  directions = jnp.array([[-1.0, 0.0, 0.0]])  # meets the regions in the order 2, 1, 0
  partials = {"t_in": jnp.array([[4.0], [2.0], [0.0]]), "optical_depth": jnp.array([[0.3], [0.2], [0.1]]),
              "rgb": np.zeros((3, 1, 3), np.float32), "depth": np.zeros((3, 1), np.float32),
              "acc": np.zeros((3, 1), np.float32)}
  out = jax.jit(regions.composite_regions)(partials)  # one program rather than one per operation
  np.testing.assert_allclose(np.asarray(out["prefix"])[:, 0], np.exp(-np.array([0.3, 0.1, 0.0])), rtol=1e-6)
  del origins, directions


def test_interlevel_loss_per_segment_sums_to_the_whole_rays_where_the_prefixes_agree():
  """Each segment's proposal histogram, and the NeRF's intervals drawn from it (as the model draws them),
  from transmittance 1; the whole ray's histograms are theirs in ray order, each scaled by the prefix P_k
  (the NeRF's transmittance before the segment): the per-segment losses sum to the whole ray's."""
  rng = np.random.default_rng(1)
  rays, count = 16, 3
  bounds = np.sort(rng.uniform(0, 1, (rays, count - 1)), axis=-1)
  lo = np.concatenate([np.zeros((rays, 1)), bounds], -1).T  # (K, R): the segments tile [0, 1]
  hi = np.concatenate([bounds, np.ones((rays, 1))], -1).T
  prefix = np.cumprod(np.concatenate([np.ones((1, rays)), rng.uniform(0.2, 0.9, (count - 1, rays))]), 0)
  # Per segment: the proposal's weights, the jitter of the NeRF's intervals and the NeRF's weights.
  draws = [(rng.uniform(0, 0.2, (rays, 8)), rng.uniform(size=(rays, 6)), rng.uniform(0, 0.3, (rays, 6)))
           for _ in range(count)]

  def union(parts):  # edges in ray order, with a zero-weight interval over any gap between two segments
    edges, weights = [parts[0][0]], [parts[0][1]]
    for e, w in parts[1:]:
      edges.append(e)
      weights += [jnp.zeros((rays, 1)), w]
    return jnp.concatenate(edges, -1), jnp.concatenate(weights, -1)

  @jax.jit  # one program rather than one per operation (the arrays in float32, as jnp.asarray made them)
  def losses(lo, hi, prefix, draws):
    env, nerf, total = [], [], jnp.zeros(rays)
    for k, (env_weights, jitter, weights) in enumerate(draws):
      a, b = lo[k][:, None], hi[k][:, None]
      env_edges = a + (b - a) * jnp.linspace(0, 1, 9)
      edges = stepfun.sample_intervals(env_edges, env_weights, 6, jitter, domain=(a, b))
      total = total + regions.interlevel_loss(edges, weights, env_edges, env_weights, prefix[k])
      env.append((env_edges, prefix[k][:, None] * env_weights))
      nerf.append((edges, prefix[k][:, None] * weights))
    whole = stepfun.interlevel_loss(*union(nerf), *union(env))
    # Zip-NeRF's form (train.interlevel_blur) at radius 0, the NeRF's histogram resampled onto the proposal's
    # intervals: per segment it sums to the whole ray's too (a radius > 0 blurs weight across the segments'
    # ends, which no segment sees, so there the sum is the whole ray's less that).
    blurred = sum(regions.interlevel_loss(nerf[k][0], nerf[k][1] / prefix[k][:, None], env[k][0],
                                          env[k][1] / prefix[k][:, None], prefix[k], radius=0.0)
                  for k in range(count))
    whole_blurred = stepfun.blurred_interlevel_loss(*union(nerf), *union(env), 0.0)
    return total, whole, blurred, whole_blurred

  total, whole, blurred, whole_blurred = losses(lo, hi, prefix, draws)
  np.testing.assert_allclose(total, whole, rtol=1e-5, atol=1e-8)
  np.testing.assert_allclose(blurred, whole_blurred,
                             rtol=1e-4, atol=1e-8)
  assert np.all(np.abs(np.asarray(blurred) - np.asarray(total)) > 0)  # another loss than mip-NeRF 360's
