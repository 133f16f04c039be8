"""The training-ray pipeline: a grain dataset of random ray batches, each host loading only its own slice.

Global batch `step` is a pure function of (seed, step): the pixel indices of its `batch_size` rays are drawn
uniformly, with replacement, over every pixel of every training image, from a NumPy generator seeded with
(seed, step). Host p of P loads rows [p B/P, (p+1) B/P) of that batch: it gathers their colours and builds
their rays, nothing else. So the sequence of global batches is the same on 1 CPU or a pod, hosts never load
the same rays, and resuming at step s needs nothing but s.
"""
import grain
import numpy as np

from nerfpod.nerf import cameras
from nerfpod.scenes import Split
from nerfpod.scenes.base import to_float


def global_pixel_indices(seed: int, step: int, batch_size: int, num_pixels: int) -> np.ndarray:
  """Flat pixel indices of global batch `step`: offset of the image + row * W + col (image * H * W + row * W
  + col where all frames have one size)."""
  return np.random.default_rng([seed, step]).integers(0, num_pixels, size=batch_size, dtype=np.int64)


class LocalRayBatch(grain.transforms.Map):
  """step -> this host's slice of the global batch: rays, target colours (and alphas where the data have
  them) and the rays' positions in the global batch.

  Frames may differ in size and camera: a flat index picks its frame by the split's pixel offsets, and each
  ray goes through its own frame's camera (lens distortion included). Colours stay uint8 in memory and
  become float32 here, for this slice only."""

  def __init__(self, split: Split, seed: int, batch_size: int, rows: slice, pixel_center: float):
    self._pixels = split.pixels
    self._alphas = split.alphas
    self._poses = split.poses
    self._cameras = split.cameras
    self._offsets = split.offsets
    self._seed, self._batch_size, self._rows = seed, batch_size, rows
    self._pixel_center = pixel_center

  def map(self, step):
    step = int(step)
    flat = global_pixel_indices(self._seed, step, self._batch_size, int(self._offsets[-1]))[self._rows]
    image = np.searchsorted(self._offsets, flat, side="right") - 1
    row, col = np.divmod(flat - self._offsets[image], self._cameras.width[image])
    origins, directions = cameras.frame_rays(self._poses[image], self._cameras, image, row, col,
                                             self._pixel_center)
    batch = {
        "origins": origins,
        "directions": directions,
        "rgb": to_float(self._pixels[flat]),
        "ray_ids": np.arange(self._rows.start, self._rows.stop, dtype=np.int32),
        "step": np.int64(step),
    }
    if self._alphas is not None:
      batch["alpha"] = to_float(self._alphas[flat])
    return batch


def ray_batches(split: Split, seed: int, batch_size: int, rows: slice, pixel_center: float,
                num_steps: int) -> grain.MapDataset:
  """The random-access dataset of this host's slices of global batches 0 .. num_steps - 1."""
  return grain.MapDataset.range(num_steps).map(
      LocalRayBatch(split, seed, batch_size, rows, pixel_center))


def iterator(dataset: grain.MapDataset, start_step: int, prefetch: int = 4):
  """An iterator from global batch `start_step` on, prepared in a background thread."""
  options = grain.ReadOptions(num_threads=1, prefetch_buffer_size=prefetch)
  return iter(dataset.slice(slice(start_step, None)).to_iter_dataset(options))
