"""The NeRF synthetic ("Blender") format: transforms_{split}.json + RGBA PNGs composited on white."""
import os

import numpy as np
from PIL import Image

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Cameras, Intrinsics
from nerfpod.scenes.base import Scene, Shards, Split, check_poses, check_split, read_json, to_uint8, unscaled
from nerfpod.scenes.capture import READ_THREADS, image_size, unreadable_image

SPLITS = ("train", "val", "test")


def _read_json(path: str) -> dict:
  meta = read_json(path)
  if not isinstance(meta, dict) or "camera_angle_x" not in meta or not isinstance(meta.get("frames"), list):
    raise UserError(f"{path} needs the keys 'camera_angle_x' (a number) and 'frames' (a list); "
                    f"is it a NeRF synthetic transforms file?")
  return meta


def _image_size(path: str, name: str, downscale: int) -> tuple[int, int]:
  """(width, height) of a frame's image as _read_image gives it, from the file's header."""
  if not storage.isfile(path):
    raise UserError(f"frame {name!r}: image file {path} not found; restore it or remove the frame from the "
                    f"transforms file.")
  return image_size(path, name, downscale)


def _read_image(path: str, name: str, downscale: int) -> np.ndarray:
  """An RGBA (or RGB) image composited on white and box-downscaled: uint8 (H, W, 4), the composited colour
  and the alpha (filtered as floats, stored as uint8)."""
  if not storage.isfile(path):
    raise UserError(f"frame {name!r}: image file {path} not found; restore it or remove the frame from the "
                    f"transforms file.")
  try:
    with Image.open(storage.open_binary(path) if storage.is_url(path) else path) as im:
      rgba = np.asarray(im.convert("RGBA"), np.float32) / 255.0
  except OSError as e:
    raise unreadable_image(name, path, e) from e
  rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])  # composite before filtering
  out = np.concatenate([rgb, rgba[..., 3:]], axis=-1)
  if downscale > 1:
    h, w = out.shape[0] // downscale, out.shape[1] // downscale
    out = out[:h * downscale, :w * downscale].reshape(h, downscale, w, downscale, 4).mean(axis=(1, 3))
  return to_uint8(out)


def load_split(root: str, split: str, downscale: int = 1) -> Split:
  """Every frame of one split, read."""
  return _listed(root, split, downscale).read()


class _Listed:
  """A split's frames as its transforms file lists them, sizes from the images' headers, nothing decoded."""

  def __init__(self, path, names, files, poses, intr, downscale):
    self.path, self.names, self.files, self.poses, self.intr = path, names, files, poses, intr
    self.downscale = downscale

  def frame_bytes(self) -> np.ndarray:
    """Each frame's bytes once read: RGB and alpha, one byte each."""
    return np.full(len(self.names), self.intr.width * self.intr.height * 4, np.int64)

  def read(self, frames=None) -> Split:
    """The split with the images of `frames` (sorted indices; default all) read."""
    def read(i):
      rgba = _read_image(self.files[i], self.names[i], self.downscale)
      return rgba[..., :3], rgba[..., 3]
    return check_split(Split.from_frames(read, self.poses.astype(np.float32),
                                         Cameras.repeat(self.intr, len(self.names)), self.names, with_alpha=True,
                                         threads=READ_THREADS, frames=frames), self.path)


def _listed(root: str, split: str, downscale: int = 1) -> _Listed:
  path = storage.join(root, f"transforms_{split}.json")
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
    file = storage.normpath(storage.join(root, name))
    if not os.path.splitext(file)[1]:
      file += ".png"  # the original data names its frames without an extension
    names.append(name)
    files.append(file)
    poses.append(pose)
  poses = unscaled(np.stack(poses), path)
  check_poses(poses, names, path, "transform_matrix")  # before spending time on the images
  sizes = [_image_size(file, name, downscale) for file, name in zip(files, names)]
  w, h = sizes[0]
  for name, file, size in zip(names, files, sizes):
    if size != (w, h):
      raise UserError(f"frame {name!r}: {file} is {size[0]}x{size[1]} pixels, but the split's first frame is "
                      f"{w}x{h}; all frames of a split must have the same size.")
  try:
    angle = float(meta["camera_angle_x"])
  except (TypeError, ValueError) as e:
    raise UserError(f"{path}: camera_angle_x is not a number.") from e
  focal = 0.5 * w / np.tan(0.5 * angle)
  intr = Intrinsics.from_focal(w, h, focal)
  return _Listed(path, names, files, poses, intr, downscale)


def load(path: str, data_config, shards: Shards | None = None) -> Scene:
  """The loader's signature (nerfpod.scenes.LOADERS): the scene folder at data.path, data.downscale."""
  return read(path, data_config.downscale, shards=shards)


def read(root: str, downscale: int = 1, splits=SPLITS, shards: Shards | None = None) -> Scene:
  """Every split whose transforms file exists; train must exist. With `shards`, only this host's training
  frames are read, after checking that they and the held-out splits fit its budget."""
  if not storage.isdir(root):
    raise UserError(f"Blender scene folder {root!r} not found; set --config.data.path to a folder holding "
                    f"transforms_train.json.")
  if not storage.isfile(storage.join(root, "transforms_train.json")):
    raise UserError(f"{root} has no transforms_train.json; set --config.data.path to a NeRF synthetic scene "
                    f"folder.")
  listed = {s: _listed(root, s, int(downscale)) for s in splits
            if storage.isfile(storage.join(root, f"transforms_{s}.json"))}
  frames = None
  if shards is not None and "train" in listed:
    heldout = sum(int(v.frame_bytes().sum()) for k, v in listed.items() if k != "train")
    shards.check(listed["train"].frame_bytes(), heldout, listed["train"].path)
    frames = shards.frames(len(listed["train"].names))
  loaded = {s: v.read(frames if s == "train" else None) for s, v in listed.items()}
  name = os.path.basename(storage.normpath(root))
  return Scene(name, loaded, near=2.0, far=6.0, background=(1.0, 1.0, 1.0), kind="blender")
