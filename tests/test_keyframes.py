"""Keyframe paths (nerf/keyframes.py) against analytic references: rotations about one axis, straight lines."""
import numpy as np
import pytest

from nerfpod.nerf import cameras, keyframes


def _rot_z(deg):
  a = np.radians(deg)
  return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _pose(rotation, position):
  pose = np.eye(4)
  pose[:3, :3], pose[:3, 3] = rotation, position
  return pose


def _random_rotation(rng):
  q, r = np.linalg.qr(rng.normal(size=(3, 3)))
  q = q * np.sign(np.diag(r))
  return q if np.linalg.det(q) > 0 else -q


def test_quaternion_round_trip_and_known_values():
  rng = np.random.default_rng(0)
  for _ in range(50):
    rotation = _random_rotation(rng)
    np.testing.assert_allclose(cameras.quaternion_to_rotation(cameras.rotation_to_quaternion(rotation)),
                               rotation, atol=1e-12)
  # 90 degrees about z: (cos 45, 0, 0, sin 45); 180 degrees about x (w = 0, the branch without the trace)
  np.testing.assert_allclose(cameras.rotation_to_quaternion(_rot_z(90)), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)],
                             atol=1e-12)
  np.testing.assert_allclose(cameras.rotation_to_quaternion(np.diag([1.0, -1, -1])), [0, 1, 0, 0], atol=1e-12)


@pytest.mark.parametrize("t", [0.0, 0.25, 0.5, 0.9, 1.0])
def test_slerp_turns_at_constant_speed_about_the_axis(t):
  q0, q1 = cameras.rotation_to_quaternion(_rot_z(10)), cameras.rotation_to_quaternion(_rot_z(130))
  np.testing.assert_allclose(cameras.quaternion_to_rotation(keyframes.slerp(q0, q1, t)), _rot_z(10 + 120 * t),
                             atol=1e-12)
  # -q1 is the same rotation: still the short way round
  np.testing.assert_allclose(cameras.quaternion_to_rotation(keyframes.slerp(q0, -q1, t)),
                             _rot_z(10 + 120 * t), atol=1e-12)


def test_path_passes_through_every_keyframe_and_poses_are_rotations():
  rng = np.random.default_rng(1)
  poses = np.stack([_pose(_random_rotation(rng), rng.normal(size=3)) for _ in range(4)])
  fov = np.array([40.0, 50.0, 60.0, 45.0])
  out, out_fov = keyframes.interpolate(poses, fov, num_frames=31)  # frames 0, 10, 20, 30 are the keyframes
  np.testing.assert_allclose(out[::10], poses, atol=1e-12)
  np.testing.assert_allclose(out_fov[::10], fov)
  np.testing.assert_allclose(out_fov[5], 45.0)
  rotations = out[:, :3, :3]
  np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (31, 3, 3)),
                             atol=1e-12)
  np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-12)
  np.testing.assert_array_equal(out[:, 3], np.broadcast_to([0, 0, 0, 1.0], (31, 4)))


def test_keyframes_on_a_line_give_constant_speed_on_that_line():
  start, step = np.array([1.0, 2.0, 3.0]), np.array([0.5, -1.0, 0.25])
  poses = np.stack([_pose(np.eye(3), start + k * step) for k in range(3)])
  out, _ = keyframes.interpolate(poses, np.full(3, 50.0), num_frames=9)
  np.testing.assert_allclose(out[:, :3, 3], start + np.arange(9)[:, None] / 4 * step, atol=1e-12)


def test_a_loop_closes_on_the_first_keyframe_and_turns_through_every_keyframe():
  # Four cameras a quarter turn apart on a circle, each facing the same way round.
  poses = np.stack([_pose(_rot_z(90 * k), _rot_z(90 * k) @ [2.0, 0, 0]) for k in range(4)])
  out, _ = keyframes.interpolate(poses, np.full(4, 50.0), num_frames=8, loop=True)
  np.testing.assert_allclose(out[::2], poses, atol=1e-12)
  np.testing.assert_allclose(out[1, :3, :3], _rot_z(45), atol=1e-12)
  np.testing.assert_allclose(out[7, :3, :3], _rot_z(315), atol=1e-12)  # wraps from the last to the first
  # Catmull-Rom through a square's corners is symmetric: the midpoints lie on the diagonals
  np.testing.assert_allclose(out[1, 0, 3], out[1, 1, 3], atol=1e-12)
  np.testing.assert_allclose(out[7, 0, 3], -out[7, 1, 3], atol=1e-12)


def test_one_keyframe_holds_still_and_bad_counts_are_refused():
  pose = _pose(_rot_z(30), [1.0, 2, 3])
  out, fov = keyframes.interpolate(pose[None], [42.0], num_frames=3)
  np.testing.assert_allclose(out, np.broadcast_to(pose, (3, 4, 4)), atol=1e-12)
  np.testing.assert_allclose(fov, 42.0)
  with pytest.raises(ValueError):
    keyframes.interpolate(np.zeros((0, 4, 4)), [], num_frames=3)
