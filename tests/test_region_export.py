"""Exports that query a region model's field at points (model.regions, NeRF-XL): each point takes the field of the
region it lies in (its field over the region's own box), checked against a loop over the points; the regions'
boxes; the mesh and point cloud of a region model.

No training: the models' initial parameters (a random hash grid: a density that varies everywhere) are
restored as the exports restore a workdir's (nerfpod.run.trained.Trained, on a mesh of the 8 devices without a
region axis, as `nerfpod export` makes it)."""
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod import distributed
from nerfpod.export import mesh as mesh_export
from nerfpod.export import pointcloud, shared
from nerfpod.nerf import fields, regions
from nerfpod.run import components
from nerfpod.run.trained import Trained

BOUND = 1.5  # the hash grid's box: exports keep [-1.5, 1.5]^3


def _config(count: int, cut: str = "grid", box: str = "scene"):
  tiny = {"model.regions": count, "model.region_cut": cut, "model.region_box": box, "model.hashgrid.num_levels": 2,
          "model.hashgrid.log2_table_size": 6, "model.hashgrid.max_resolution": 32, "model.hashgrid.hidden_width": 8,
          "model.proposal.num_levels": 2, "model.proposal.log2_table_size": 6, "model.proposal.max_resolution": 32,
          "model.proposal.hidden_width": 8, "render.proposal_samples": (8,), "render.num_samples": 6,
          "model.hashgrid.bound": BOUND, "eval.chunk": 256}
  return smoke_config(**tiny)


def _trained(config, workdir) -> Trained:
  """What nerfpod.run.trained.restore gives for `config` (its components on every device, no region axis),
  holding random parameters (_scrambled) as step 0."""
  comps = components.build(config, distributed.make_mesh())
  return Trained(str(workdir), config, comps, _scrambled(comps.init_state().params), 0, np.eye(4))


@pytest.fixture(scope="module")
def models(tmp_path_factory):
  """{name: Trained}, built once for the module: 'one' (model.regions=1), 'grid' (4 regions, a 2 x 2 grid),
  'cameras' (4 regions cut around the training cameras) and 'own' (those, each field over its own box)."""
  folder = tmp_path_factory.mktemp("models")
  return {name: _trained(_config(*args), folder / name)
          for name, args in (("one", (1,)), ("grid", (4, "grid")), ("cameras", (4, "cameras")),
                             ("own", (4, "cameras", "own")))}


def _scrambled(params, seed=0):
  """Every parameter drawn from N(0, 0.5^2): fields whose density and colour vary across the box and from
  region to region (the initial hash grid's entries are near zero: an almost even density)."""
  leaves, treedef = jax.tree.flatten(params)
  rng = np.random.default_rng(seed)
  # (Cast in NumPy and put on the device as they are: no program per leaf.)
  return jax.tree.unflatten(treedef, [jax.device_put((0.5 * rng.normal(size=leaf.shape)).astype(leaf.dtype))
                                      for leaf in leaves])


def _points(partition, seed=0):
  """Points in every region, on their boundaries and just either side of them: random points of the box;
  points exactly on each boundary plane (a grid's cuts are exact in float32); and each of those moved 1e-4
  along the plane's normal either way."""
  rng = np.random.default_rng(seed)
  inner = rng.uniform(-BOUND, BOUND, (96, 3))
  planes = [(n, b) for ns, bs in zip(partition.normals_KxPx3, partition.offsets_KxP) for n, b in zip(ns, bs)
            if np.any(n)]
  on = []
  for normal, offset in planes:  # random points of the box projected onto the plane n . x = b
    unit = normal / np.linalg.norm(normal)
    p = rng.uniform(-BOUND, BOUND, (4, 3))
    on.append(p + ((offset - p @ normal) / np.dot(normal, normal))[:, None] * normal)
    on.append(on[-1] + 1e-4 * unit)
    on.append(on[-2] - 1e-4 * unit)
  return np.concatenate([inner] + on).astype(np.float32)


def _one_point(config):
  """(field params, box (centre (3,), half extents (3,)), point (3,), viewdir (3,)) -> (rgb (3,), sigma, outward
  unit normal (3,)) of one region's field at one world point, its box mapped onto the field's [-B, B]^3 axis
  by axis: the brute-force reference."""
  field = fields.make_field(config.model, jnp.float32)

  def apply(params, box, point, viewdir):
    centre, half = box
    return field.apply({"params": params}, ((point - centre) * (BOUND / half))[None], viewdir[None])

  def sigma(params, box, point, viewdir):
    return apply(params, box, point, viewdir)[1][0]

  def at(params, box, point, viewdir):
    gradient = jax.grad(sigma, argnums=2)(params, box, point, viewdir)
    rgb = apply(params, box, point, viewdir)[0][0]
    return rgb, sigma(params, box, point, viewdir), -gradient / jnp.maximum(jnp.linalg.norm(gradient), 1e-12)
  return jax.jit(at)


def test_each_region_has_its_own_box_around_its_cell():
  """A 2 x 2 grid's regions: boxes around their quarter of the ground square, the whole height, grown by 1% of
  the bound; the Voronoi cells of camera centres: every point of a cell maps into the field's box."""
  centres, halves = regions.boxes(regions.grid(4, BOUND), BOUND)
  np.testing.assert_allclose(np.abs(centres), [[BOUND / 2, BOUND / 2, 0]] * 4, atol=1e-6)
  assert sorted(map(tuple, np.sign(centres[:, :2]).tolist())) == [(-1, -1), (-1, 1), (1, -1), (1, 1)]
  np.testing.assert_allclose(halves, [[0.51 * BOUND, 0.51 * BOUND, 1.01 * BOUND]] * 4, rtol=1e-6)
  cut = regions.voronoi(np.float32([[0.3, 0.2], [-0.9, 0.4], [0.1, -1.1]]))
  centres, halves = regions.boxes(cut, BOUND)
  points = np.random.default_rng(4).uniform(-BOUND, BOUND, (4000, 3)).astype(np.float32)
  ids = np.asarray(jax.jit(lambda x: regions.region_of(x, cut))(points))  # one program, not one per operation
  local = (points - centres[ids]) * (BOUND / halves[ids])
  assert np.abs(local).max() <= BOUND and np.ptp(local[:, 0]) > BOUND  # inside, and spread over the box
  for k in range(3):  # each box is no larger than its cell's bounds (plus the margin)
    mine = points[ids == k, :2]
    np.testing.assert_allclose(centres[k, :2] - halves[k, :2], mine.min(0) - 0.01 * BOUND, atol=0.05)
    np.testing.assert_allclose(centres[k, :2] + halves[k, :2], mine.max(0) + 0.01 * BOUND, atol=0.05)


@pytest.mark.parametrize("cut", ["grid", "cameras", "own"])
def test_each_point_takes_the_field_of_its_own_region(cut, models):
  """The query of a 4-region model equals a loop over the points that applies, to each point alone, the field
  of the region nerf_regions.region_of puts it in: density, colour and normal, on both sides of every
  boundary and on it."""
  trained = models[cut]
  config = trained.config
  partition = trained.comps.model.partition
  points = _points(partition)
  rng = np.random.default_rng(1)
  viewdirs = rng.normal(size=points.shape).astype(np.float32)
  viewdirs /= np.linalg.norm(viewdirs, axis=1, keepdims=True)
  ids = np.asarray(jax.jit(lambda x: regions.region_of(x, partition))(points))  # one program, not one per operation
  assert sorted(set(ids.tolist())) == [0, 1, 2, 3]
  query = shared.FieldQuery(trained, 64)  # several chunks, each device's share meeting several regions
  rgb, sigma, normals = query.query(points, viewdirs)
  np.testing.assert_allclose(query.density(points), sigma, rtol=1e-6)
  # (On the host: a region's parameters sliced in NumPy, not by a program per leaf.)
  stacked = jax.tree.map(np.asarray, trained.params["params"]["regions"]["coarse"])
  centres, halves = trained.comps.model.region_boxes
  assert np.allclose(halves, BOUND) == (cut != "own")  # 'own': the cells' boxes, smaller than the field's
  at = _one_point(config)
  want = [at(jax.tree.map(lambda p: p[k], stacked), (centres[k], halves[k]), p, d)
          for k, p, d in zip(ids, points, viewdirs)]
  np.testing.assert_allclose(sigma, [float(w[1]) for w in want], rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(rgb, np.stack([w[0] for w in want]), rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(normals, np.stack([w[2] for w in want]), atol=1e-4)
  # The fields differ: a point near a boundary takes another density on its other side.
  other = np.array([float(at(jax.tree.map(lambda p: p[(k + 1) % 4], stacked), (centres[k], halves[k]), p, d)[1])
                    for k, p, d in zip(ids[:16], points[:16], viewdirs[:16])])
  assert np.abs(other - sigma[:16]).max() > 1e-3
  # The order the points are queried in changes nothing: reversed, each comes back with its own values.
  np.testing.assert_allclose(query.density(points[::-1])[::-1], sigma, rtol=1e-6)


def test_the_ground_order_puts_neighbours_together():
  """Blocks of 256 points in ground order (a device's share of a chunk) each meet 1 or 2 of a 4 x 4 grid's
  regions on average, where blocks of points in no order meet nearly all 16."""
  points = np.random.default_rng(3).uniform(-BOUND, BOUND, (32768, 3))
  order = shared.ground_order(points)
  assert sorted(order.tolist()) == list(range(len(points)))
  ids = np.asarray(jax.jit(lambda x: regions.region_of(x, regions.grid(16, BOUND)))(  # one program
      points.astype(np.float32)))
  met = lambda ids: np.mean([len(set(block.tolist())) for block in ids.reshape(-1, 256)])  # noqa: E731
  assert met(ids[order]) < 2 and met(ids) > 15


def _mesh_args(out, level, resolution=20):
  return types.SimpleNamespace(resolution=resolution, level=level, bound=0.0, normalized=True, out=str(out))


def test_a_region_models_mesh_and_point_cloud_are_valid(models, tmp_path):
  trimesh = pytest.importorskip("trimesh")
  pytest.importorskip("skimage")
  one, split = models["one"], models["grid"]
  assert one.comps.model.regions == 1
  probe = np.random.default_rng(0).uniform(-BOUND, BOUND, (4096, 3))
  level = float(np.median(shared.FieldQuery(split, 1024).density(probe)))
  meshes = {}
  for name, trained in (("one", one), ("four", split)):
    path = tmp_path / f"{name}.ply"
    summary = mesh_export.export(_mesh_args(path, level), trained, str(path))
    mesh = trimesh.load(path, process=False)
    assert len(mesh.faces) == summary["faces"] > 0 and len(mesh.vertices) == summary["vertices"]
    assert (np.abs(mesh.vertices) <= BOUND + 1e-5).all()
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)
    meshes[name] = mesh
  # A region model's own mesh crosses its regions' boundaries (x = 0 and y = 0 for a 2 x 2 grid).
  vertices = meshes["four"].vertices
  # Its vertices lie on the level set of the region field's density (up to the grid's interpolation): the
  # density there is far nearer the level than at random points (0.05 against 0.47 in log density, 2026-12-06).
  query = shared.FieldQuery(split, 1024)
  off = lambda points: np.median(np.abs(np.log(query.density(points)) - np.log(level)))  # noqa: E731
  assert off(np.asarray(vertices)) < 0.2 * off(probe)
  for axis in (0, 1):
    assert (vertices[:, axis] < 0).any() and (vertices[:, axis] > 0).any()
  # The point cloud: rendered by the region renderer, its normals by the region query.
  cloud = tmp_path / "cloud.ply"
  args = types.SimpleNamespace(num_points=200, min_opacity=0.01, split="train", bound=0.0, seed=0, normalized=True)
  summary = pointcloud.export(args, split, str(cloud))
  points = trimesh.load(cloud)
  assert len(points.vertices) == summary["points"] > 0
  assert (np.abs(points.vertices) <= BOUND + 1e-5).all()


def test_the_one_field_query_is_the_fields_own(models):
  """model.regions=1 queries the one field as before: the field applied to the points directly."""
  trained = models["one"]
  config = trained.config
  points = np.random.default_rng(2).uniform(-BOUND, BOUND, (500, 3)).astype(np.float32)
  field = fields.make_field(config.model, jnp.float32)
  rgb, sigma = jax.jit(lambda p, x, d: field.apply({"params": p}, x, d))(
      trained.params["params"]["coarse"], points, np.broadcast_to(np.float32([0, 0, -1]), points.shape))
  got_rgb, got_sigma, _ = shared.FieldQuery(trained, 128).query(points)
  np.testing.assert_allclose(got_sigma, sigma, rtol=1e-6, atol=1e-7)
  np.testing.assert_allclose(got_rgb, rgb, rtol=1e-6, atol=1e-7)
