"""Camera paths in nerfstudio's `camera_path.json` format: what its viewer exports and `ns-render` reads.

    {"camera_type": "perspective", "render_width": W, "render_height": H, "fps": 30, "seconds": 4,
     "camera_path": [{"camera_to_world": [16 numbers, row-major 4x4], "fov": degrees, "aspect": W / H}, ...],
     "keyframes": [...]}

`camera_to_world` is an OpenGL camera-to-world matrix (the camera looks down -z, +y up) in the scene's
frame, i.e. the frame the field was trained in (nerfpod's normalised frame for captures). `fov` is the
vertical field of view in degrees, as three.js and nerfstudio define it: focal = H / 2 / tan(fov / 2). The
render size is the file's `render_width` x `render_height`. Only perspective cameras are supported; other
keys (keyframes, smoothness, crop) are kept by `write` when given and ignored by `read`.
"""
import dataclasses
import json
import math

import numpy as np

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.nerf import cameras


@dataclasses.dataclass(frozen=True)
class CameraPath:
  """The cameras of a path: poses with a vertical field of view each, one image size, a frame rate."""
  poses: np.ndarray      # (N, 4, 4) float64 camera-to-world, OpenGL convention, in the scene's frame
  fov_y_deg: np.ndarray  # (N,) float64 vertical field of view of each camera, degrees
  width: int
  height: int
  fps: float

  def __len__(self) -> int:
    return len(self.poses)

  def intrinsics(self, index: int) -> cameras.Intrinsics:
    """Frame `index`'s pinhole camera: square pixels, principal point at the centre."""
    return cameras.Intrinsics.from_focal(self.width, self.height,
                                         focal_from_fov(self.fov_y_deg[index], self.height))


def focal_from_fov(fov_y_deg: float, height: int) -> float:
  """three.js's (and nerfstudio's) focal length in pixels of a vertical field of view over `height` pixels."""
  return 0.5 * height / math.tan(0.5 * math.radians(float(fov_y_deg)))


def _fail(path, what: str) -> UserError:
  return UserError(f"camera path {path}: {what}; write it in nerfstudio's camera_path.json format "
                   f"(render_width, render_height, camera_path: [{{camera_to_world, fov}}, ...]).")


def read(path) -> CameraPath:
  """Reads a camera_path.json, local or in a bucket (gs://); a missing file, bad JSON or a malformed camera is
  one sentence (UserError)."""
  try:
    spec = json.loads(storage.read_bytes(path))
  except FileNotFoundError:
    raise UserError(f"camera path {path} does not exist; give the path of a camera_path.json file.") from None
  except (OSError, ValueError) as e:
    raise _fail(path, f"it is not readable JSON ({e})") from None
  if not isinstance(spec, dict):
    raise _fail(path, "it is not a JSON object")
  camera_type = spec.get("camera_type", "perspective")
  if camera_type != "perspective":
    raise UserError(f"camera path {path}: camera_type {camera_type!r} is not supported; only 'perspective' "
                    f"paths can be rendered.")
  try:
    width, height = int(spec["render_width"]), int(spec["render_height"])
    fps = float(spec.get("fps", 30))
    frames = spec["camera_path"]
    poses = np.array([np.asarray(c["camera_to_world"], np.float64).reshape(4, 4) for c in frames])
    fov = np.array([float(c["fov"]) for c in frames], np.float64)
  except KeyError as e:
    raise _fail(path, f"it has no {e.args[0]!r}") from None
  except (TypeError, ValueError) as e:
    raise _fail(path, f"a value is malformed ({e})") from None
  if width < 1 or height < 1:
    raise _fail(path, f"the render size {width}x{height} is not positive")
  if not len(poses):
    raise _fail(path, "camera_path lists no camera")
  bad = np.flatnonzero(~(np.isfinite(poses).all(axis=(1, 2)) & np.isfinite(fov) & (fov > 0) & (fov < 180)))
  if bad.size:
    raise _fail(path, f"camera {bad[0]} has a non-finite matrix or a field of view outside (0, 180) degrees")
  if not fps > 0:
    raise _fail(path, f"fps {fps:g} is not positive")
  return CameraPath(poses, fov, width, height, fps)


def write(path, camera_path: CameraPath, **extra) -> None:
  """Writes `camera_path` as a camera_path.json that nerfstudio and `read` accept; `extra` keys (e.g.
  keyframes, seconds, is_cycle) are stored beside it."""
  spec = {"camera_type": "perspective", "render_width": int(camera_path.width),
          "render_height": int(camera_path.height), "fps": float(camera_path.fps),
          "seconds": len(camera_path) / float(camera_path.fps),
          "camera_path": [{"camera_to_world": np.asarray(p, np.float64).reshape(16).tolist(), "fov": float(f),
                           "aspect": camera_path.width / camera_path.height}
                          for p, f in zip(camera_path.poses, camera_path.fov_y_deg)]} | extra
  with open(path, "w") as f:
    json.dump(spec, f, indent=1)
