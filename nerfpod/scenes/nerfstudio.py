"""transforms.json as nerfstudio's ns-process-data and instant-ngp's colmap2nerf.py write it.

Intrinsics fl_x, fl_y, cx, cy, w, h at the top level or per frame (a frame's own win); where fl_x is absent,
camera_angle_x (and camera_angle_y) give it, as in instant-ngp and multinerf; w and h default to the image's
size, cx and cy to its centre. Distortion k1, k2, k3, k4, p1, p2 (or nerfstudio's distortion_params) with
camera_model SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV (instant-ngp writes none: the keys
alone say it); fisheye and equirectangular cameras are refused. file_path is relative to the JSON's folder
and has its extension; transform_matrix is camera-to-world OpenGL. Frames are sorted by file path, as
nerfstudio does. Explicit train_filenames / val_filenames / test_filenames win; otherwise every
data.llffhold-th frame is held out as test (and val). With data.downscale = N, images come from images_N/
(nerfstudio's layout) where it exists, else are shrunk on loading. Masks and depth files are not used.
"""
import os

import numpy as np

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Cameras, DISTORTION_PARAMS
from nerfpod.scenes import capture
from nerfpod.scenes.base import Scene, capture_scene, check_poses, read_json, unscaled

TRANSFORMS = "transforms.json"
PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def _number(meta: dict, frame: dict, key: str, where: str):
  value = frame.get(key, meta.get(key))
  if value is None:
    return None
  try:
    value = float(value)
  except (TypeError, ValueError) as e:
    raise UserError(f"{where}: {key} is {value!r}, not a number.") from e
  return value


def _distortion(meta: dict, frame: dict, where: str) -> list[float]:
  params = frame.get("distortion_params", meta.get("distortion_params"))
  if params is not None:  # nerfstudio's [k1, k2, k3, k4, p1, p2]
    if not isinstance(params, list) or len(params) != 6:
      raise UserError(f"{where}: distortion_params must list 6 numbers (k1, k2, k3, k4, p1, p2).")
    return [float(v) for v in params]
  return [_number(meta, frame, k, where) or 0.0 for k in DISTORTION_PARAMS]


def _image_path(base: str, file_path: str, downscale: int) -> tuple[str, int]:
  """(the file to read, factor still to apply): nerfstudio's images_N/ counterpart of images/... where
  data.downscale = N > 1 and it exists."""
  path = storage.normpath(storage.join(base, file_path))
  if downscale > 1:
    parent, name = os.path.split(path)
    shrunk = storage.join(parent + f"_{downscale}", name)
    if storage.isfile(shrunk):
      return shrunk, 1
  return path, downscale


def _read_meta(path: str) -> dict:
  meta = read_json(path)
  if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
    raise UserError(f"{path} needs a non-empty 'frames' list; is it a nerfstudio / instant-ngp transforms file?")
  return meta


def load(path: str, data_config, shards=None) -> Scene:
  """`path`: a folder holding transforms.json, or the JSON file itself."""
  path = _transforms_path(path)
  meta = _read_meta(path)
  _check_camera_model(meta, path)
  frames = _frames(meta, path)
  names = [str(f["file_path"]) for f in frames]
  base = os.path.dirname(path)
  downscale = int(data_config.downscale)
  located = [_image_path(base, n, downscale) for n in names]
  capture.check_files_exist([p for p, _ in located], names, path)
  poses = _poses(frames, names, path)
  widths, heights = capture.image_sizes([p for p, _ in located], names, [f for _, f in located])
  cams = _cameras(meta, frames, names, widths, heights, path, downscale)
  name = os.path.basename(storage.normpath(base)) or "capture"
  framing = capture.frame(poses, None, names, data_config, "nerfstudio", path, default_space="unbounded",
                          split_lists=_split_lists(meta, names, path))
  read = lambda i: capture.read_image(located[i][0], names[i], located[i][1])
  return capture_scene(name, "nerfstudio", read, cams, names, framing, path, capture.READ_THREADS, shards)


def _transforms_path(path: str) -> str:
  """The transforms file of data.path: the file itself, or transforms.json in the folder."""
  if storage.isdir(path):
    path = storage.join(path, TRANSFORMS)
  if not storage.isfile(path):
    raise UserError(f"{path} not found; set --config.data.path to a folder holding {TRANSFORMS} (or to the file).")
  return path


def _check_camera_model(meta: dict, path: str) -> None:
  """Refuses a camera that is not a perspective one (fisheye, equirectangular, ...) in one sentence."""
  model = str(meta.get("camera_model", "OPENCV")).upper()
  if model not in PERSPECTIVE_MODELS or meta.get("is_fisheye"):
    raise UserError(f"{path} describes {'a fisheye' if meta.get('is_fisheye') else 'a ' + model} camera, which "
                    f"nerfpod does not handle (it handles {', '.join(PERSPECTIVE_MODELS)}); undistort the images "
                    f"to a perspective camera first.")


def _frames(meta: dict, path: str) -> list[dict]:
  """The frames, each with its file_path and transform_matrix, sorted by file path (as nerfstudio does)."""
  frames = []
  for i, frame in enumerate(meta["frames"]):
    if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
      raise UserError(f"{path}: frame {i} needs 'file_path' and 'transform_matrix'.")
    frames.append(frame)
  frames.sort(key=lambda f: str(f["file_path"]))
  return frames


def _poses(frames: list[dict], names: list[str], path: str) -> np.ndarray:
  """(N, 4, 4) camera-to-world OpenGL poses of the frames' transform_matrix (3x4 or 4x4), checked rigid
  (scenes.base.check_poses) before any image is read, their last row exactly (0, 0, 0, 1)."""
  poses = []
  for name, frame in zip(names, frames):
    try:
      pose = np.asarray(frame["transform_matrix"], np.float64)
    except (TypeError, ValueError) as e:
      raise UserError(f"{path}: frame {name!r} has a transform_matrix that is not a 4x4 matrix of numbers.") from e
    if pose.shape not in ((4, 4), (3, 4)):
      raise UserError(f"{path}: frame {name!r} has a transform_matrix of shape {pose.shape}, expected 4x4.")
    poses.append(pose if pose.shape == (4, 4) else np.concatenate([pose, [[0.0, 0.0, 0.0, 1.0]]]))
  poses = unscaled(np.stack(poses), path)
  check_poses(poses, names, path, "transform_matrix")  # before spending time on the images
  poses[:, 3] = [0.0, 0.0, 0.0, 1.0]  # exactly (check_poses allows round-off)
  return poses


def _intrinsics(meta: dict, frame: dict, where: str, image_w: int, image_h: int, downscale: int) -> tuple:
  """(w, h, fx, fy, cx, cy, distortion) of a frame at the full images' size: its own values, else the file's,
  else from camera_angle_x / _y and the image's size."""
  # The camera's size is the full images'; a shrunk image (images_N/ or data.downscale) scales it later.
  w = _number(meta, frame, "w", where) or int(image_w) * downscale
  h = _number(meta, frame, "h", where) or int(image_h) * downscale
  fx = _number(meta, frame, "fl_x", where)
  if fx is None:
    angle = _number(meta, frame, "camera_angle_x", where)
    if angle is None:
      raise UserError(f"{where}: no focal length; give fl_x (and fl_y) or camera_angle_x.")
    fx = 0.5 * w / np.tan(0.5 * angle)
  fy = _number(meta, frame, "fl_y", where)
  angle_y = _number(meta, frame, "camera_angle_y", where)
  if fy is None:  # square pixels, unless only angles are given and they say otherwise
    given_fx = _number(meta, frame, "fl_x", where) is not None
    fy = 0.5 * h / np.tan(0.5 * angle_y) if angle_y is not None and not given_fx else fx
  cx = _number(meta, frame, "cx", where)
  cy = _number(meta, frame, "cy", where)
  return (round(w), round(h), fx, fy, w / 2.0 if cx is None else cx, h / 2.0 if cy is None else cy,
          _distortion(meta, frame, where))


def _cameras(meta: dict, frames: list[dict], names: list[str], widths, heights, path: str,
             downscale: int) -> Cameras:
  """The frames' cameras (per-frame intrinsics and distortion) at the size of the images loaded."""
  rows = [_intrinsics(meta, frame, f"{path}, frame {name!r}", image_w, image_h, downscale)
          for name, frame, image_w, image_h in zip(names, frames, widths, heights)]
  col = lambda i, dtype: np.array([r[i] for r in rows], dtype)
  cams = Cameras(col(0, np.int64), col(1, np.int64), col(2, np.float64), col(3, np.float64), col(4, np.float64),
                 col(5, np.float64), np.array([r[6] for r in rows], np.float64))
  return capture.scaled_cameras(cams, widths, heights, names, path, downscale)


def _split_lists(meta: dict, names: list[str], path: str) -> dict | None:
  """{split: frame indices} of the file's train_filenames / val_filenames / test_filenames (val and test each
  the other's where one is missing), or None where it has none (data.llffhold then holds frames out)."""
  lists = {s: meta.get(f"{s}_filenames") for s in ("train", "val", "test")}
  if all(v is None for v in lists.values()):
    return None
  index = {os.path.normpath(n): i for i, n in enumerate(names)}
  split_lists = {}
  for split, files in lists.items():
    if files is None:
      continue
    unknown = [f for f in files if os.path.normpath(str(f)) not in index]
    if unknown:
      raise UserError(f"{path}: {split}_filenames names {len(unknown)} file(s) that no frame has (e.g. "
                      f"{unknown[0]!r}); list the frames' file_path values.")
    split_lists[split] = np.array(sorted(index[os.path.normpath(str(f))] for f in files), np.int64)
  if "val" not in split_lists and "test" in split_lists:
    split_lists["val"] = split_lists["test"]
  if "test" not in split_lists and "val" in split_lists:
    split_lists["test"] = split_lists["val"]
  return split_lists
