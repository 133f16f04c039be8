"""Camera paths through keyframes: the poses between cameras a user placed (the viewer's saved paths).

Keyframes are evenly spaced in time. Between them:
- positions follow a uniform Catmull-Rom spline through the keyframe positions: it passes through every
  keyframe, is smooth (C1) across them, and reproduces a straight line walked at constant speed exactly
  (the ends are extended by reflection, so the first and last segments keep that property);
- orientations are spherically interpolated (slerp) between consecutive keyframes, so every pose is a
  rotation (never a blend of matrices, which would shear) turning at constant angular speed per segment;
- the vertical field of view is interpolated linearly.
With `loop`, the path comes back to the first keyframe and the spline wraps around.

Quaternions are (w, x, y, z), as viser and nerfstudio write them (nerf/cameras.py converts them).
"""
import numpy as np

from nerfpod.nerf.cameras import quaternion_to_rotation, rotation_to_quaternion


def slerp(q0, q1, t: float) -> np.ndarray:
  """The rotation a fraction `t` of the way from q0 to q1 along the shorter arc, at constant angular speed."""
  q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64)
  dot = float(q0 @ q1)
  if dot < 0:  # q and -q are the same rotation: take the shorter way round
    q1, dot = -q1, -dot
  if dot > 0.9995:  # nearly equal: the linear blend is exact to rounding, and sin(angle) ~ 0 below
    q = q0 + t * (q1 - q0)
    return q / np.linalg.norm(q)
  angle = np.arccos(dot)
  return (np.sin((1 - t) * angle) * q0 + np.sin(t * angle) * q1) / np.sin(angle)


def _catmull_rom(p0, p1, p2, p3, u: float) -> np.ndarray:
  """The uniform Catmull-Rom segment from p1 (u = 0) to p2 (u = 1)."""
  return 0.5 * (2 * p1 + (p2 - p0) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u ** 2
                + (3 * p1 - p0 - 3 * p2 + p3) * u ** 3)


def frame_times(num_keyframes: int, num_frames: int, loop: bool = False) -> np.ndarray:
  """Each frame's time in keyframe units (keyframe k at time k). Without `loop` the first and last frames
  are the first and last keyframes; with it, the frames cover the whole loop, the last one just before
  the path closes on the first keyframe again."""
  if loop:
    return np.arange(num_frames) * (num_keyframes / num_frames)
  if num_frames == 1:
    return np.zeros(1)
  return np.linspace(0.0, num_keyframes - 1.0, num_frames)


def interpolate(poses_Kx4x4, fov_K, num_frames: int, loop: bool = False) -> tuple[np.ndarray, np.ndarray]:
  """(poses (N, 4, 4), vertical fields of view (N,)) of `num_frames` cameras along the keyframes' path.

  poses_Kx4x4: camera-to-world keyframes (any convention: the rotation is interpolated as it is given).
  """
  poses = np.asarray(poses_Kx4x4, np.float64)
  fov = np.asarray(fov_K, np.float64)
  k = len(poses)
  if k < 1 or num_frames < 1:
    raise ValueError(f"need at least one keyframe and one frame, got {k} keyframes and {num_frames} frames")
  positions = poses[:, :3, 3]
  quaternions = [rotation_to_quaternion(p[:3, :3]) for p in poses]
  if loop:
    point = lambda i: positions[i % k]
  else:  # the ends extended by reflection, so that a straight keyframe line stays straight to its ends
    before = 2 * positions[0] - positions[1] if k > 1 else positions[0]
    after = 2 * positions[-1] - positions[-2] if k > 1 else positions[-1]
    point = lambda i: before if i < 0 else after if i >= k else positions[i]
  out_poses = np.tile(np.eye(4), (num_frames, 1, 1))
  out_fov = np.empty(num_frames)
  for n, t in enumerate(frame_times(k, num_frames, loop)):
    j = min(int(np.floor(t)), k - 1 if loop else max(k - 2, 0))
    u = float(t - j)
    if k == 1:
      j, u = 0, 0.0
    out_poses[n, :3, 3] = _catmull_rom(point(j - 1), point(j), point(j + 1), point(j + 2), u)
    out_poses[n, :3, :3] = quaternion_to_rotation(slerp(quaternions[j % k], quaternions[(j + 1) % k], u))
    out_fov[n] = (1 - u) * fov[j % k] + u * fov[(j + 1) % k]
  return out_poses, out_fov
