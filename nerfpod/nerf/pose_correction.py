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


def so3_exp_numpy(w_Nx3) -> np.ndarray:
  """so3_exp in float64 NumPy (for exports, outside the traced step)."""
  w = np.asarray(w_Nx3, np.float64)
  a = np.linalg.norm(w, axis=-1)[..., None, None]
  safe = np.where(a > 1e-8, a, 1.0)
  sin_a = np.where(a > 1e-8, np.sin(safe) / safe, 1.0 - a * a / 6.0)
  cos_a = np.where(a > 1e-8, (1.0 - np.cos(safe)) / (safe * safe), 0.5 - a * a / 24.0)
  k = np.zeros(w.shape[:-1] + (3, 3))
  k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
  k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
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
