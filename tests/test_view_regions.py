"""The viewer (nerfpod/view.py) draws a region model's regions (model.regions, NeRF-XL): what it adds to the
scene, read off viser's handles on the server (no browser): each region's cell, centre and label, and the
training cameras in their regions' colours. And the cells themselves (nerf/regions.py's cells)."""
import json

import jax
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod.nerf import regions
from nerfpod.workdir import files as workdir_files


def _area(polygon) -> float:
  x, y = polygon[:, 0], polygon[:, 1]
  return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))  # > 0: counter-clockwise


def test_a_grids_cells_are_its_squares_and_voronoi_cells_tile_the_square():
  cells = regions.cells(regions.grid(4, 1.5), 1.5)
  assert len(cells) == 4
  for cell, (x0, y0) in zip(cells, [(-1.5, -1.5), (0, -1.5), (-1.5, 0), (0, 0)]):  # x first, then y
    np.testing.assert_allclose(np.sort(cell, axis=0)[[0, -1]], [[x0, y0], [x0 + 1.5, y0 + 1.5]])
    assert _area(cell) == pytest.approx(2.25)
  centres = np.random.default_rng(0).uniform(-1, 1, (6, 2))
  partition = regions.voronoi(centres)
  cells = regions.cells(partition, 2.0)
  region_of = jax.jit(lambda x: regions.region_of(x, partition))  # one program rather than one per operation
  assert sum(_area(c) for c in cells) == pytest.approx(16.0, rel=1e-9)  # the square, no gap, no overlap
  for k, cell in enumerate(cells):
    assert _area(cell) > 0
    inside = np.append(cell.mean(0), 0.0)[None]
    assert int(np.asarray(region_of(inside.astype(np.float32)))[0]) == k
    # Every corner is at least as near to its own centre as to any other (the planes are float32).
    distances = np.linalg.norm(cell[:, None] - centres[None], axis=-1)
    assert (distances[:, k] <= distances.min(1) + 1e-6).all()
  # A region that misses the square: no polygon.
  far = regions.voronoi(np.array([[0.0, 0.0], [10.0, 0.0]]))
  assert [len(c) for c in regions.cells(far, 1.0)] == [4, 0]


@pytest.fixture(scope="module")
def region_viewer(tmp_path_factory):
  """A viewer (no browser) of a workdir as a run of 4 regions cut around the training cameras writes it at
  step 0: config.json, regions.json and a checkpoint of the initial state."""
  pytest.importorskip("viser", reason="viser is not installed (pip install 'nerfpod[viewer]')")
  from nerfpod import distributed, view
  from nerfpod.run import components
  from nerfpod.workdir import checkpoints
  config = smoke_config(**{"model.regions": 4, "model.region_cut": "cameras", "model.hashgrid.num_levels": 2,
                           "model.hashgrid.log2_table_size": 6, "model.proposal.num_levels": 2,
                           "model.proposal.log2_table_size": 6, "render.proposal_samples": (8,),
                           "render.num_samples": 6})
  workdir = tmp_path_factory.mktemp("regions") / "run"
  comps = components.build(config, distributed.make_mesh())
  workdir_files.write_config(str(workdir), json.loads(config.to_json_best_effort()))
  workdir_files.write_regions(str(workdir), config.model.region_cut, comps.model.region_planes)
  with checkpoints.Checkpoints(str(workdir), 10, 2) as ckpt:
    ckpt.save(0, comps.init_state(), {"next_step": 0}, force=True)
  viewer = view.Viewer(str(workdir), port=0)
  try:
    yield viewer, workdir
  finally:
    viewer.close()


def test_the_viewer_draws_each_region_and_colours_each_training_camera_by_its_region(region_viewer):
  from nerfpod import view
  viewer, workdir = region_viewer
  written = json.loads((workdir / "regions.json").read_text())
  assert written["count"] == 4 and viewer.partition.size == 4
  # The partition drawn is the one the run wrote.
  for k, region in enumerate(written["regions"]):
    np.testing.assert_allclose(viewer.partition.offsets_KxP[k], [p["offset"] for p in region["planes"]], rtol=1e-6)
  names = sorted(h.name for h in viewer._regions)
  assert names == sorted(f"/regions/{k}/{part}" for k in range(4) for part in ("cell", "centre", "label"))
  bound = viewer.config.model.hashgrid.bound
  cells = regions.cells(viewer.partition, bound)
  train = viewer.comps.scene.split("train")
  positions = np.asarray(train.poses)[:, :3, 3]
  region_of = jax.jit(lambda x: regions.region_of(x, viewer.partition))  # one program rather than one per operation
  held = np.asarray(region_of(positions.astype(np.float32)))
  assert sorted(set(held.tolist())) == [0, 1, 2, 3]
  handles = {h.name: h for h in viewer._regions}
  for k in range(4):
    cell = handles[f"/regions/{k}/cell"]
    ends = np.asarray(cell.points).reshape(-1, 3)
    assert np.asarray(cell.points).shape == (3 * len(cells[k]), 2, 3)  # bottom, top and upright edges
    assert set(np.round(ends[:, 2], 6).tolist()) == {-bound, bound}
    np.testing.assert_allclose(np.unique(np.round(ends[:, :2], 5), axis=0), np.unique(np.round(cells[k], 5), axis=0))
    assert tuple(cell.colors.reshape(-1, 3)[0]) == view.region_colour(k)
    centre = handles[f"/regions/{k}/centre"]
    np.testing.assert_allclose(centre.position, positions[held == k].mean(0), rtol=1e-5, atol=1e-6)
    assert int(np.asarray(region_of(np.asarray(centre.position[None], np.float32)))[0]) == k
    assert handles[f"/regions/{k}/label"].text == f"region {k} ({int(np.sum(held == k))} cameras)"
  frustums = {f.name: f for f in viewer._frustums}
  for i, k in enumerate(held):
    assert tuple(frustums[f"/cameras/train/{i}"].color) == view.region_colour(k)
  assert all(tuple(f.color) == (230, 120, 30) for name, f in frustums.items() if not name.startswith("/cameras/train/"))
  viewer._set_regions_visible(False)
  assert not any(h.visible for h in viewer._regions)
  viewer._set_regions_visible(True)
  assert all(h.visible for h in viewer._regions)
