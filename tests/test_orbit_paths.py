"""orbit.path: the spiral, the ellipse and a user's camera_path.json rendered into the orbit archive; a path
file's cameras are its matrices and fovs; another path replaces the archive instead of resuming it."""
import numpy as np
import pytest

from conftest import DATA, load_config, require, smoke_config
from nerfpod.render import archive as archives
from nerfpod.render import camera_path, renderer
from nerfpod.run import components, orbit
from nerfpod.errors import UserError
from nerfpod.nerf import cameras, paths


def _path_file(tmp_path, fovs=(40.0, 55.0, 70.0)):
  """A camera_path.json of len(fovs) cameras on a small arc, each with its own vertical fov, 20x14."""
  poses = np.stack([cameras.look_at(np.array([4.0 * np.cos(a), 4.0 * np.sin(a), 1.5]))
                    for a in np.linspace(0.0, 1.0, len(fovs))])
  file = tmp_path / "camera_path.json"
  camera_path.write(file, camera_path.CameraPath(poses, np.asarray(fovs), 20, 14, 12.0))
  return file, poses


def test_a_path_files_cameras_are_its_matrices_and_fovs(tmp_path):
  file, poses = _path_file(tmp_path)
  config = smoke_config(**{"orbit.path": "file", "orbit.path_file": str(file)})
  from nerfpod.scenes import procedural
  cams = orbit.path_cameras(config, procedural.make(16))
  np.testing.assert_allclose(cams.poses, poses, rtol=1e-6, atol=1e-7)
  assert cams.fps == 12.0 and len(cams.intrinsics) == 3
  for intr, fov in zip(cams.intrinsics, (40.0, 55.0, 70.0)):
    assert (intr.width, intr.height) == (20, 14)
    assert intr.fy == pytest.approx(7.0 / np.tan(np.radians(fov) / 2))


@pytest.mark.parametrize("path", ["spiral", "ellipse"])
def test_spiral_and_ellipse_are_drawn_from_the_scenes_cameras(path):
  from nerfpod.scenes import procedural
  scene = procedural.make(16)
  config = smoke_config(**{"orbit.path": path, "orbit.num_frames": 12})
  cams = orbit.path_cameras(config, scene)
  names = {}
  for split in scene.splits.values():
    names.update(zip(split.names, split.poses.astype(np.float64)))
  everyone = np.stack(list(names.values()))
  want = (paths.spiral(everyone, scene.near, scene.far, 12) if path == "spiral" else paths.ellipse(everyone, 12))
  np.testing.assert_allclose(cams.poses, want, rtol=1e-6, atol=1e-6)
  assert cams.intrinsics == (orbit.orbit_intrinsics(config.orbit, scene.split("test").intrinsics),)


@pytest.mark.slow  # compiles and renders two archives
def test_a_path_file_is_rendered_into_the_archive_with_each_frames_camera(tmp_path):
  file, poses = _path_file(tmp_path)
  config = smoke_config(**{"orbit.path": "file", "orbit.path_file": str(file), "orbit.chunk": 64})
  comps = components.build(config)
  params = comps.init_state().params
  orbit.render_orbit(comps, params, str(tmp_path), step=3)
  archive = archives.Archive.open(str(tmp_path / "renders" / "orbit.zarr"))
  assert archive.num_frames == 3 and archive.attributes["path"] == "file" and archive.attributes["fps"] == 12.0
  np.testing.assert_allclose(archive.poses, poses, rtol=1e-6, atol=1e-7)
  for index in (0, 2):
    intr = camera_path.read(file).intrinsics(index)
    assert archive.frame_intrinsics(index) == intr
    want = renderer.render_image(comps.renderer, params, comps.mesh, poses[index], intr, 0.5, 256)
    got = archive.read_frame(index)
    assert got["rgb"].shape == (14, 20, 3)
    np.testing.assert_allclose(got["depth"], want["depth"], rtol=1e-5, atol=1e-5)
  assert (tmp_path / "renders" / "orbit_rgb.mp4").exists()

  # Another path in the same workdir replaces the archive: every frame is rendered again.
  config.orbit.path, config.orbit.num_frames, config.orbit.width, config.orbit.height = "ellipse", 2, 8, 8
  result = orbit.render_orbit(components.build(config), params, str(tmp_path), step=3)
  assert result["rendered"] == [0, 1] and result["skipped"] == []
  archive = archives.Archive.open(str(tmp_path / "renders" / "orbit.zarr"))
  assert archive.attributes["path"] == "ellipse" and "frame_intrinsics" not in archive.attributes


def test_a_bad_path_file_fails_before_training(tmp_path):
  (tmp_path / "bad.json").write_text("{\"render_width\": 4}")
  config = smoke_config(**{"orbit.path": "file", "orbit.path_file": str(tmp_path / "bad.json")})
  with pytest.raises(UserError, match="camera path .*bad.json: it has no 'render_height'"):
    components.build(config)


def test_the_llff_configs_spiral_on_horns_is_the_originals():
  """The whole way: configs/llff.py's loader (recentring, bounds rescale) and orbit.path=spiral give the
  original load_llff_data's render_poses for the real horns capture, each frame counted once."""
  from nerfpod import scenes
  from test_paths import load_llff_spiral
  folder = require(DATA / "llff_horns")
  config = load_config("llff", "scene=horns")
  config.data.path = str(folder)
  cams = orbit.path_cameras(config, scenes.load(config.data))
  raw = np.load(folder / "poses_bounds.npy")
  poses = raw[:, :-2].reshape([-1, 3, 5])
  poses = np.concatenate([poses[:, :, 1:2], -poses[:, :, 0:1], poses[:, :, 2:]], 2)
  _, _, want = load_llff_spiral(poses, raw[:, -2:].copy())
  assert cams.poses.shape == (120, 4, 4)
  np.testing.assert_allclose(cams.poses[:, :3, :4], want, atol=1e-4)
  assert cams.intrinsics[0].width == 252 and cams.intrinsics[0].height == 189
