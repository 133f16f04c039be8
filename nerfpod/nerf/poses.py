"""Pose normalisation: similarity transforms that bring a capture's cameras into a frame the field likes.

Captures come in whatever frame their structure-from-motion run chose: any orientation, any origin, any
unit. A NeRF wants the scene centred at the origin, a known size (a unit box, or the LLFF bounds' scale), and
for 360-degree captures +z up. Each function here returns a 4x4 similarity `T` (uniform scale s, rotation R,
translation): a point X of the capture lies at T @ X in the scene; `transform_poses(T, c2w)` moves cameras
the same way, keeping their rotations orthonormal. Every pose is camera-to-world, OpenGL (x right, y up, the
camera looks down -z). Sources: bmild/nerf load_llff.py (poses_avg, recenter), nerfstudio camera_utils
(auto_orient_and_center_poses 'up'), multinerf camera_utils (transform_poses_pca), instant-ngp colmap2nerf
(the point the cameras look at).
"""
import numpy as np


def normalize(v: np.ndarray) -> np.ndarray:
  return v / np.linalg.norm(v)


def viewmatrix(z: np.ndarray, up: np.ndarray, position: np.ndarray) -> np.ndarray:
  """LLFF's viewmatrix: the 4x4 c2w whose back axis (+z) is `z`, whose up (+y) is nearest `up`."""
  z = normalize(np.asarray(z, np.float64))
  x = normalize(np.cross(up, z))
  y = normalize(np.cross(z, x))
  out = np.eye(4)
  out[:3, :4] = np.stack([x, y, z, np.asarray(position, np.float64)], 1)
  return out


def poses_avg(poses_Nx4x4: np.ndarray) -> np.ndarray:
  """LLFF's average camera: mean position, summed back (+z) axes and up (+y) axes (load_llff.poses_avg)."""
  poses = np.asarray(poses_Nx4x4, np.float64)
  return viewmatrix(poses[:, :3, 2].sum(0), poses[:, :3, 1].sum(0), poses[:, :3, 3].mean(0))


def similarity(scale: float = 1.0, rotation: np.ndarray | None = None, center=None) -> np.ndarray:
  """T(X) = scale * R (X - center): the 4x4 matrix."""
  rot = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
  c = np.zeros(3) if center is None else np.asarray(center, np.float64)
  out = np.eye(4)
  out[:3, :3] = scale * rot
  out[:3, 3] = -scale * rot @ c
  return out


def scale_of(transform: np.ndarray) -> float:
  """The uniform scale s of a similarity."""
  return float(np.cbrt(np.linalg.det(np.asarray(transform, np.float64)[:3, :3])))


def transform_poses(transform: np.ndarray, poses_Nx4x4: np.ndarray) -> np.ndarray:
  """Camera-to-world poses moved by the similarity `transform`: positions mapped by it, rotations turned
  by its rotation (not scaled: a camera's axes stay unit vectors)."""
  t = np.asarray(transform, np.float64)
  out = t @ np.asarray(poses_Nx4x4, np.float64)
  out[..., :3, :3] /= scale_of(t)
  return out


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
  """The rotation that turns direction a to direction b, about their common normal (Rodrigues)."""
  a, b = normalize(np.asarray(a, np.float64)), normalize(np.asarray(b, np.float64))
  v, c = np.cross(a, b), float(a @ b)
  if c < -1.0 + 1e-10:  # opposite: half a turn about any axis normal to a
    axis = normalize(np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0]))
    return 2.0 * np.outer(axis, axis) - np.eye(3)
  vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
  return np.eye(3) + vx + vx @ vx / (1.0 + c)


def up_rotation(poses_Nx4x4: np.ndarray) -> np.ndarray:
  """The rotation taking the cameras' mean up vector (+y of each c2w) to +z (nerfstudio's 'up')."""
  return rotation_between(np.asarray(poses_Nx4x4)[:, :3, 1].mean(0), np.array([0.0, 0.0, 1.0]))


def pca_rotation(positions_Nx3: np.ndarray, poses_Nx4x4: np.ndarray) -> np.ndarray:
  """multinerf's transform_poses_pca rotation: the camera positions' principal axes become x, y, z (most
  spread first), a right-handed frame, flipped about x if the cameras' mean up then points down."""
  t = np.asarray(positions_Nx3, np.float64)
  t = t - t.mean(0)
  eigval, eigvec = np.linalg.eigh(t.T @ t)
  rot = eigvec[:, np.argsort(eigval)[::-1]].T
  if np.linalg.det(rot) < 0:
    rot = np.diag([1.0, 1.0, -1.0]) @ rot
  if (rot @ np.asarray(poses_Nx4x4, np.float64)[:, :3, 1].mean(0))[2] < 0:
    rot = np.diag([1.0, -1.0, -1.0]) @ rot
  return rot


def focus_point(poses_Nx4x4: np.ndarray, min_spread: float = 0.05) -> np.ndarray | None:
  """The point nearest every camera's optical axis in the least-squares sense (what a 360 capture looks
  at; instant-ngp centres there), or None where the axes are too close to parallel to meet (forward-facing
  captures): the smallest eigenvalue of sum(I - d d^T) below `min_spread` times the largest."""
  poses = np.asarray(poses_Nx4x4, np.float64)
  d = -poses[:, :3, 2]
  d = d / np.linalg.norm(d, axis=1, keepdims=True)
  proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
  a = proj.sum(0)
  eig = np.linalg.eigvalsh(a)
  if eig[0] < min_spread * eig[-1]:
    return None
  return np.linalg.solve(a, np.einsum("nij,nj->i", proj, poses[:, :3, 3]))
