"""The orbit: camera path, the tensorstore archive, resuming a partial render, replacing a stale one."""
import json

import numpy as np
import pytest

from conftest import smoke_config
from nerfpod.render import archive as archives
from nerfpod.render import renderer, video
from nerfpod.run import components, orbit
from nerfpod.errors import UserError
from nerfpod.nerf import cameras


@pytest.mark.parametrize("elevation", [-30.0, 15.0])
def test_orbit_poses_look_at_the_origin_at_the_given_radius_and_elevation(elevation):
  radius, n = 3.5, 8
  poses = orbit.orbit_poses(n, elevation, radius)
  assert poses.shape == (n, 4, 4) and poses.dtype == np.float32
  eyes = poses[:, :3, 3].astype(np.float64)
  np.testing.assert_allclose(np.linalg.norm(eyes, axis=-1), radius, rtol=1e-6)
  # The tutorial's sign: elevation -30 puts the camera 30 degrees above the z = 0 plane.
  np.testing.assert_allclose(eyes[:, 2], radius * np.sin(np.deg2rad(-elevation)), atol=1e-5)
  # Equal azimuth steps of 360 / n degrees, one full turn without repeating the first frame; the tutorial's
  # azimuth turns clockwise seen from above.
  azimuths = np.rad2deg(np.arctan2(eyes[:, 1], eyes[:, 0]))
  np.testing.assert_allclose(np.mod(-np.diff(azimuths), 360.0), 360.0 / n, atol=1e-4)
  for pose, eye in zip(poses.astype(np.float64), eyes):
    rotation = pose[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-6)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(-rotation[:, 2], -eye / radius, atol=1e-6)  # looks down -z at the origin
    assert rotation[2, 1] > 0  # image up points to world up: the video is not upside down
    # The origin projects to the image centre.
    intr = cameras.Intrinsics.from_focal(40, 30, 50.0)
    xy, depth = cameras.project(np.zeros((1, 3)), pose, intr)
    np.testing.assert_allclose(xy[0], [intr.cx, intr.cy], atol=1e-4)
    assert depth[0] == pytest.approx(radius, rel=1e-6)
  np.testing.assert_allclose(poses[0], cameras.spherical_pose(0.0, elevation, radius), atol=1e-6)


def test_orbit_camera_defaults_to_the_eval_split_camera_and_keeps_its_field_of_view():
  reference = cameras.Intrinsics.from_focal(200, 100, 300.0)
  config = smoke_config(**{"orbit.width": 0, "orbit.height": 0, "orbit.focal": 0.0}).orbit
  assert orbit.orbit_intrinsics(config, reference) == reference
  config.width = 50  # height from the aspect ratio, focal scaled with the width
  assert orbit.orbit_intrinsics(config, reference) == cameras.Intrinsics.from_focal(50, 25, 75.0)
  config.width, config.height, config.focal = 0, 20, 10.0
  assert orbit.orbit_intrinsics(config, reference) == cameras.Intrinsics.from_focal(40, 20, 10.0)


@pytest.fixture(scope="module")
def trained():
  """Smoke scene, model and (initial) parameters on 8 devices; 5 frames of 16x12 (an uneven split)."""
  config = smoke_config(**{"orbit.num_frames": 5, "orbit.width": 16, "orbit.height": 12,
                           "orbit.chunk": 64})
  comps = components.build(config)
  return comps, comps.init_state().params


def _reference_frames(comps, params):
  """Every orbit frame rendered by the evaluator's renderer (all devices together), rgb as uint8."""
  config = comps.config
  intr = orbit.orbit_intrinsics(config.orbit, comps.scene.split(config.eval.split).intrinsics)
  frames = []
  for pose in orbit.orbit_poses(config.orbit.num_frames, config.orbit.elevation, config.orbit.radius):
    out = renderer.render_image(comps.renderer, params, comps.mesh, pose, intr, config.data.pixel_center, 256)
    out["rgb"] = np.round(np.clip(out["rgb"], 0, 1) * 255).astype(np.uint8)
    frames.append(out)
  return frames


def _assert_frame_equal(got, want):
  assert got["rgb"].dtype == np.uint8 and got["rgb"].shape == want["rgb"].shape
  assert np.abs(got["rgb"].astype(int) - want["rgb"]).max() <= 1
  for name in ("depth", "acc", "disparity"):
    assert got[name].dtype == np.float32
    np.testing.assert_allclose(got[name], want[name], rtol=1e-5, atol=1e-5)


def test_orbit_archive_holds_every_frame_cameras_step_and_config(trained, tmp_path):
  comps, params = trained
  config, scene = comps.config, comps.scene
  import tensorboardX
  with tensorboardX.SummaryWriter(logdir=str(tmp_path / "tb")) as writer:
    result = orbit.render_orbit(comps, params, str(tmp_path), step=7, writer=writer)
  assert result["rendered"] == [0, 1, 2, 3, 4] and result["skipped"] == []
  archive = archives.Archive.open(str(tmp_path / "renders" / "orbit.zarr"))
  assert archive.num_frames == 5
  np.testing.assert_array_equal(archive.written_by(), [0, 0, 0, 0, 0])
  assert archive.missing_frames() == []
  # One chunk per frame, in every array.
  for name, shape in (("rgb", [1, 12, 16, 3]), ("depth", [1, 12, 16]), ("written_by", [1])):
    assert list(archive.arrays[name].chunk_layout.read_chunk.shape) == shape
  attributes = archive.attributes
  assert attributes["step"] == 7 and attributes["scene"] == "procedural"
  assert (attributes["near"], attributes["far"]) == (2.0, 6.0)
  assert archive.intrinsics == orbit.orbit_intrinsics(config.orbit, scene.split("test").intrinsics)
  np.testing.assert_array_equal(archive.poses, orbit.orbit_poses(5, -30.0, 4.0))
  assert attributes["config"] == json.loads(config.to_json_best_effort())
  for index, want in enumerate(_reference_frames(comps, params)):
    _assert_frame_equal(archive.read_frame(index), want)
  assert sorted(p.name for p in (tmp_path / "renders").iterdir()) == [
      "orbit.zarr", "orbit_acc.mp4", "orbit_depth.mp4", "orbit_disparity.mp4", "orbit_rgb.mp4",
      "orbit_sheet.png"]
  # TensorBoard shows the contact sheet: 4 channel rows of 5 frames of 16x12, 2-pixel gaps.
  from tensorboard.backend.event_processing import event_accumulator
  events = event_accumulator.EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 0})
  events.Reload()
  (image,) = events.Images("orbit/contact_sheet")
  assert (image.step, image.height, image.width) == (7, 4 * 12 + 3 * 2, 5 * 16 + 4 * 2)


def test_partial_archive_is_completed_without_rerendering_its_frames(trained, tmp_path):
  comps, params = trained
  orbit.render_orbit(comps, params, str(tmp_path), step=3)
  archive = archives.Archive.open(str(tmp_path / "renders" / "orbit.zarr"))
  reference = [archive.read_frame(i) for i in range(5)]
  # Mark the complete frames 0 and 4 so that re-rendering them would show; cut frames 1 and 3 off: frame 1
  # half written (its rgb chunk committed, not its marker), frame 3 never started.
  marked = dict(reference[0], rgb=np.full_like(reference[0]["rgb"], 7))
  archive.write_frame(0, marked, process_index=0)
  archive.arrays["rgb"][4].write(np.full_like(reference[4]["rgb"], 9)).result()
  archive.arrays["rgb"][1].write(np.full_like(reference[1]["rgb"], 5)).result()
  archive.arrays["written_by"][1].write(np.int16(-1)).result()
  archive.arrays["written_by"][3].write(np.int16(-1)).result()
  assert archive.missing_frames() == [1, 3]
  with pytest.raises(UserError, match=r"2 of 5 frames are missing \(1, 3\)"):
    archive.check_complete()

  result = orbit.render_orbit(comps, params, str(tmp_path), step=3)
  assert result["rendered"] == [1, 3] and result["skipped"] == [0, 2, 4]
  assert archive.missing_frames() == []
  assert (archive.read_frame(0)["rgb"] == 7).all() and (archive.read_frame(4)["rgb"] == 9).all()
  for index in (1, 2, 3):
    _assert_frame_equal(archive.read_frame(index), reference[index])


def test_archive_of_another_step_is_replaced_not_resumed(trained, tmp_path):
  comps, params = trained
  orbit.render_orbit(comps, params, str(tmp_path), step=1)
  result = orbit.render_orbit(comps, params, str(tmp_path), step=2)
  assert result["rendered"] == [0, 1, 2, 3, 4] and result["skipped"] == []
  assert archives.Archive.open(str(tmp_path / "renders" / "orbit.zarr")).attributes["step"] == 2


def test_a_missing_archive_is_a_user_error(tmp_path):
  with pytest.raises(UserError, match="no orbit archive"):
    archives.Archive.open(str(tmp_path / "nothing.zarr"))


def test_a_frame_renders_as_the_chunked_renderer_renders_it_and_a_padding_round_renders_nothing(trained):
  """orbit.FrameRenderer (one call per chunk over every device, each process feeding its own frame) gives
  the bits of renderer.render_image with the same chunk, also where the last chunk is padded."""
  comps, params = trained
  intr = cameras.Intrinsics.from_focal(16, 12, 20.0)
  pose = orbit.orbit_poses(3, -30.0, 4.0)[1]
  frames = orbit.FrameRenderer(comps.renderer, params, comps.mesh, intr, 0.5, 40, pose)
  assert (frames.chunk, frames.calls) == (40, 5)  # 192 rays: 5 calls of 40, the last padded by 8 rays
  got = frames.render(pose, intr)
  want = renderer.render_image(comps.renderer, params, comps.mesh, pose, intr, 0.5, 40)
  np.testing.assert_array_equal(got["rgb"], video.to_uint8(want["rgb"]))
  for name in ("depth", "acc", "disparity"):
    np.testing.assert_array_equal(got[name], want[name])
  assert frames.render() is None
  assert orbit.chunk_rays(4096, 192, comps.mesh) == 192 and orbit.chunk_rays(5, 192, comps.mesh) == 8
  assert orbit.chunk_rays(56, 192, comps.mesh) == 48  # 4 calls of 48 rather than 3 of 56 and one padded
