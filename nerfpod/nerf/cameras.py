"""Cameras and rays (host side, NumPy): pinhole cameras with optional lens distortion.

Conventions (those of the NeRF synthetic data): a pose is a camera-to-world matrix (3x4 or 4x4); the
camera looks down its -z axis with +y up and +x right (OpenGL). Image pixel (row i, column j) covers the
continuous image coordinates [j, j+1) x [i, i+1) (COLMAP's convention: the top-left pixel's centre is at
(0.5, 0.5)); `pixel_center` is where inside that square its ray goes: 0.5 (the default) is the true centre,
0.0 reproduces the original NeRF code and the Tiny NeRF tutorial, whose rays pass through pixel corners.

Lens distortion is OpenCV's radial-tangential model on normalised image coordinates (x right, y down, as
the lens sees them), the one COLMAP's SIMPLE_RADIAL, RADIAL and OPENCV models are special cases of:

    r2 = x^2 + y^2,  d = 1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4
    xd = x d + 2 p1 x y + p2 (r2 + 2 x^2),   yd = y d + 2 p2 x y + p1 (r2 + 2 y^2)

A captured pixel sits at the *distorted* position; its ray goes through the undistorted one, found per
ray by 10 Newton iterations (multinerf's camera_utils). Per ray rather than by undistorting the images once:
no resampling blurs the pixels, no pixel is lost at the borders, and the training pixels stay the captured
ones; the cost is a few dozen flops per ray on the host, negligible beside the model.
"""
import dataclasses

import numpy as np

# Camera axes: OpenCV's (COLMAP's, viser's: x right, y down, looking down +z) -> OpenGL's (nerfpod's: y up,
# looking down -z): c2w_opengl[:3, :3] = c2w_opencv[:3, :3] @ OPENCV_TO_OPENGL (it is its own inverse).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])

# The distortion parameters every camera carries, in this order; all zero is a pinhole camera.
DISTORTION_PARAMS = ("k1", "k2", "k3", "k4", "p1", "p2")
NO_DISTORTION = (0.0,) * len(DISTORTION_PARAMS)


@dataclasses.dataclass(frozen=True)
class Intrinsics:
  """One camera: image size in pixels, focal lengths and principal point in pixels, and its lens
  distortion (k1, k2, k3, k4, p1, p2; all zero for a pinhole camera)."""
  width: int
  height: int
  fx: float
  fy: float
  cx: float
  cy: float
  distortion: tuple[float, ...] = NO_DISTORTION

  @classmethod
  def from_focal(cls, width: int, height: int, focal: float) -> "Intrinsics":
    """Square pixels, principal point at the image centre (the Blender and Tiny NeRF cameras)."""
    return cls(int(width), int(height), float(focal), float(focal), width / 2.0, height / 2.0)

  @property
  def is_distorted(self) -> bool:
    return any(self.distortion)


@dataclasses.dataclass(frozen=True)
class Cameras:
  """The cameras of a split's N frames, one entry per frame (real captures mix sizes and lenses).

  Arrays rather than one object per frame, so that a batch of rays from many frames is computed at once.
  """
  width: np.ndarray       # (N,) int64 pixels
  height: np.ndarray      # (N,) int64 pixels
  fx: np.ndarray          # (N,) float64 focal lengths, pixels
  fy: np.ndarray          # (N,) float64
  cx: np.ndarray          # (N,) float64 principal point, pixels (continuous coordinates, see above)
  cy: np.ndarray          # (N,) float64
  distortion: np.ndarray  # (N, 6) float64 k1, k2, k3, k4, p1, p2

  @classmethod
  def stack(cls, intrinsics: "list[Intrinsics] | tuple[Intrinsics, ...]") -> "Cameras":
    """Cameras from one Intrinsics per frame."""
    col = lambda name, dtype: np.asarray([getattr(i, name) for i in intrinsics], dtype)
    dist = np.asarray([tuple(i.distortion) for i in intrinsics], np.float64).reshape(len(intrinsics), -1)
    if dist.shape[1] != len(DISTORTION_PARAMS):
      raise ValueError(f"distortion needs {len(DISTORTION_PARAMS)} parameters {DISTORTION_PARAMS}")
    return cls(col("width", np.int64), col("height", np.int64), col("fx", np.float64), col("fy", np.float64),
               col("cx", np.float64), col("cy", np.float64), dist)

  @classmethod
  def repeat(cls, intr: Intrinsics, n: int) -> "Cameras":
    """n frames taken with the same camera."""
    return cls.stack([intr] * n)

  def __len__(self) -> int:
    return len(self.width)

  def __getitem__(self, index: int) -> Intrinsics:
    """Frame `index`'s camera."""
    return Intrinsics(int(self.width[index]), int(self.height[index]), float(self.fx[index]),
                      float(self.fy[index]), float(self.cx[index]), float(self.cy[index]),
                      tuple(float(v) for v in self.distortion[index]))

  def select(self, indices) -> "Cameras":
    """The cameras of frames `indices` (an index array or a boolean mask), in that order."""
    return Cameras(*(getattr(self, f.name)[indices] for f in dataclasses.fields(self)))

  @property
  def num_pixels(self) -> np.ndarray:
    """(N,) int64 pixels per frame."""
    return self.width * self.height

  @property
  def is_distorted(self) -> bool:
    return bool(np.any(self.distortion))


def distort(x, y, distortion):
  """Normalised undistorted coordinates (x, y; y down) -> distorted (xd, yd): the model above.
  `distortion` (..., 6) broadcasts against x and y."""
  k1, k2, k3, k4, p1, p2 = np.moveaxis(np.asarray(distortion, np.float64), -1, 0)
  r2 = x * x + y * y
  d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
  return (x * d + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
          y * d + 2.0 * p2 * x * y + p1 * (r2 + 2.0 * y * y))


def undistort(xd, yd, distortion, iterations: int = 10, eps: float = 1e-9):
  """Distorted normalised coordinates -> undistorted ones: Newton's method on distort(x, y) = (xd, yd),
  from (xd, yd), `iterations` times (multinerf's _radial_and_tangential_undistort). A step whose Jacobian is
  singular (|det| <= eps) is skipped."""
  k1, k2, k3, k4, p1, p2 = np.moveaxis(np.asarray(distortion, np.float64), -1, 0)
  xd, yd = np.asarray(xd, np.float64), np.asarray(yd, np.float64)
  x, y = xd.copy(), yd.copy()
  for _ in range(iterations):
    r2 = x * x + y * y
    d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    d_r = k1 + r2 * (2.0 * k2 + r2 * (3.0 * k3 + r2 * 4.0 * k4))  # d(d)/d(r2)
    d_x, d_y = 2.0 * x * d_r, 2.0 * y * d_r
    fx = d * x + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
    fy = d * y + 2.0 * p2 * x * y + p1 * (r2 + 2.0 * y * y) - yd
    fx_x = d + d_x * x + 2.0 * p1 * y + 6.0 * p2 * x
    fx_y = d_y * x + 2.0 * p1 * x + 2.0 * p2 * y
    fy_x = d_x * y + 2.0 * p2 * y + 2.0 * p1 * x
    fy_y = d + d_y * y + 2.0 * p2 * x + 6.0 * p1 * y
    det = fx_x * fy_y - fx_y * fy_x
    ok = np.abs(det) > eps
    safe = np.where(ok, det, 1.0)
    x = x - np.where(ok, (fx * fy_y - fy * fx_y) / safe, 0.0)
    y = y - np.where(ok, (fy * fx_x - fx * fy_x) / safe, 0.0)
  return x, y


def _directions(cols, rows, fx, fy, cx, cy, distortion, pixel_center: float) -> np.ndarray:
  """Camera-space (OpenGL, z = -1) directions through pixels; every argument broadcasts, `distortion`
  (..., 6) or None for pinhole cameras."""
  x = (np.asarray(cols, np.float64) + pixel_center - cx) / fx
  y = (np.asarray(rows, np.float64) + pixel_center - cy) / fy  # y down, as the lens model has it
  if distortion is not None:
    x, y = undistort(x, y, distortion)
  return np.stack([x, -y, -np.ones_like(x)], axis=-1)


def pixel_directions(intr: Intrinsics, rows, cols, pixel_center: float = 0.5) -> np.ndarray:
  """Camera-space ray directions (z = -1) through pixels (rows, cols); any matching shapes -> (..., 3)."""
  distortion = np.asarray(intr.distortion, np.float64) if intr.is_distorted else None
  return _directions(cols, rows, intr.fx, intr.fy, intr.cx, intr.cy, distortion, pixel_center)


def _to_world(c2w, dirs_cam) -> tuple[np.ndarray, np.ndarray]:
  c2w = np.asarray(c2w, np.float64)[..., :3, :4]
  directions = np.einsum("...ij,...j->...i", c2w[..., :3, :3], dirs_cam)
  origins = np.broadcast_to(c2w[..., :3, 3], directions.shape)
  return origins.astype(np.float32), directions.astype(np.float32)


def frame_rays(c2w: np.ndarray, cams: Cameras, frames, rows, cols,
               pixel_center: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """World-space rays through pixels (rows, cols) of frames `frames` (index arrays of one shape), each
  through its own frame's camera (size, focal, principal point, distortion) and pose c2w (same shape + 4x4).
  Returns (origins, directions), float32 (..., 3), directions with camera-space z = -1."""
  frames = np.asarray(frames)
  distortion = cams.distortion[frames] if cams.is_distorted else None
  dirs_cam = _directions(cols, rows, cams.fx[frames], cams.fy[frames], cams.cx[frames], cams.cy[frames],
                         distortion, pixel_center)
  return _to_world(c2w, dirs_cam)


def rays_for_pixels(c2w: np.ndarray, intr: Intrinsics, rows, cols,
                    pixel_center: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """World-space rays through pixels (rows, cols) of cameras c2w (..., 3 or 4, 4), broadcast together.

  Returns (origins, directions), float32, shape (..., 3). Directions are not normalised: their camera-space
  z is -1, so a point at ray parameter t lies at depth t in front of the camera.
  """
  return _to_world(c2w, pixel_directions(intr, rows, cols, pixel_center))


def image_rays(c2w: np.ndarray, intr: Intrinsics,
               pixel_center: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """All rays of one image, (H, W, 3) origins and directions."""
  rows, cols = np.meshgrid(np.arange(intr.height), np.arange(intr.width), indexing="ij")
  return rays_for_pixels(np.asarray(c2w)[None, None], intr, rows, cols, pixel_center)


def project(points_Nx3: np.ndarray, c2w: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
  """Continuous image coordinates (x = column, y = row) and depth of world points seen by camera c2w,
  through its lens distortion."""
  c2w = np.asarray(c2w, np.float64)
  rot, trans = c2w[:3, :3], c2w[:3, 3]
  cam = (np.asarray(points_Nx3, np.float64) - trans) @ rot  # world -> camera: R^T (p - t)
  depth = -cam[..., 2]
  x, y = cam[..., 0] / depth, -cam[..., 1] / depth
  if intr.is_distorted:
    x, y = distort(x, y, np.asarray(intr.distortion, np.float64))
  return np.stack([x * intr.fx + intr.cx, y * intr.fy + intr.cy], axis=-1), depth


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


def rotation_to_quaternion(rotation_3x3) -> np.ndarray:
  """The unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method: the largest of
  the four squared components is taken first, so no division by a small number)."""
  m = np.asarray(rotation_3x3, np.float64)
  trace = np.trace(m)
  squares = np.array([1 + trace, 1 + 2 * m[0, 0] - trace, 1 + 2 * m[1, 1] - trace, 1 + 2 * m[2, 2] - trace])
  k = int(np.argmax(squares))
  big = 0.5 * np.sqrt(squares[k])
  s = 0.25 / big
  if k == 0:
    q = [big, (m[2, 1] - m[1, 2]) * s, (m[0, 2] - m[2, 0]) * s, (m[1, 0] - m[0, 1]) * s]
  elif k == 1:
    q = [(m[2, 1] - m[1, 2]) * s, big, (m[0, 1] + m[1, 0]) * s, (m[0, 2] + m[2, 0]) * s]
  elif k == 2:
    q = [(m[0, 2] - m[2, 0]) * s, (m[0, 1] + m[1, 0]) * s, big, (m[1, 2] + m[2, 1]) * s]
  else:
    q = [(m[1, 0] - m[0, 1]) * s, (m[0, 2] + m[2, 0]) * s, (m[1, 2] + m[2, 1]) * s, big]
  q = np.array(q) / np.linalg.norm(q)
  return q if q[0] >= 0 else -q


def quaternion_to_rotation(wxyz) -> np.ndarray:
  """The 3x3 rotation matrix of a quaternion (w, x, y, z) (normalised first)."""
  w, x, y, z = np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz)
  return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def pose_from_opencv(wxyz, position) -> np.ndarray:
  """A camera given as (w, x, y, z) orientation of its OpenCV camera-to-world and position (a web viewer's,
  viser's) -> nerfpod's 4x4 OpenGL camera-to-world pose."""
  pose = np.eye(4)
  pose[:3, :3] = quaternion_to_rotation(wxyz) @ OPENCV_TO_OPENGL
  pose[:3, 3] = position
  return pose


def pose_to_opencv(pose_4x4) -> tuple[np.ndarray, np.ndarray]:
  """nerfpod's OpenGL camera-to-world pose -> (w, x, y, z) of the OpenCV camera-to-world, position."""
  pose = np.asarray(pose_4x4, np.float64)
  return rotation_to_quaternion(pose[:3, :3] @ OPENCV_TO_OPENGL), pose[:3, 3].copy()


def intrinsics_from_fov(fov_y_rad: float, width: int, height: int) -> Intrinsics:
  """A pinhole camera of `width` x `height` pixels with a vertical field of view of `fov_y_rad`."""
  return Intrinsics.from_focal(width, height, 0.5 * height / np.tan(0.5 * fov_y_rad))


def fov_y(intr: Intrinsics) -> float:
  """The vertical field of view of a pinhole camera, radians."""
  return float(2 * np.arctan(0.5 * intr.height / intr.fy))
