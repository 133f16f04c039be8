"""The one scene type every loader returns: posed images in train / val / test splits."""
import dataclasses

import numpy as np

from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Intrinsics


@dataclasses.dataclass(frozen=True)
class Split:
  """Images of one split and the cameras that took them (one intrinsics for the whole split)."""
  images: np.ndarray      # (N, H, W, 3) float32 in [0, 1], composited on the scene's background
  poses: np.ndarray       # (N, 4, 4) float32 camera-to-world, OpenGL convention (camera looks down -z)
  intrinsics: Intrinsics  # width, height, focal lengths, principal point in pixels
  names: tuple[str, ...]  # where each frame came from (file path or index), for messages and metrics
  alphas: np.ndarray | None = None  # (N, H, W) float32 coverage in [0, 1], where the data have it (RGBA)

  def __len__(self) -> int:
    return len(self.images)


@dataclasses.dataclass(frozen=True)
class Scene:
  """A scene: its splits, the near/far bounds of its rays and the colour where rays hit nothing."""
  name: str
  splits: dict[str, Split]
  near: float
  far: float
  background: tuple[float, float, float]

  def split(self, name: str) -> Split:
    if name not in self.splits:
      raise UserError(f"scene {self.name!r} has no {name!r} split (it has {sorted(self.splits)}); "
                      f"choose one of those, e.g. --config.eval.split={sorted(self.splits)[-1]}.")
    return self.splits[name]


def check_split(split: Split, where: str) -> Split:
  """Validates shapes, value ranges and finiteness; raises UserError naming the first bad frame."""
  n = len(split.images)
  if n == 0:
    raise UserError(f"{where} has no frames; a split needs at least one posed image.")
  h, w = split.intrinsics.height, split.intrinsics.width
  if split.images.shape != (n, h, w, 3):
    raise UserError(f"{where}: images have shape {split.images.shape}, expected ({n}, {h}, {w}, 3).")
  if split.alphas is not None and split.alphas.shape != (n, h, w):
    raise UserError(f"{where}: alphas have shape {split.alphas.shape}, expected ({n}, {h}, {w}).")
  if split.poses.shape != (n, 4, 4):
    raise UserError(f"{where}: poses have shape {split.poses.shape}, expected ({n}, 4, 4) camera-to-world.")
  bad = np.flatnonzero(~np.isfinite(split.poses).all(axis=(1, 2)))
  if bad.size:
    raise UserError(f"{where}: the pose of frame {split.names[bad[0]]} contains NaN or infinity; "
                    f"fix or remove that frame.")
  bad = np.flatnonzero(~np.isfinite(split.images).all(axis=(1, 2, 3)))
  if bad.size:
    raise UserError(f"{where}: the image of frame {split.names[bad[0]]} contains NaN or infinity.")
  if not np.isfinite([split.intrinsics.fx, split.intrinsics.fy]).all() or split.intrinsics.fx <= 0:
    raise UserError(f"{where}: the focal length {split.intrinsics.fx} is not a positive number.")
  return split
