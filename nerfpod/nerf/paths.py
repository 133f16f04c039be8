"""Camera paths drawn from a capture's own cameras, so that a video looks at what was captured.

- `spiral`: the original NeRF's forward-facing path (bmild/nerf load_llff.py, render_path_spiral with the
  arguments load_llff_data gives it): around the average camera, radii the 90th percentile of the camera
  offsets, two turns, looking at a focus depth drawn from the scene's depth bounds.
- `ellipse`: mip-NeRF 360's path for 360-degree captures (multinerf camera_utils.generate_ellipse_path):
  an ellipse at the cameras' mean height through the spread of the cameras, looking at the point nearest
  to every camera's optical axis, at constant speed, with the world axis nearest the cameras' mean up as up.

Poses are (N, 4, 4) camera-to-world, OpenGL convention (the camera looks down -z, +y up), as every scene
has them. Pure NumPy, float64; the LLFF pose helpers (viewmatrix, poses_avg, focus_point) are nerf/poses.py's.
"""
import numpy as np

from nerfpod.nerf import poses as pose_math


def _normalize(v):
  return v / np.linalg.norm(v)


def spiral(poses_Nx4x4, near: float, far: float, num_frames: int = 120, num_turns: float = 2.0,
           z_rate: float = 0.5) -> np.ndarray:
  """The original's forward-facing spiral, (num_frames, 4, 4).

  near/far: the smallest and largest depth bound of the capture (LLFF's bds.min() and bds.max(), in the
  poses' frame). Focus depth 1 / (0.25 / (0.9 near) + 0.75 / (5 far)); radii the 90th percentile of |camera
  position| per axis (the capture recentred, as LLFF does, so that the average camera is at the origin);
  the camera circles num_turns times in x, y while bobbing in z at z_rate of that speed.
  """
  poses = np.asarray(poses_Nx4x4, np.float64)
  c2w = pose_math.poses_avg(poses)
  up = _normalize(poses[:, :3, 1].sum(0))
  close_depth, inf_depth = 0.9 * near, 5.0 * far
  focus = 1.0 / (0.25 / close_depth + 0.75 / inf_depth)
  radii = np.append(np.percentile(np.abs(poses[:, :3, 3]), 90, axis=0), 1.0)
  out = []
  for theta in np.linspace(0.0, 2.0 * np.pi * num_turns, num_frames + 1)[:-1]:
    centre = c2w[:3, :4] @ (np.array([np.cos(theta), -np.sin(theta), -np.sin(theta * z_rate), 1.0]) * radii)
    back = centre - c2w[:3, :4] @ np.array([0.0, 0.0, -focus, 1.0])
    out.append(pose_math.viewmatrix(back, up, centre))
  return np.stack(out)


def ellipse(poses_Nx4x4, num_frames: int = 120, z_variation: float = 0.0, z_phase: float = 0.0) -> np.ndarray:
  """mip-NeRF 360's ellipse path, (num_frames, 4, 4), for captures oriented with +z up (nerfpod normalises
  360-degree captures so). Its axes are the 90th percentile of the cameras' offsets from the focus point in
  x and y; it lies at the cameras' mean height (plus z_variation times an oscillation between their 10th and
  90th percentile heights); its angles are resampled so that the camera moves at constant speed.

  multinerf's path lies at height 0 of its frame, which is centred on the cameras' mean position. nerfpod
  centres a capture on its focus point instead, so the path is raised to the cameras' mean height: at
  height 0 here it would circle at the height of the object and look at it from the side, which a capture
  taken from above never saw.
  """
  poses = np.asarray(poses_Nx4x4, np.float64)
  center = pose_math.focus_point(poses, min_spread=0.0)  # multinerf's focus_point_fn
  offset = np.array([center[0], center[1], 0.0])
  scale = np.percentile(np.abs(poses[:, :3, 3] - offset), 90, axis=0)
  low, high = -scale + offset, scale + offset
  height = poses[:, 2, 3].mean()
  z_low = np.percentile(poses[:, :3, 3], 10, axis=0)
  z_high = np.percentile(poses[:, :3, 3], 90, axis=0)

  def positions_at(theta):
    return np.stack([
        low[0] + (high - low)[0] * (np.cos(theta) * 0.5 + 0.5),
        low[1] + (high - low)[1] * (np.sin(theta) * 0.5 + 0.5),
        height + z_variation * (z_low[2] - height + (z_high - z_low)[2]
                                * (np.cos(theta + 2 * np.pi * z_phase) * 0.5 + 0.5)),
    ], -1)

  theta = np.linspace(0.0, 2.0 * np.pi, num_frames + 1)
  positions = positions_at(theta)
  # Constant speed: resample the angles by inverting the cumulative arc length (multinerf's
  # stepfun.sample with weights proportional to each step's length, deterministic, u in [0, 1 - eps]).
  lengths = np.linalg.norm(positions[1:] - positions[:-1], axis=-1)
  cdf = np.concatenate([[0.0], np.minimum(1.0, np.cumsum(lengths / lengths.sum())[:-1]), [1.0]])
  theta = np.interp(np.linspace(0.0, 1.0 - np.finfo(np.float32).eps, num_frames + 1), cdf, theta)
  positions = positions_at(theta)[:-1]
  mean_up = poses[:, :3, 1].mean(0)
  mean_up /= np.linalg.norm(mean_up)
  axis = np.argmax(np.abs(mean_up))
  up = np.eye(3)[axis] * np.sign(mean_up[axis])
  return np.stack([pose_math.viewmatrix(p - center, up, p) for p in positions])
