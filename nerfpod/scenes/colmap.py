"""COLMAP sparse models: sparse/0/{cameras,images,points3D}.{bin,txt} + images/ (or images_N/).

The model is read with the maintained `pycolmap` package (the optional extra `nerfpod[colmap]`), which
reads both the binary and the text format. Each image brings its own camera (COLMAP shares one between
images or not; both work) with its model's parameters mapped onto nerfpod's (fx, fy, cx, cy, k1, k2, k3, k4,
p1, p2): SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV are supported; fisheye and other models
are refused. Poses are world-to-camera in OpenCV axes; they become camera-to-world OpenGL. Per-frame near/far
bounds are the 0.1 and 99.9 percentile depths of the 3D points each image observes (LLFF's imgs2poses rule).
Frames are sorted by image name; every data.llffhold-th is held out as test (and val).
"""
import os

import numpy as np

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Cameras
from nerfpod.scenes import capture
from nerfpod.scenes.base import Scene, capture_scene, check_poses

# COLMAP model name -> the names of its parameters, in COLMAP's order.
MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
MODEL_FILES = ("cameras", "images", "points3D")


def model_format(folder: str) -> str | None:
  """'.bin' where `folder` holds the whole model in COLMAP's binary format, else '.txt' where it holds it in
  text, else None (pycolmap reads the binary model where both are there)."""
  for ext in (".bin", ".txt"):
    if all(storage.isfile(storage.join(folder, f + ext)) for f in MODEL_FILES):
      return ext
  return None


def model_folder(root: str) -> str | None:
  """Where the sparse model of a capture folder is: sparse/0/, sparse/ or the folder itself."""
  for folder in (storage.join(root, "sparse", "0"), storage.join(root, "sparse"), root):
    if model_format(folder) is not None:
      return folder
  return None


def incomplete_model(root: str) -> tuple[str, list[str]] | None:
  """Where a capture folder holds a COLMAP model that is not complete: (its folder, the full paths of the
  files it lacks) for sparse/0/ (or else sparse/) where it is a folder without a whole model, or the
  folder itself where it holds some of the model's files; None where there is no such thing (no model, or
  a complete one: `model_folder`). The files are taken in the format (.bin or .txt) most of them are in."""
  if model_folder(root) is not None:
    return None
  sparse = storage.join(root, "sparse")
  folders = [storage.join(sparse, "0")] if storage.isdir(storage.join(sparse, "0")) else (
      [sparse] if storage.isdir(sparse) else [])
  for folder in folders + [root]:
    present = {ext: [f for f in MODEL_FILES if storage.isfile(storage.join(folder, f + ext))]
               for ext in (".bin", ".txt")}
    ext = max(present, key=lambda e: len(present[e]))  # .bin on a tie
    if present[ext] or folder != root:
      return folder, [storage.join(folder, f + ext) for f in MODEL_FILES if f not in present[ext]]
  return None


def missing_files(paths: list[str]) -> str:
  """'A is missing' or 'A, B are missing'."""
  return f"{', '.join(paths)} {'is' if len(paths) == 1 else 'are'} missing"


def camera_params(model: str, params, width: int, height: int, where: str) -> dict:
  """A COLMAP camera as {"fx", "fy", "cx", "cy", "k1", ...}; refuses a model nerfpod cannot handle."""
  if model not in MODELS:
    raise UserError(f"{where} uses COLMAP's {model} camera model, which nerfpod does not handle (it handles "
                    f"{', '.join(MODELS)}); undistort the images with `colmap image_undistorter` (it writes "
                    f"PINHOLE cameras) or re-run COLMAP with one of those models.")
  names = MODELS[model]
  if len(params) != len(names):
    raise UserError(f"{where}: a {model} camera has {len(names)} parameters ({', '.join(names)}), this one "
                    f"{len(params)}.")
  out = dict(zip(names, (float(p) for p in params)))
  if "f" in out:
    out["fx"] = out["fy"] = out.pop("f")
  return out


def _reconstruction(folder: str):
  try:
    import pycolmap
  except ImportError as e:
    raise UserError("reading COLMAP models needs the pycolmap package: pip install 'nerfpod[colmap]' "
                    "(or pip install pycolmap).") from e
  try:
    # pycolmap reads local files only: a bucket's model is copied into a temporary folder first.
    with storage.local_copy([storage.join(folder, f + model_format(folder)) for f in MODEL_FILES]) as local:
      return pycolmap.Reconstruction(local)
  except UserError:
    raise
  except Exception as e:  # pycolmap raises its own error types for unreadable models
    reason = (str(e).strip().splitlines() or [type(e).__name__])[-1]
    raise UserError(f"the COLMAP model in {folder} cannot be read ({reason}); re-export it from COLMAP.") from e


def _depth_bounds(rec, image, w2c_3x4: np.ndarray) -> np.ndarray | None:
  ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
  if not ids:
    return None
  xyz = np.array([rec.points3D[i].xyz for i in ids], np.float64)
  depth = xyz @ w2c_3x4[2, :3] + w2c_3x4[2, 3]
  depth = depth[depth > 0]
  if depth.size == 0:
    return None
  return np.percentile(depth, [0.1, 99.9])


def load(root: str, data_config, shards=None) -> Scene:
  folder = model_folder(root)
  broken = incomplete_model(root)
  if broken is not None:
    raise UserError(f"the COLMAP model in {broken[0]} is incomplete: {missing_files(broken[1])}; restore "
                    f"{'it' if len(broken[1]) == 1 else 'them'} or re-export the model from COLMAP (cameras, "
                    f"images and points3D, as .bin or .txt).")
  if folder is None:
    raise UserError(f"{root} holds no COLMAP sparse model (sparse/0/ with cameras, images and points3D as .bin "
                    f"or .txt); set --config.data.path to the capture folder that holds sparse/.")
  rec = _reconstruction(folder)
  images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
  if not images:
    raise UserError(f"the COLMAP model in {folder} has no registered images; re-run the reconstruction.")
  downscale = int(data_config.downscale)
  image_dir, shrink = capture.image_folder(root, downscale)
  names = [im.name for im in images]
  paths = [storage.join(image_dir, n) for n in names]
  capture.check_files_exist(paths, names, f"the COLMAP model in {folder}")
  # World-to-camera poses, checked (finite, rigid) before they are inverted.
  world_to_camera = np.stack([np.concatenate([np.asarray(im.cam_from_world().matrix(), np.float64),
                                              [[0.0, 0.0, 0.0, 1.0]]]) for im in images])
  check_poses(world_to_camera, names, folder, "world-to-camera pose")
  intrinsics, poses, bounds = [], [], []
  for im, w2c in zip(images, world_to_camera):
    cam = rec.cameras[im.camera_id]
    p = camera_params(cam.model.name, cam.params, cam.width, cam.height,
                      f"camera {im.camera_id} of image {im.name!r} in {folder}")
    intrinsics.append((cam.width, cam.height, p["fx"], p["fy"], p["cx"], p["cy"],
                       [p.get(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")]))
    poses.append(np.linalg.inv(w2c) @ capture.OPENCV_TO_OPENGL)
    bounds.append(_depth_bounds(rec, im, w2c[:3]))
  col = lambda i, dtype: np.array([c[i] for c in intrinsics], dtype)
  cams = Cameras(col(0, np.int64), col(1, np.int64), col(2, np.float64), col(3, np.float64), col(4, np.float64),
                 col(5, np.float64), np.array([c[6] for c in intrinsics], np.float64))
  poses = np.stack(poses)
  widths, heights = capture.image_sizes(paths, names, shrink)
  cams = capture.scaled_cameras(cams, widths, heights, names, folder, downscale)
  # Bounds where every image sees points (an image seeing none leaves the scene without per-frame bounds).
  bounds = np.array(bounds, np.float64) if all(b is not None for b in bounds) else None
  framing = capture.frame(poses, bounds, names, data_config, "colmap", folder, default_space="unbounded")
  read = lambda i: capture.read_image(paths[i], names[i], shrink)
  return capture_scene(os.path.basename(storage.normpath(root)), "colmap", read, cams, names, framing, folder,
                       capture.READ_THREADS, shards)
