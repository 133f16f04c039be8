"""Pinhole cameras and rays (host side, NumPy).

Conventions (those of the NeRF synthetic data): a pose is a camera-to-world matrix (3x4 or 4x4); the
camera looks down its -z axis with +y up and +x right (OpenGL). Image pixel (row i, column j) covers the
continuous image coordinates [j, j+1) x [i, i+1); `pixel_center` is where inside that square its ray goes:
0.5 (the default) is the true centre, 0.0 reproduces the original NeRF code and the Tiny NeRF tutorial,
whose rays pass through pixel corners.
"""
import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Intrinsics:
  """A pinhole camera: image size in pixels, focal lengths and principal point in pixels."""
  width: int
  height: int
  fx: float
  fy: float
  cx: float
  cy: float

  @classmethod
  def from_focal(cls, width: int, height: int, focal: float) -> "Intrinsics":
    """Square pixels, principal point at the image centre (the Blender and Tiny NeRF cameras)."""
    return cls(int(width), int(height), float(focal), float(focal), width / 2.0, height / 2.0)


def pixel_directions(intr: Intrinsics, rows, cols, pixel_center: float = 0.5) -> np.ndarray:
  """Camera-space ray directions (z = -1) through pixels (rows, cols); any matching shapes -> (..., 3)."""
  x = (np.asarray(cols, np.float64) + pixel_center - intr.cx) / intr.fx
  y = -(np.asarray(rows, np.float64) + pixel_center - intr.cy) / intr.fy
  return np.stack([x, y, -np.ones_like(x)], axis=-1)


def rays_for_pixels(c2w: np.ndarray, intr: Intrinsics, rows, cols,
                    pixel_center: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """World-space rays through pixels (rows, cols) of cameras c2w (..., 3 or 4, 4), broadcast together.

  Returns (origins, directions), float32, shape (..., 3). Directions are not normalised: their camera-space
  z is -1, so a point at ray parameter t lies at depth t in front of the camera.
  """
  c2w = np.asarray(c2w, np.float64)[..., :3, :4]
  dirs_cam = pixel_directions(intr, rows, cols, pixel_center)
  directions = np.einsum("...ij,...j->...i", c2w[..., :3, :3], dirs_cam)
  origins = np.broadcast_to(c2w[..., :3, 3], directions.shape)
  return origins.astype(np.float32), directions.astype(np.float32)


def image_rays(c2w: np.ndarray, intr: Intrinsics,
               pixel_center: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """All rays of one image, (H, W, 3) origins and directions."""
  rows, cols = np.meshgrid(np.arange(intr.height), np.arange(intr.width), indexing="ij")
  return rays_for_pixels(np.asarray(c2w)[None, None], intr, rows, cols, pixel_center)


def project(points_Nx3: np.ndarray, c2w: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
  """Continuous image coordinates (x = column, y = row) and depth of world points seen by camera c2w."""
  c2w = np.asarray(c2w, np.float64)
  rot, trans = c2w[:3, :3], c2w[:3, 3]
  cam = (np.asarray(points_Nx3, np.float64) - trans) @ rot  # world -> camera: R^T (p - t)
  depth = -cam[..., 2]
  x = cam[..., 0] / depth * intr.fx + intr.cx
  y = -cam[..., 1] / depth * intr.fy + intr.cy
  return np.stack([x, y], axis=-1), depth


def look_at(eye: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
  """The 4x4 camera-to-world pose of a camera at `eye` looking at `target`, its +y towards `up`."""
  eye = np.asarray(eye, np.float64)
  forward = np.asarray(target, np.float64) - eye
  forward /= np.linalg.norm(forward)
  right = np.cross(forward, np.asarray(up, np.float64))
  right /= np.linalg.norm(right)
  cam_up = np.cross(right, forward)
  pose = np.eye(4)
  pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, cam_up, -forward, eye
  return pose


def spherical_pose(azimuth_deg: float, elevation_deg: float, radius: float) -> np.ndarray:
  """The Tiny NeRF tutorial's `pose_spherical(theta, phi, radius)`: a camera on a sphere looking at the origin.

  Its convention is kept so that its numbers mean the same here: elevation (phi) is measured downwards, so
  the tutorial's -30 puts the camera 30 degrees *above* the z = 0 plane, looking down at the object.
  """
  az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
  trans_t = np.eye(4)
  trans_t[2, 3] = radius
  rot_phi = np.array([[1, 0, 0, 0], [0, np.cos(el), -np.sin(el), 0], [0, np.sin(el), np.cos(el), 0],
                      [0, 0, 0, 1]])
  rot_theta = np.array([[np.cos(az), 0, -np.sin(az), 0], [0, 1, 0, 0], [np.sin(az), 0, np.cos(az), 0],
                        [0, 0, 0, 1]])
  swap = np.array([[-1, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], np.float64)
  return swap @ rot_theta @ rot_phi @ trans_t
