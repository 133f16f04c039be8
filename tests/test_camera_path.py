"""nerfstudio camera_path.json: matrices read row-major, vertical field of view -> focal, bad files refused."""
import json
import math

import numpy as np
import pytest

from nerfpod.render import camera_path
from nerfpod.errors import UserError
from nerfpod.nerf import cameras


def _spec(**changes):
  pose = cameras.look_at(np.array([1.0, 2.0, 3.0]))
  spec = {"camera_type": "perspective", "render_width": 64, "render_height": 48, "fps": 24,
          "camera_path": [{"camera_to_world": pose.reshape(16).tolist(), "fov": 50.0, "aspect": 4 / 3}]}
  return spec | changes, pose


def test_reads_row_major_matrices_and_vertical_fov(tmp_path):
  spec, pose = _spec()
  (tmp_path / "p.json").write_text(json.dumps(spec))
  path = camera_path.read(tmp_path / "p.json")
  np.testing.assert_array_equal(path.poses[0], pose)
  np.testing.assert_array_equal(path.poses[0][:3, 3], [1.0, 2.0, 3.0])  # translation from entries 3, 7, 11
  intr = path.intrinsics(0)
  assert (intr.width, intr.height, path.fps) == (64, 48, 24.0)
  # nerfstudio: three_js_perspective_camera_focal_length(fov, H) = H / 2 / tan(radians(fov) / 2)
  assert intr.fx == intr.fy == pytest.approx(24 / math.tan(math.radians(25)))
  assert (intr.cx, intr.cy) == (32.0, 24.0)


def test_write_then_read_gives_the_same_cameras(tmp_path):
  poses = np.stack([cameras.spherical_pose(a, -30, 4) for a in (0, 90, 180)])
  original = camera_path.CameraPath(poses, np.array([40.0, 50.0, 60.0]), 80, 60, 30.0)
  camera_path.write(tmp_path / "p.json", original, keyframes=[])
  back = camera_path.read(tmp_path / "p.json")
  np.testing.assert_array_equal(back.poses, poses)
  np.testing.assert_array_equal(back.fov_y_deg, original.fov_y_deg)
  assert (back.width, back.height, back.fps) == (80, 60, 30.0)
  assert json.loads((tmp_path / "p.json").read_text())["keyframes"] == []


@pytest.mark.parametrize("change, message", [
    ({"camera_type": "fisheye"}, "only 'perspective'"),
    ({"camera_path": []}, "lists no camera"),
    ({"render_width": 0}, "not positive"),
    ({"camera_path": [{"camera_to_world": [0.0] * 15, "fov": 50}]}, "malformed"),
    ({"camera_path": [{"camera_to_world": [float("nan")] * 16, "fov": 50}]}, "non-finite"),
    ({"camera_path": [{"camera_to_world": np.eye(4).reshape(16).tolist(), "fov": 180}]}, "outside (0, 180)"),
])
def test_bad_files_are_one_sentence(tmp_path, change, message):
  spec, _ = _spec(**change)
  (tmp_path / "p.json").write_text(json.dumps(spec))
  with pytest.raises(UserError, match=message.replace("(", r"\(").replace(")", r"\)")):
    camera_path.read(tmp_path / "p.json")


def test_missing_key_missing_file_and_bad_json(tmp_path):
  spec, _ = _spec()
  del spec["render_height"]
  (tmp_path / "p.json").write_text(json.dumps(spec))
  with pytest.raises(UserError, match="has no 'render_height'"):
    camera_path.read(tmp_path / "p.json")
  with pytest.raises(UserError, match="does not exist"):
    camera_path.read(tmp_path / "none.json")
  (tmp_path / "bad.json").write_text("{not json")
  with pytest.raises(UserError, match="not readable JSON"):
    camera_path.read(tmp_path / "bad.json")
