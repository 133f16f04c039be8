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


def global_pixel_indices(seed: int, step: int, batch_size: int, num_pixels: int) -> np.ndarray:
  """Flat pixel indices (image * H * W + row * W + col) of global batch `step`."""
  return np.random.default_rng([seed, step]).integers(0, num_pixels, size=batch_size, dtype=np.int64)


class LocalRayBatch(grain.transforms.Map):
  """step -> this host's slice of the global batch: rays, target colours (and alphas where the data have
  them) and the rays' positions in the global batch."""

  def __init__(self, split: Split, seed: int, batch_size: int, rows: slice, pixel_center: float):
    self._images = split.images
    self._alphas = split.alphas
    self._poses = split.poses
    self._intr = split.intrinsics
    self._seed, self._batch_size, self._rows = seed, batch_size, rows
    self._pixel_center = pixel_center

  def map(self, step):
    step = int(step)
    n, h, w, _ = self._images.shape
    flat = global_pixel_indices(self._seed, step, self._batch_size, n * h * w)[self._rows]
    image, pixel = np.divmod(flat, h * w)
    row, col = np.divmod(pixel, w)
    origins, directions = cameras.rays_for_pixels(self._poses[image], self._intr, row, col,
                                                  self._pixel_center)
    batch = {
        "origins": origins,
        "directions": directions,
        "rgb": self._images[image, row, col],
        "ray_ids": np.arange(self._rows.start, self._rows.stop, dtype=np.int32),
        "step": np.int64(step),
    }
    if self._alphas is not None:
      batch["alpha"] = self._alphas[image, row, col]
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
