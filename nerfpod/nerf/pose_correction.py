"""Per-frame camera pose corrections (pose refinement, nerfacto's camera optimiser, its SO3xR3 form).

A training frame's correction is a 6-vector `(t, w)`: a translation t (world units) and a rotation w
(axis-angle, radians, exponentiated with Rodrigues' formula). It moves the frame's camera-to-world pose
[R | o] to [exp(w) R | o + t]: the camera turns by exp(w) about its own centre, in world axes, and shifts by
t. A ray of that frame, origin o and direction d = R c (c its camera-space direction), becomes
(o + t, exp(w) d): the world-space ray is all the correction needs, so the step re-derives the corrected ray
from the batch's rays and frame indices inside the differentiated function. A zero correction is the
identity exactly (exp(0) = I bit for bit), so rays are unchanged to the bit.

Shapes: N frames (or rays), vectors (..., 6) as [tx, ty, tz, wx, wy, wz].
"""
import jax.numpy as jnp
import numpy as np

from nerfpod.nerf import cameras as nerf_cameras

# The model's parameter holding the corrections, (N, 6) per training frame (nerf/model.py).
PARAM = "pose_correction"

# Below this squared angle, sin(a)/a and (1 - cos a)/a^2 are their Taylor series (exact to float32 there,
# and differentiable at 0, where the closed forms divide 0 by 0).
_SMALL_ANGLE_SQ = 1e-4


def _skew(w):
  """(..., 3) -> (..., 3, 3): the cross-product matrix [w]x, with [w]x v = w x v."""
  zero = jnp.zeros_like(w[..., 0])
  return jnp.stack([jnp.stack([zero, -w[..., 2], w[..., 1]], -1),
                    jnp.stack([w[..., 2], zero, -w[..., 0]], -1),
                    jnp.stack([-w[..., 1], w[..., 0], zero], -1)], -2)


def so3_exp(w_Nx3):
  """Rotation matrices (..., 3, 3) of axis-angle vectors: I + sin(a)/a [w]x + (1 - cos a)/a^2 [w]x^2, a = |w|."""
  w = jnp.asarray(w_Nx3)
  a2 = jnp.sum(w * w, axis=-1)[..., None, None]
  small = a2 < _SMALL_ANGLE_SQ
  safe = jnp.where(small, 1.0, a2)  # no 0/0 in either branch's value or gradient
  a = jnp.sqrt(safe)
  sin_a = jnp.where(small, 1.0 - a2 / 6.0 + a2 * a2 / 120.0, jnp.sin(a) / a)
  cos_a = jnp.where(small, 0.5 - a2 / 24.0 + a2 * a2 / 720.0, (1.0 - jnp.cos(a)) / safe)
  k = _skew(w)
  return jnp.eye(3, dtype=w.dtype) + sin_a * k + cos_a * (k @ k)


def _skew_numpy(v) -> np.ndarray:
  """_skew in float64 NumPy: (..., 3) -> (..., 3, 3), [v]x u = v x u."""
  v = np.asarray(v, np.float64)
  k = np.zeros(v.shape + (3,))
  k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
  k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
  return k


def so3_exp_numpy(w_Nx3) -> np.ndarray:
  """so3_exp in float64 NumPy (for exports, outside the traced step)."""
  w = np.asarray(w_Nx3, np.float64)
  a = np.linalg.norm(w, axis=-1)[..., None, None]
  safe = np.where(a > 1e-8, a, 1.0)
  sin_a = np.where(a > 1e-8, np.sin(safe) / safe, 1.0 - a * a / 6.0)
  cos_a = np.where(a > 1e-8, (1.0 - np.cos(safe)) / (safe * safe), 0.5 - a * a / 24.0)
  k = _skew_numpy(w)
  return np.eye(3) + sin_a * k + cos_a * (k @ k)


def correct_rays(origins_Rx3, directions_Rx3, corrections_Rx6):
  """Each ray moved by its own frame's correction: (o + t, exp(w) d)."""
  rotation = so3_exp(corrections_Rx6[..., 3:])
  directions = jnp.einsum("...ij,...j->...i", rotation, directions_Rx3)
  return origins_Rx3 + corrections_Rx6[..., :3], directions


def of_params(params) -> np.ndarray | None:
  """The training frames' corrections (N, 6), NumPy, of a model's parameters (replicated arrays: this
  process's copy), or None where the run had no pose refinement."""
  corrections = params["params"].get(PARAM)
  if corrections is None:
    return None
  return np.asarray(corrections.addressable_data(0) if hasattr(corrections, "addressable_data") else corrections)


def corrected_poses(poses_Nx4x4, corrections_Nx6) -> np.ndarray:
  """Camera-to-world poses (N, 4, 4) with their corrections applied, float64 NumPy: [exp(w) R | o + t]."""
  poses = np.array(poses_Nx4x4, np.float64)
  corrections = np.asarray(corrections_Nx6, np.float64)
  poses[:, :3, :3] = so3_exp_numpy(corrections[:, 3:]) @ poses[:, :3, :3]
  poses[:, :3, 3] += corrections[:, :3]
  return poses


# CamP's preconditioning (Park et al. 2023, "Camera Preconditioning for Neural Radiance Fields"): the points
# each camera's sensitivity is averaged over, and the damping added to J^T J's diagonal before its inverse
# square root (a share of that diagonal, as CamP's relative padding; Levenberg-Marquardt's damping).
PRECONDITION_POINTS = 512
PRECONDITION_DAMPING = 1e-2
_UNBOUNDED_FAR = 1e6


def projection_jacobians(poses_Nx4x4, cameras, points_NxKx3) -> np.ndarray:
  """d(projection)/d(correction) at the zero correction, (N, K, 2, 6) float64: how each point's image moves
  (in image sizes: pixels over the camera's larger side, so one number for any resolution) as the frame's
  correction (t, w) moves its camera. `cameras`: nerf.cameras.Cameras of the N frames (pinhole: the lens
  distortion is left out). For a point X at p = X - o from the camera, camera coordinates c = R^T exp(w)^T
  (p - t) (OpenGL: the camera looks down -z), so dc/dt = -R^T and dc/dw = R^T [p]x at zero; the image
  u = cx + fx c_x / -c_z, v = cy + fy c_y / c_z."""
  poses = np.asarray(poses_Nx4x4, np.float64)
  rot, origin = poses[:, :3, :3], poses[:, :3, 3]
  p = np.asarray(points_NxKx3, np.float64) - origin[:, None, :]
  rt = np.swapaxes(rot, -1, -2)  # world -> camera
  c = np.einsum("nij,nkj->nki", rt, p)
  dc = np.concatenate([np.broadcast_to(-rt[:, None], p.shape[:2] + (3, 3)),
                       np.einsum("nij,nkjl->nkil", rt, _skew_numpy(p))], -1)  # (N, K, 3, 6)
  size = np.maximum(np.asarray(cameras.width, np.float64), np.asarray(cameras.height, np.float64))
  fx, fy = (np.asarray(f, np.float64)[:, None] / size[:, None] for f in (cameras.fx, cameras.fy))
  cx_, cy_, cz = c[..., 0], c[..., 1], c[..., 2]
  duv_dc = np.zeros(c.shape[:2] + (2, 3))
  duv_dc[..., 0, 0], duv_dc[..., 0, 2] = -fx / cz, fx * cx_ / cz**2
  duv_dc[..., 1, 1], duv_dc[..., 1, 2] = fy / cz, -fy * cy_ / cz**2
  return duv_dc @ dc


def frustum_points(poses_Nx4x4, cameras, near: float, far: float, count: int = PRECONDITION_POINTS,
                   seed: int = 0) -> np.ndarray:
  """(N, count, 3) world points inside each camera's view: pixels drawn uniformly over its image, each ray
  through its own camera and lens (nerf.cameras.frame_rays), depths uniformly in disparity (1 / depth) between
  near and far (an unbounded far counts as 1e6), so near and far content both weigh in, as along the rays the
  sampler spaces."""
  rng = np.random.default_rng(seed)
  poses = np.asarray(poses_Nx4x4, np.float64)
  n = len(poses)
  near = max(float(near), 1e-3 * min(float(far), _UNBOUNDED_FAR))
  far = min(float(far), _UNBOUNDED_FAR)
  cols = rng.uniform(0, 1, (n, count)) * np.asarray(cameras.width, np.float64)[:, None]
  rows = rng.uniform(0, 1, (n, count)) * np.asarray(cameras.height, np.float64)[:, None]
  depth = 1.0 / rng.uniform(1.0 / far, 1.0 / near, (n, count))
  frames = np.broadcast_to(np.arange(n)[:, None], (n, count))
  origins, directions = nerf_cameras.frame_rays(poses[:, None], cameras, frames, rows, cols, pixel_center=0.0)
  return origins + directions * depth[..., None].astype(np.float32)  # directions: camera-space z = -1


def preconditioners(poses_Nx4x4, cameras, near: float, far: float, damping: float = PRECONDITION_DAMPING,
                    count: int = PRECONDITION_POINTS) -> np.ndarray:
  """CamP's preconditioners (N, 6, 6) float32: per frame M = (J^T J + damping diag(J^T J))^(-1/2), J^T J the
  mean over frustum_points of projection_jacobians' J^T J. Optimising v with the correction = M v makes a unit
  step of v in any direction move the frame's image by about one image size (mean square), and decorrelates
  what moves it alike (a sideways shift and a turn, for a distant scene)."""
  jac = projection_jacobians(poses_Nx4x4, cameras, frustum_points(poses_Nx4x4, cameras, near, far, count))
  jtj = np.einsum("nkai,nkaj->nij", jac, jac) / jac.shape[1]
  jtj = jtj + damping * np.einsum("nii->ni", jtj)[:, :, None] * np.eye(6)
  values, vectors = np.linalg.eigh(jtj)
  return np.einsum("nij,nj,nkj->nik", vectors, 1.0 / np.sqrt(values), vectors).astype(np.float32)
