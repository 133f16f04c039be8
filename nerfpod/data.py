"""The training-ray pipeline: a grain dataset of random ray batches, each host loading only its own slice.

Global batch `step` is a pure function of (seed, step): the pixel indices of its `batch_size` rays are drawn
uniformly, with replacement, over every pixel of every training image, from a NumPy generator seeded with
(seed, step). Host p of P loads rows [p B/P, (p+1) B/P) of that batch: it gathers their colours and builds
their rays, nothing else. So the sequence of global batches is the same on 1 CPU or a pod, hosts never load
the same rays, and resuming at step s needs nothing but s.

With data.shards = S > 1 the training frames make S fixed shards (frame i in shard i mod S,
`scenes.Shards`), and global batch `step` is S sub-batches of B/S rays one after the other: sub-batch s is
drawn uniformly, with replacement, over the pixels of shard s's frames, from a generator seeded with
(seed, step, s). Host p of P (P divides S) holds shards [p S/P, (p+1) S/P): their sub-batches are exactly its
rows [p B/P, (p+1) B/P), so it needs the frames of its own shards only, and the global batches depend on
(seed, step, S), never on the number of hosts. (S = 1 is the single draw above, seeded (seed, step).)
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


def shard_pixel_indices(seed: int, step: int, shard: int, batch_size: int, num_pixels: int) -> np.ndarray:
  """Pixel indices, within shard `shard`'s frames (offset of the frame in the shard + row * W + col), of
  the sub-batch of `batch_size` rays that shard gives to global batch `step` (data.shards > 1)."""
  return np.random.default_rng([seed, step, shard]).integers(0, num_pixels, size=batch_size, dtype=np.int64)



class LocalRayBatch(grain.transforms.Map):
  """step -> this host's slice of the global batch: rays, target colours (and alphas where the data have
  them) and the rays' positions in the global batch; `with_frames`: also each ray's training frame (its
  index in the split, "frame"), for per-frame appearance codes and pose corrections.

  Frames may differ in size and camera: a flat index picks its frame by the split's pixel offsets, and each
  ray goes through its own frame's camera (lens distortion included). Colours stay uint8 in memory and
  become float32 here, for this slice only."""

  def __init__(self, split: Split, seed: int, batch_size: int, rows: slice, pixel_center: float,
               num_shards: int = 1, with_frames: bool = False):
    self._pixels = split.pixels
    self._alphas = split.alphas
    self._poses = split.poses
    self._cameras = split.cameras
    self._offsets = split.offsets
    self._seed, self._batch_size, self._rows = seed, batch_size, rows
    self._pixel_center = pixel_center
    self._num_shards = num_shards
    self._with_frames = with_frames
    if num_shards > 1:  # this host's shards: those whose sub-batches are its rows, each with its frames
      per_shard = batch_size // num_shards
      shard_ids = range(rows.start // per_shard, rows.stop // per_shard)
      self._shards = []
      for s in shard_ids:
        frames = np.arange(s, len(split), num_shards, dtype=np.int64)  # shard s: frames i with i mod S = s
        if not np.isin(frames, split.held_frames).all():
          raise ValueError(f"rows {rows} need shard {s}, whose frames this split does not hold")
        starts = np.concatenate([[0], np.cumsum(split.cameras.num_pixels[frames])]).astype(np.int64)
        self._shards.append((s, frames, starts))

  def _flat_indices(self, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """This host's rows of global batch `step`: (frame, offset of the pixel in the frame, offset in the
    split's pixel buffer), each (R,)."""
    if self._num_shards == 1:
      flat = global_pixel_indices(self._seed, step, self._batch_size, int(self._offsets[-1]))[self._rows]
      image = np.searchsorted(self._offsets, flat, side="right") - 1
      return image, flat - self._offsets[image], flat
    images, within = [], []
    for s, frames, starts in self._shards:
      local = shard_pixel_indices(self._seed, step, s, self._batch_size // self._num_shards, int(starts[-1]))
      k = np.searchsorted(starts, local, side="right") - 1
      images.append(frames[k])
      within.append(local - starts[k])
    image, within = np.concatenate(images), np.concatenate(within)
    return image, within, self._offsets[image] + within

  def map(self, step):
    step = int(step)
    image, within, flat = self._flat_indices(step)
    row, col = np.divmod(within, self._cameras.width[image])
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
    if self._with_frames:
      batch["frame"] = image.astype(np.int32)
    return batch


def ray_batches(split: Split, seed: int, batch_size: int, rows: slice, pixel_center: float,
                num_steps: int, num_shards: int = 1, with_frames: bool = False) -> grain.MapDataset:
  """The random-access dataset of this host's slices of global batches 0 .. num_steps - 1 (`num_shards`:
  data.shards; the rows then span whole sub-batches, those of the shards the split holds; `with_frames`:
  the rays' training frames too)."""
  return grain.MapDataset.range(num_steps).map(
      LocalRayBatch(split, seed, batch_size, rows, pixel_center, num_shards, with_frames))


PREFETCH = 4  # batches a background thread prepares ahead (on accelerators: nerfpod.run.components)


def iterator(dataset: grain.MapDataset, start_step: int, prefetch: int = PREFETCH, background: bool = True):
  """An iterator from global batch `start_step` on, prepared `prefetch` batches ahead in a background thread,
  or (`background`=False) each in the caller's thread when it is asked for."""
  options = (grain.ReadOptions(num_threads=1, prefetch_buffer_size=prefetch) if background else
             grain.ReadOptions(num_threads=0, prefetch_buffer_size=0))
  return iter(dataset.slice(slice(start_step, None)).to_iter_dataset(options))
