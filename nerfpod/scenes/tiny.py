"""The Tiny NeRF data (tiny_nerf_data.npz): 106 lego views at 100x100 on black, frames 100-105 held out."""
import zipfile

import numpy as np

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Intrinsics
from nerfpod.scenes.base import Scene, Split, check_split

NUM_TRAIN = 100  # frames 0-99 train, the rest are held out (the tutorial validates on frame 101)


def load(path: str, data_config, shards=None) -> Scene:
  """The loader's signature (nerfpod.scenes.LOADERS): the npz at data.path, whole (cut to a shard after)."""
  return read(path)


def read(path: str) -> Scene:
  if not storage.isfile(path):
    raise UserError(f"Tiny NeRF data file {path!r} not found; set --config.data.path to tiny_nerf_data.npz.")
  try:
    with np.load(storage.open_binary(path) if storage.is_url(path) else path) as npz:
      missing = {"images", "poses", "focal"} - set(npz.files)
      if missing:
        raise UserError(f"{path} lacks the key(s) {sorted(missing)}; a Tiny NeRF npz holds images, poses "
                        f"and focal.")
      images = np.asarray(npz["images"], np.float32)
      poses = np.asarray(npz["poses"], np.float32)
      focal = float(npz["focal"])
  except (ValueError, OSError, zipfile.BadZipFile) as e:
    raise UserError(f"{path} is not a readable .npz file ({e}); re-download tiny_nerf_data.npz.") from e
  if images.ndim != 4 or images.shape[-1] != 3 or len(images) <= NUM_TRAIN:
    raise UserError(f"{path}: images have shape {images.shape}, expected (N > {NUM_TRAIN}, H, W, 3).")
  if images.max() > 1.0 + 1e-6:  # some copies store 0-255
    images = images / 255.0
  _, h, w, _ = images.shape
  intr = Intrinsics.from_focal(w, h, focal)
  names = tuple(str(i) for i in range(len(images)))
  if poses.shape != (len(images), 4, 4):
    raise UserError(f"{path}: poses have shape {poses.shape}, expected ({len(images)}, 4, 4) camera-to-world.")
  full = check_split(Split.from_images(images, poses, intr, names), path)
  train = full.select(np.arange(NUM_TRAIN))
  heldout = full.select(np.arange(NUM_TRAIN, len(full)))
  return Scene("tiny_lego", {"train": train, "val": heldout, "test": heldout}, near=2.0, far=6.0,
               background=(0.0, 0.0, 0.0), kind="tiny")
