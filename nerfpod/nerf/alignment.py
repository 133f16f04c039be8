"""Similarity alignment of two sets of cameras (the gauge of pose refinement).

Pose refinement (nerf/pose_correction.py) learns each training camera's correction from its pixels alone.
A similarity of every camera and the scene together (scale s, rotation R, translation t) changes no
training pixel, so the refined cameras may drift by one such motion, and the field drifts with them; a
held-out camera at its given pose then looks at the field from the wrong place. Evaluation maps it into the
refined frame instead: `umeyama(given centres, refined centres)` is the similarity that best carries the
given training cameras onto their refined ones (least squares, Umeyama 1991), and `transform_poses` applies
it to the held-out cameras.

A similarity maps a point x to s R x + t; a camera-to-world pose [Rc | o] to [R Rc | s R o + t] (its centre
moves as a point, its axes turn by R; ray directions stay unit length, so distances along a ray stay those of
the refined frame, where the field lives).
"""
import numpy as np


def umeyama(src_Nx3, dst_Nx3) -> tuple[float, np.ndarray, np.ndarray]:
  """(s, R, t) minimising sum |dst_i - (s R src_i + t)|^2 over scales s > 0, rotations R (det +1) and
  translations t, float64 NumPy (Umeyama 1991, "Least-squares estimation of transformation parameters
  between two point patterns", eqs. 40-42). Needs N >= 3 points not all on a line for a unique R; with
  every src at one point, s = 1 and R = I (only t is determined)."""
  src = np.asarray(src_Nx3, np.float64)
  dst = np.asarray(dst_Nx3, np.float64)
  if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
    raise ValueError(f"umeyama takes two (N, 3) arrays of the same shape, got {src.shape} and {dst.shape}")
  mu_src, mu_dst = src.mean(0), dst.mean(0)
  a, b = src - mu_src, dst - mu_dst
  var_src = np.mean(np.sum(a * a, axis=1))
  if var_src <= 1e-24:
    return 1.0, np.eye(3), mu_dst - mu_src
  cov = b.T @ a / len(src)  # (3, 3): dst against src
  u, d, vt = np.linalg.svd(cov)
  sign = np.eye(3)
  if np.linalg.det(u) * np.linalg.det(vt) < 0:  # a reflection would fit better: take the best rotation
    sign[2, 2] = -1.0
  rotation = u @ sign @ vt
  scale = float(np.trace(np.diag(d) @ sign) / var_src)
  return scale, rotation, mu_dst - scale * rotation @ mu_src


def transform_poses(poses_Nx4x4, scale: float, rotation_3x3, translation_3) -> np.ndarray:
  """Camera-to-world poses (N, 4, 4) moved by the similarity x -> s R x + t, float64: [R Rc | s R o + t]."""
  poses = np.array(poses_Nx4x4, np.float64)
  rotation = np.asarray(rotation_3x3, np.float64)
  out = poses.copy()
  out[..., :3, :3] = rotation @ poses[..., :3, :3]
  out[..., :3, 3] = scale * poses[..., :3, 3] @ rotation.T + np.asarray(translation_3, np.float64)
  return out


def rotation_angle_deg(rotation_3x3) -> float:
  """The angle of a rotation matrix, degrees (for reports)."""
  cos = (np.trace(np.asarray(rotation_3x3, np.float64)) - 1.0) / 2.0
  return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
