"""The LLFF format (forward-facing captures, NeRF's nerf_llff_data): poses_bounds.npy + images_N/.

poses_bounds.npy is (N, 17), one row per image in name order: a 3x5 matrix [R | t | hwf] (camera-to-world,
rotation columns [down, right, back]; hwf = height, width, focal at the full resolution) and the near/far
depths of the scene points that image sees. As the original code (bmild/nerf load_llff.py) does: the
columns become [right, up, back] (OpenGL), focal lengths follow each image's size, and by default
(data.orient/center/scale 'auto', 0) the capture is rescaled so the nearest bound is at 1/0.75 and recentred
on the average camera. Every data.llffhold-th image is held out as test (and val).
"""
import os

import numpy as np

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Cameras
from nerfpod.scenes import capture
from nerfpod.scenes.base import Scene, capture_scene, check_poses

POSES_FILE = "poses_bounds.npy"


def read_poses_bounds(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """(poses (N, 4, 4) OpenGL c2w, hwf (N, 3) at full resolution, bounds (N, 2)) from poses_bounds.npy."""
  try:
    arr = np.load(storage.open_binary(path) if storage.is_url(path) else path, allow_pickle=False)
  except (OSError, ValueError) as e:
    raise UserError(f"{path} is not a readable .npy array ({e}); regenerate it with LLFF's imgs2poses.py.") from e
  if arr.ndim != 2 or arr.shape[1] != 17 or len(arr) == 0:
    raise UserError(f"{path} has shape {arr.shape}, expected (N, 17): a 3x5 pose-and-hwf matrix and 2 bounds "
                    f"per image; regenerate it with LLFF's imgs2poses.py.")
  arr = arr.astype(np.float64)
  raw = arr[:, :15].reshape(-1, 3, 5)
  down, right, back, t = raw[:, :, 0], raw[:, :, 1], raw[:, :, 2], raw[:, :, 3]
  poses = np.tile(np.eye(4), (len(arr), 1, 1))
  poses[:, :3, :4] = np.stack([right, -down, back, t], axis=2)  # [down, right, back] -> [right, up, back]
  return poses, raw[:, :, 4], arr[:, 15:17]


def load(root: str, data_config, shards=None) -> Scene:
  path = storage.join(root, POSES_FILE)
  if not storage.isfile(path):
    raise UserError(f"{root} has no {POSES_FILE}; set --config.data.path to an LLFF scene folder (with "
                    f"{POSES_FILE} and images_N/).")
  poses, hwf, bounds = read_poses_bounds(path)
  downscale = int(data_config.downscale)
  folder, shrink = capture.image_folder(root, downscale)
  files = capture.list_images(folder)
  if not files:
    raise UserError(capture.empty_folder_message(folder, f"{path} has {len(poses)} poses, one per image of "
                                                         f"{folder}/"))
  if len(files) != len(poses):
    raise UserError(f"{folder} holds {len(files)} images but {path} has {len(poses)} poses; the images must be "
                    f"the ones the poses were computed for, one per row, in name order.")
  names = [os.path.join(os.path.basename(folder), f) for f in files]
  bad = np.flatnonzero(~np.isfinite(hwf).all(1) | (hwf <= 0).any(1) | ~np.isfinite(bounds).all(1)
                       | (bounds <= 0).any(1))
  if bad.size:
    raise UserError(f"{path}: the row of {names[bad[0]]} has a height/width/focal or near/far bound that is not "
                    f"a positive number; regenerate the file.")
  check_poses(poses, names, path)
  paths = [storage.join(folder, f) for f in files]
  widths, heights = capture.image_sizes(paths, names, shrink)
  full = Cameras(np.round(hwf[:, 1]).astype(np.int64), np.round(hwf[:, 0]).astype(np.int64), hwf[:, 2].copy(),
                 hwf[:, 2].copy(), hwf[:, 1] / 2.0, hwf[:, 0] / 2.0, np.zeros((len(hwf), 6)))
  # images_N may round the size either way: the factor is each image's size over the full one's.
  factor = np.maximum(1, np.round(full.width / widths)).astype(np.int64)
  cams = capture.scaled_cameras(full, widths, heights, names, path, factor)
  framing = capture.frame(poses, bounds, names, data_config, "llff", path, default_space="forward_facing")
  read = lambda i: capture.read_image(paths[i], names[i], shrink)
  return capture_scene(os.path.basename(storage.normpath(root)), "llff", read, cams, names, framing, path,
                       capture.READ_THREADS, shards)
