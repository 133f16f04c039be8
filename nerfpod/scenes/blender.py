"""The NeRF synthetic ("Blender") format: transforms_{split}.json + RGBA PNGs composited on white."""
import concurrent.futures
import os

import numpy as np
from PIL import Image

from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Intrinsics
from nerfpod.scenes.base import Scene, Split, check_split, read_json, to_uint8

SPLITS = ("train", "val", "test")


def _read_json(path: str) -> dict:
  meta = read_json(path)
  if not isinstance(meta, dict) or "camera_angle_x" not in meta or not isinstance(meta.get("frames"), list):
    raise UserError(f"{path} needs the keys 'camera_angle_x' (a number) and 'frames' (a list); "
                    f"is it a NeRF synthetic transforms file?")
  return meta


def _read_image(path: str, name: str, downscale: int) -> np.ndarray:
  """An RGBA (or RGB) image composited on white and box-downscaled: uint8 (H, W, 4), the composited colour
  and the alpha (filtered as floats, stored as uint8)."""
  if not os.path.isfile(path):
    raise UserError(f"frame {name!r}: image file {path} not found; restore it or remove the frame from the "
                    f"transforms file.")
  try:
    with Image.open(path) as im:
      rgba = np.asarray(im.convert("RGBA"), np.float32) / 255.0
  except OSError as e:
    raise UserError(f"frame {name!r}: {path} is not a readable image ({e}).") from e
  rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])  # composite before filtering
  out = np.concatenate([rgb, rgba[..., 3:]], axis=-1)
  if downscale > 1:
    h, w = out.shape[0] // downscale, out.shape[1] // downscale
    out = out[:h * downscale, :w * downscale].reshape(h, downscale, w, downscale, 4).mean(axis=(1, 3))
  return to_uint8(out)


def load_split(root: str, split: str, downscale: int = 1) -> Split:
  path = os.path.join(root, f"transforms_{split}.json")
  meta = _read_json(path)
  frames = meta["frames"]
  if not frames:
    raise UserError(f"{path} lists no frames.")
  names, files, poses = [], [], []
  for i, frame in enumerate(frames):
    if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
      raise UserError(f"{path}: frame {i} needs 'file_path' and 'transform_matrix'.")
    name = str(frame["file_path"])
    try:
      pose = np.asarray(frame["transform_matrix"], np.float64)
    except (TypeError, ValueError) as e:
      raise UserError(f"{path}: frame {name!r} has a transform_matrix that is not a 4x4 matrix of numbers.") from e
    if pose.shape != (4, 4):
      raise UserError(f"{path}: frame {name!r} has a transform_matrix of shape {pose.shape}, expected 4x4.")
    file = os.path.normpath(os.path.join(root, name))
    if not os.path.splitext(file)[1]:
      file += ".png"  # the original data names its frames without an extension
    names.append(name)
    files.append(file)
    poses.append(pose)
  poses = np.stack(poses).astype(np.float32)
  if not np.isfinite(poses).all():  # fail before spending time on the images
    bad = names[int(np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))[0])]
    raise UserError(f"{path}: the transform_matrix of frame {bad!r} contains NaN or infinity; fix or remove "
                    f"that frame.")
  with concurrent.futures.ThreadPoolExecutor(8) as pool:
    images = list(pool.map(lambda a: _read_image(a[0], a[1], downscale), zip(files, names)))
  h, w = images[0].shape[:2]
  for name, file, im in zip(names, files, images):
    if im.shape[:2] != (h, w):
      raise UserError(f"frame {name!r}: {file} is {im.shape[1]}x{im.shape[0]} pixels, but the split's "
                      f"first frame is {w}x{h}; all frames of a split must have the same size.")
  try:
    angle = float(meta["camera_angle_x"])
  except (TypeError, ValueError) as e:
    raise UserError(f"{path}: camera_angle_x is not a number.") from e
  focal = 0.5 * w / np.tan(0.5 * angle)
  intr = Intrinsics.from_focal(w, h, focal)
  return check_split(Split.from_images([im[..., :3] for im in images], poses, intr, names,
                                      alphas=[im[..., 3] for im in images]), path)


def load(root: str, downscale: int = 1, splits=SPLITS) -> Scene:
  """Every split whose transforms file exists; train must exist."""
  if not os.path.isdir(root):
    raise UserError(f"Blender scene folder {root!r} not found; set --config.data.path to a folder holding "
                    f"transforms_train.json.")
  if not os.path.isfile(os.path.join(root, "transforms_train.json")):
    raise UserError(f"{root} has no transforms_train.json; set --config.data.path to a NeRF synthetic scene "
                    f"folder.")
  loaded = {s: load_split(root, s, int(downscale)) for s in splits
            if os.path.isfile(os.path.join(root, f"transforms_{s}.json"))}
  name = os.path.basename(os.path.normpath(root))
  return Scene(name, loaded, near=2.0, far=6.0, background=(1.0, 1.0, 1.0), kind="blender")
