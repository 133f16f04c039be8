"""The one scene type every loader returns: posed images in train / val / test splits.

Images are kept as uint8, a quarter of float32's memory (a real capture's hundreds of frames fit where they
would not as floats), in one flat (P, 3) buffer of every frame's pixels, row-major, frame after frame: frames
of a split may differ in size. Colours become float32 in [0, 1] per batch (`to_float`), and per image for
evaluation (`Split.image`).

A training split may hold the pixels of some of its frames only (`Split.held`, data.shards > 1: each host
reads the frames of its shards, `Shards`): it still has every frame's pose, camera and name (what orbits,
bounds and the NDC camera are computed from, the same on every host), and a frame it does not hold has an
empty slot in the pixel buffer.
"""
import concurrent.futures
import dataclasses
import functools
import json
import sys

import numpy as np

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.nerf.cameras import Cameras, Intrinsics

SPACES = ("object", "forward_facing", "unbounded")  # what kind of space a scene's rays cross (see Scene)


def to_uint8(values) -> np.ndarray:
  """Colours or alphas in [0, 1] -> uint8, rounded to the nearest of 256 levels."""
  return np.round(np.clip(np.asarray(values, np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)


def to_float(values_uint8: np.ndarray) -> np.ndarray:
  """uint8 -> float32 in [0, 1] (the exact inverse of to_uint8 on its 256 levels)."""
  return np.asarray(values_uint8).astype(np.float32) / np.float32(255.0)


@dataclasses.dataclass(frozen=True)
class Split:
  """The images of one split and the cameras that took them, one camera per frame."""
  pixels: np.ndarray      # (P, 3) uint8: every frame's pixels, row-major, frame after frame
  poses: np.ndarray       # (N, 4, 4) float32 camera-to-world, OpenGL convention (camera looks down -z)
  cameras: Cameras        # per-frame size, focal lengths, principal point and lens distortion
  names: tuple[str, ...]  # where each frame came from (file path or index), for messages and metrics
  alphas: np.ndarray | None = None  # (P,) uint8 coverage, where the data have it (RGBA)
  bounds: np.ndarray | None = None  # (N, 2) float32 near/far scene depth per frame, where the format has it
  held: np.ndarray | None = None  # (K,) int64 sorted indices of the frames whose pixels are held; None: all

  @classmethod
  def from_images(cls, images, poses, cameras: Cameras | Intrinsics, names, alphas=None, bounds=None) -> "Split":
    """A split from per-frame images (an (N, H, W, 3) array or a list of (H_i, W_i, 3) ones), float in
    [0, 1] or uint8, with alphas likewise; `cameras` one per frame, or one Intrinsics shared by all."""
    images = list(images)
    alphas = None if alphas is None else list(alphas)
    if isinstance(cameras, Intrinsics):
      cameras = Cameras.repeat(cameras, len(images))
    names = tuple(names)
    if not len(images) == len(cameras) == len(names):
      raise UserError(f"{len(images)} images, {len(cameras)} cameras and {len(names)} names do not match.")
    return cls.from_frames(lambda i: (images[i], None if alphas is None else alphas[i]), poses, cameras, names,
                           with_alpha=alphas is not None, bounds=bounds)

  @classmethod
  def from_frames(cls, read, poses, cameras: Cameras, names, with_alpha: bool = False, bounds=None,
                  threads: int = 1, frames=None) -> "Split":
    """A split whose frames are read one at a time straight into its pixel buffer, allocated once at its final
    size from the cameras' sizes: `read(i)` gives frame i's (rgb (H_i, W_i, 3), alpha (H_i, W_i) or None),
    uint8 or float in [0, 1], which is copied into its slot and dropped. So loading holds the final buffer
    plus one decoded image per thread, never a second copy of the frames. `threads` > 1 reads frames in
    parallel threads (image decoding releases the GIL); the first bad frame in frame order is the error.
    `frames` (sorted indices): read only those frames (`held`); the others keep their poses and cameras and
    take no memory."""
    names = tuple(names)
    if len(cameras) != len(names):
      raise UserError(f"{len(cameras)} cameras and {len(names)} names do not match.")
    empty = np.flatnonzero((cameras.width < 1) | (cameras.height < 1))
    if empty.size:
      raise UserError(f"frame {names[empty[0]]} has an empty image ({cameras.width[empty[0]]}x"
                      f"{cameras.height[empty[0]]} pixels); fix its size or remove the frame.")
    held = None if frames is None or len(frames) == len(names) else np.asarray(frames, np.int64)
    offsets = _offsets(cameras.num_pixels, held)
    pixels = np.empty((int(offsets[-1]), 3), np.uint8)
    alphas = np.empty((int(offsets[-1]),), np.uint8) if with_alpha else None

    def slot(im, i, channels):
      im = np.asarray(im)
      if im.shape[:2] != (cameras.height[i], cameras.width[i]):
        raise UserError(f"the image of frame {names[i]} is {im.shape[1]}x{im.shape[0]} pixels but its camera "
                        f"is {cameras.width[i]}x{cameras.height[i]}; use the images the cameras were made for.")
      if im.dtype != np.uint8:
        if not np.isfinite(im).all():
          raise UserError(f"the image of frame {names[i]} contains NaN or infinity; fix or remove that frame.")
        im = to_uint8(im)
      return im.reshape(-1, channels)

    def put(i):
      rgb, alpha = read(i)
      pixels[offsets[i]:offsets[i + 1]] = slot(rgb, i, 3)
      if with_alpha:
        alphas[offsets[i]:offsets[i + 1]] = slot(alpha, i, 1)[:, 0]

    to_read = range(len(names)) if held is None else held.tolist()
    if threads > 1 and len(to_read) > 1:
      pool = concurrent.futures.ThreadPoolExecutor(min(threads, len(to_read)))
      try:
        for _ in pool.map(put, to_read):
          pass
      finally:
        pool.shutdown(cancel_futures=True)  # after a bad frame, read no more
    else:
      for i in to_read:
        put(i)
    return cls(pixels, np.asarray(poses, np.float32), cameras, names, alphas,
               None if bounds is None else np.asarray(bounds, np.float32), held)

  def __len__(self) -> int:
    return len(self.poses)

  @functools.cached_property
  def offsets(self) -> np.ndarray:
    """(N + 1,) int64: frame i's pixels are pixels[offsets[i]:offsets[i + 1]] (empty for a frame not held)."""
    return _offsets(self.cameras.num_pixels, self.held)

  @property
  def held_frames(self) -> np.ndarray:
    """The indices of the frames whose pixels this split holds (all of them unless `held` says otherwise)."""
    return np.arange(len(self), dtype=np.int64) if self.held is None else self.held

  def keep(self, frames) -> "Split":
    """This split with the pixels of `frames` (sorted indices) only: what a loader that generates its frames
    in memory gives for a shard (the others' poses and cameras kept)."""
    frames = np.asarray(frames, np.int64)
    take = lambda buf: None if buf is None else (np.concatenate(
        [buf[self.offsets[i]:self.offsets[i + 1]] for i in frames]) if len(frames) else buf[:0])
    return dataclasses.replace(self, pixels=take(self.pixels), alphas=take(self.alphas), held=frames)

  @property
  def num_pixels(self) -> int:
    return int(self.offsets[-1])

  @property
  def nbytes(self) -> int:
    """The bytes of the images this split holds (uint8 RGB, and alpha where there is one)."""
    return self.pixels.nbytes + (0 if self.alphas is None else self.alphas.nbytes)

  @property
  def intrinsics(self) -> Intrinsics:
    """The first frame's camera: the reference for sizes and field of view (e.g. the orbit's). Per-frame
    cameras are `cameras[i]`."""
    return self.cameras[0]

  def image_uint8(self, index: int) -> np.ndarray:
    self._check_held(index)
    h, w = int(self.cameras.height[index]), int(self.cameras.width[index])
    return self.pixels[self.offsets[index]:self.offsets[index + 1]].reshape(h, w, 3)

  def image(self, index: int) -> np.ndarray:
    """Frame `index`'s image, (H, W, 3) float32 in [0, 1]."""
    return to_float(self.image_uint8(index))

  def alpha(self, index: int) -> np.ndarray | None:
    """Frame `index`'s alpha, (H, W) float32 in [0, 1], or None where the data have none."""
    if self.alphas is None:
      return None
    self._check_held(index)
    h, w = int(self.cameras.height[index]), int(self.cameras.width[index])
    return to_float(self.alphas[self.offsets[index]:self.offsets[index + 1]].reshape(h, w))

  def _check_held(self, index: int) -> None:
    if self.held is not None and not np.isin(index, self.held):
      raise UserError(f"frame {self.names[index]} is in another host's shard of the training images "
                      f"(data.shards); read the split on one host (data.shards=1) to see every frame.")

  @property
  def images(self) -> "FloatImages":
    """The images as float32 in [0, 1], converted when read: `images[i]` is `image(i)`; `np.asarray(images)`,
    `.shape` and any other indexing stack them all, (N, H, W, 3), for splits whose frames share one size."""
    return FloatImages(self)

  def select(self, indices) -> "Split":
    """The split of frames `indices` (in that order)."""
    indices = np.asarray(indices, np.int64)
    take = lambda buf: None if buf is None else np.concatenate(
        [buf[self.offsets[i]:self.offsets[i + 1]] for i in indices]) if len(indices) else buf[:0]
    held = None if self.held is None else np.flatnonzero(np.isin(indices, self.held)).astype(np.int64)
    return Split(take(self.pixels), self.poses[indices], self.cameras.select(indices),
                 tuple(self.names[i] for i in indices), take(self.alphas),
                 None if self.bounds is None else self.bounds[indices], held)


def _offsets(num_pixels: np.ndarray, held: np.ndarray | None) -> np.ndarray:
  """(N + 1,) int64 pixel offsets of frames of `num_pixels` pixels each, frames not `held` taking none."""
  sizes = np.asarray(num_pixels, np.int64)
  if held is not None:
    sizes = np.where(np.isin(np.arange(len(sizes)), held), sizes, 0)
  return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)


class FloatImages:
  """A split's images seen as float32, one frame converted at a time where one is asked for."""

  def __init__(self, split: Split):
    self._split = split

  def __len__(self) -> int:
    return len(self._split)

  def __getitem__(self, key):
    if isinstance(key, (int, np.integer)):
      return self._split.image(int(key) % len(self._split))
    return np.asarray(self)[key]

  @property
  def shape(self) -> tuple[int, ...]:
    sizes = set(zip(self._split.cameras.height.tolist(), self._split.cameras.width.tolist()))
    if len(sizes) > 1:
      raise ValueError("the frames of this split differ in size; read them one by one with Split.image(i)")
    return (len(self._split), *sizes.pop(), 3)

  @property
  def size(self) -> int:
    return self._split.num_pixels * 3

  def __array__(self, dtype=None, copy=None):
    self.shape  # noqa: B018 (refuses frames of different sizes)
    out = np.stack([self._split.image(i) for i in range(len(self._split))])
    return out if dtype is None else out.astype(dtype)


@dataclasses.dataclass(frozen=True)
class Scene:
  """A scene: its splits, the near/far bounds of its rays, the colour where rays hit nothing, and where it
  came from.

  `space` says what the rays cross: "object" (a bounded object seen from around it, the synthetic scenes),
  "forward_facing" (LLFF captures: everything in front of the cameras, for NDC) or "unbounded" (360-degree
  captures whose background extends to infinity, for a contracted space). `transform` is the 4x4
  similarity from the capture's own frame to the scene's (identity for synthetic data): a point X of the
  capture lies at transform @ X here; it is written to the workdir's scene.json so that renders and exports
  map back to the capture.
  """
  name: str
  splits: dict[str, Split]
  near: float
  far: float
  background: tuple[float, float, float]
  space: str = "object"
  transform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
  kind: str = ""  # the format it was read from (data.kind, or what "auto" found)

  def split(self, name: str) -> Split:
    if name not in self.splits:
      raise UserError(f"scene {self.name!r} has no {name!r} split (it has {sorted(self.splits)}); "
                      f"choose one of those, e.g. --config.eval.split={sorted(self.splits)[-1]}.")
    return self.splits[name]

  def description(self) -> dict:
    """What scene.json records: the scene's name, format, space, ray bounds and capture -> scene transform."""
    return {"name": self.name, "kind": self.kind, "space": self.space, "near": float(self.near),
            "far": float(self.far), "capture_to_scene": np.asarray(self.transform, np.float64).tolist()}


def with_pose_noise(scene: Scene, degrees: float, units: float, seed: int) -> Scene:
  """The scene with every training camera moved by a known error (data.pose_noise), as BARF measures pose
  refinement on synthetic scenes: each camera-to-world pose [R | o] becomes [exp(w) R | o + t], turned by
  `degrees` about a random axis through its centre (world axes) and shifted by `units` (scene units) in a random
  direction, axes and directions uniform on the sphere from NumPy's generator with `seed`. The held-out splits
  keep their poses (a split that is also the training split's object keeps them too: it is the truth). The
  error is a pose correction's (t, w) form, applied as pose refinement applies one."""
  from nerfpod.nerf import pose_correction  # noqa: PLC0415 (it imports JAX; the schema reads this module without)
  train = scene.split("train")
  rng = np.random.default_rng(seed)
  unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)  # noqa: E731
  axes, directions = unit(rng.normal(size=(len(train), 3))), unit(rng.normal(size=(len(train), 3)))
  error = np.concatenate([directions * units, axes * np.deg2rad(degrees)], -1)
  poses = pose_correction.corrected_poses(train.poses, error)
  moved = dataclasses.replace(train, poses=poses.astype(train.poses.dtype))
  return dataclasses.replace(scene, splits={k: moved if k == "train" else v for k, v in scene.splits.items()})


MIB = 2**20


@dataclasses.dataclass(frozen=True)
class Shards:
  """Which training frames a host reads (data.shards): the training frames make `count` fixed shards, frame
  i in shard i mod `count`, and this host, `host` of `hosts`, holds the shards `held`. Every shard gets the
  frames of the whole capture's path (every count-th one), so each sub-batch sees the whole scene, and shard
  sizes differ by at most one frame. `budget_bytes`: the host memory its images may take (None: unchecked).
  Held-out splits are not sharded: every host reads them."""
  count: int = 1
  held: tuple[int, ...] = (0,)
  host: int = 0
  hosts: int = 1
  budget_bytes: int | None = None

  def frames(self, num_frames: int) -> np.ndarray:
    """The sorted indices of this host's training frames among `num_frames`."""
    return frames_of(num_frames, self.count, self.held)

  def check(self, frame_bytes, heldout_bytes: int, where: str) -> None:
    """Refuses, before any image is read, a host whose training frames (`frame_bytes`: each training frame's
    bytes) and held-out images would not fit its budget, naming a host count that would."""
    frame_bytes = np.asarray(frame_bytes, np.int64)
    n = len(frame_bytes)
    if self.count > n:
      raise UserError(f"data.shards={self.count} is more than the {n} training images of {where}, so a shard "
                      f"would be empty; use at most {n} shards (and a multiple of the {self.hosts} host(s)).")
    if self.budget_bytes is None:
      return
    held = int(frame_bytes[self.frames(n)].sum())
    if held + heldout_bytes <= self.budget_bytes:
      return
    fix = _hosts_that_fit(frame_bytes, heldout_bytes, self.budget_bytes, self.count, self.hosts)
    raise UserError(f"host {self.host} would hold {len(self.frames(n))} of {n} training images "
                    f"({held / MIB:.1f} MiB) and {heldout_bytes / MIB:.1f} MiB of held-out images, more than its "
                    f"memory budget of {self.budget_bytes / MIB:.1f} MiB (data.host_memory_gib); {fix}.")


def frames_of(num_frames: int, count: int, shards) -> np.ndarray:
  """The sorted indices of the frames of `shards` (frame i in shard i mod `count`) among `num_frames`."""
  return np.flatnonzero(np.isin(np.arange(num_frames) % count, np.asarray(shards, np.int64))).astype(np.int64)


def _largest_host_bytes(frame_bytes: np.ndarray, count: int, hosts: int) -> int:
  """The training bytes of the fullest host of `hosts`, each holding count / hosts consecutive shards."""
  per_shard = np.bincount(np.arange(len(frame_bytes)) % count, weights=frame_bytes, minlength=count)
  return int(per_shard.reshape(hosts, count // hosts).sum(axis=1).max())


def _hosts_that_fit(frame_bytes: np.ndarray, heldout_bytes: int, budget: int, count: int, hosts: int) -> str:
  """What to do about a shard that does not fit: the fewest hosts (and shard count, a multiple of them)
  whose largest share fits `budget`, or a smaller capture where even one frame per host would not."""
  n = len(frame_bytes)
  room = budget - heldout_bytes
  if room < frame_bytes.max():
    return ("not even one image per host would fit beside the held-out images: raise data.downscale or "
            "data.host_memory_gib")
  # With shards a host holds 1 / hosts of the frames whatever their count: only more hosts help. With one
  # shard every host holds every frame: shards over the same hosts may be enough.
  start = max(hosts if count == 1 and hosts > 1 else hosts + 1, int(frame_bytes.sum() // room))
  for wanted in range(start, min(n, start + 4096) + 1):
    shards = count if count % wanted == 0 and count > 1 else wanted * -(-count // wanted)
    if shards <= n and _largest_host_bytes(frame_bytes, shards, wanted) <= room:
      keep = f"data.shards={count} stays" if shards == count else f"data.shards={shards}, a multiple of {wanted}"
      where = f"on {wanted} hosts" if wanted > hosts else f"on these {hosts} hosts"
      return (f"run {where} ({keep}; each then holds about 1/{wanted} of the images), or raise "
              f"data.downscale or data.host_memory_gib")
  return "raise data.downscale or data.host_memory_gib: no host count up to one image per host fits"


def capture_scene(name: str, kind: str, read, cams: Cameras, names, framing, where: str, threads: int,
                  shards: Shards | None = None) -> Scene:
  """A real capture's Scene from its frames and their framing (nerfpod.scenes.capture.frame): one split per
  list of frame indices, each read straight into its own buffer (`read(i)`: frame i's (H_i, W_i, 3) uint8
  image; `cams` already the images' sizes); black background (captures are opaque). Frames no split lists
  are not read, nor training frames outside this host's `shards` (checked against its budget first)."""
  train = tuple(int(i) for i in framing.splits["train"])
  if shards is not None:
    heldout = {tuple(int(i) for i in v) for k, v in framing.splits.items() if k != "train"}
    heldout_bytes = sum(int(cams.num_pixels[list(key)].sum()) * 3 for key in heldout)
    shards.check(cams.num_pixels[list(train)] * 3, heldout_bytes, where)
  selected: dict[tuple, Split] = {}  # val and test are often the same frames: one copy
  splits = {}
  for split, indices in framing.splits.items():
    key = tuple(int(i) for i in indices)
    frames = shards.frames(len(key)) if shards is not None and split == "train" else None
    if frames is not None and len(frames) == len(key):
      frames = None  # every frame: one shard, or one host holding them all
    part = None if frames is None else tuple(frames.tolist())
    if (key, part) not in selected:
      selected[key, part] = check_split(Split.from_frames(
          lambda j, key=key: (read(key[j]), None), framing.poses[list(key)], cams.select(list(key)),
          [names[i] for i in key], bounds=None if framing.bounds is None else framing.bounds[list(key)],
          threads=threads, frames=frames), where)
    splits[split] = selected[key, part]
  return Scene(name, splits, near=framing.near, far=framing.far, background=(0.0, 0.0, 0.0), space=framing.space,
               transform=framing.transform, kind=kind)


# A pose must be a rigid camera-to-world transform: its 3x3 rotation R orthonormal to within RIGID_TOLERANCE
# (the largest entry of |R^T R - I|) with determinant +1, and its last row, where the format has one, 0 0 0 1
# to within the same. Rays are R @ d with d at camera depth 1, so a scaled or sheared R puts samples at the
# wrong depths, and an all-zero one (what some tools write for an image they could not register) makes
# every ray of the frame empty. The real captures of the tests' shared data (lego, tiny, fox, horns, cup)
# are within 1.3e-6 (float32 rounding); 1e-3 also admits matrices written with 4 decimals.
RIGID_TOLERANCE = 1e-3


def unscaled(poses, where: str, what: str = "transform_matrix") -> np.ndarray:
  """`poses` (N, 3 or 4, 4) with every rotation scaled uniformly by s (R^T R = s^2 I: some tools write a
  scene scale into camera-to-world matrices; other NeRF codes take only the axes' directions from them)
  divided by s, with one line saying so; other poses unchanged, left to check_poses."""
  poses = np.array(poses, np.float64)
  rotation = poses[:, :3, :3]
  gram = np.einsum("nki,nkj->nij", rotation, rotation)
  scale = np.sqrt(np.trace(gram, axis1=1, axis2=2) / 3)
  with np.errstate(divide="ignore", invalid="ignore"):
    uniform = (np.abs(gram / scale[:, None, None] ** 2 - np.eye(3)).max(axis=(1, 2)) <= RIGID_TOLERANCE)
  scaled = np.flatnonzero(np.isfinite(scale) & (scale > 1e-6) & uniform & (np.abs(scale - 1) > RIGID_TOLERANCE))
  if scaled.size:
    poses[scaled, :3, :3] /= scale[scaled, None, None]
    print(f"nerfpod: note: {where}: the {what} of {scaled.size} frame(s) has its rotation scaled by "
          f"{scale[scaled].min():.6g}..{scale[scaled].max():.6g}; their axes are used as unit vectors "
          f"(positions unchanged)", file=sys.stderr, flush=True)
  return poses


def check_poses(poses, names, where: str, what: str = "pose") -> None:
  """Refuses, naming the first bad frame (and how many more there are), poses (N, 3 or 4, 4) that are not
  finite or not rigid camera-to-world transforms (see RIGID_TOLERANCE): one shared check, run by every
  loader on the poses as its file gives them."""
  poses = np.asarray(poses, np.float64)
  names = list(names)

  def refuse(bad, problem):
    more = f" (and {bad.size - 1} more frame{'s' if bad.size > 2 else ''})" if bad.size > 1 else ""
    raise UserError(f"{where}: the {what} of frame {names[bad[0]]!r}{more} {problem}; fix or remove that "
                    f"frame.")

  bad = np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))
  if bad.size:
    refuse(bad, "contains NaN or infinity")
  rotation = poses[:, :3, :3]
  gram = np.einsum("nki,nkj->nij", rotation, rotation)
  off = np.abs(gram - np.eye(3)).max(axis=(1, 2))
  det = np.linalg.det(rotation)
  last = (np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) if poses.shape[1] == 4
          else np.zeros(len(poses)))
  bad = np.flatnonzero((off > RIGID_TOLERANCE) | (det <= 0) | (last > RIGID_TOLERANCE))
  if not bad.size:
    return
  i = bad[0]
  scale = float(np.sqrt(np.trace(gram[i]) / 3))
  if scale < 1e-6:
    reason = "has an all-zero rotation (as tools write for a frame they could not register)"
  elif off[i] > RIGID_TOLERANCE and np.abs(gram[i] / scale**2 - np.eye(3)).max() <= RIGID_TOLERANCE:
    reason = f"has a rotation scaled by {scale:.6g} (a camera's axes must be unit vectors)"
  elif off[i] > RIGID_TOLERANCE:
    reason = (f"has a rotation whose axes are not orthonormal (R^T R is off the identity by up to "
              f"{off[i]:.3g}, more than the {RIGID_TOLERANCE:g} allowed)")
  elif det[i] <= 0:
    reason = "has a mirrored rotation (determinant -1): its axes are left-handed"
  else:
    reason = f"has the last row {' '.join(f'{v:g}' for v in poses[i, 3])} instead of 0 0 0 1"
  refuse(bad, f"is not a rigid camera-to-world transform: it {reason}")


def check_split(split: Split, where: str) -> Split:
  """Validates shapes, value ranges, finiteness and rigid poses; raises UserError naming the first bad frame."""
  n = len(split.poses)
  if n == 0:
    raise UserError(f"{where} has no frames; a split needs at least one posed image.")
  cams = split.cameras
  if len(cams) != n or len(split.names) != n:
    raise UserError(f"{where}: {n} poses but {len(cams)} cameras and {len(split.names)} names.")
  if split.pixels.dtype != np.uint8 or split.pixels.shape != (split.num_pixels, 3):
    raise UserError(f"{where}: the pixel buffer is {split.pixels.dtype} {split.pixels.shape}, expected uint8 "
                    f"({split.num_pixels}, 3) for the frames' sizes.")
  if split.alphas is not None and split.alphas.shape != (split.num_pixels,):
    raise UserError(f"{where}: alphas have shape {split.alphas.shape}, expected ({split.num_pixels},).")
  if split.poses.shape != (n, 4, 4):
    raise UserError(f"{where}: poses have shape {split.poses.shape}, expected ({n}, 4, 4) camera-to-world.")
  check_poses(split.poses, split.names, where)
  intrinsic = np.stack([cams.fx, cams.fy, cams.cx, cams.cy], 1)
  bad = np.flatnonzero(~(np.isfinite(intrinsic).all(1) & (cams.fx > 0) & (cams.fy > 0)
                         & np.isfinite(cams.distortion).all(1)))
  if bad.size:
    i = bad[0]
    raise UserError(f"{where}: frame {split.names[i]}'s camera has focal lengths {cams.fx[i]:g}, {cams.fy[i]:g} "
                    f"(or a principal point or distortion) that are not finite positive numbers.")
  bad = np.flatnonzero((cams.width < 1) | (cams.height < 1))
  if bad.size:
    raise UserError(f"{where}: frame {split.names[bad[0]]} has an empty image.")
  if split.bounds is not None and (split.bounds.shape != (n, 2) or not np.isfinite(split.bounds).all()):
    raise UserError(f"{where}: the per-frame near/far bounds are not ({n}, 2) finite numbers.")
  return split


def read_json(path: str):
  """A scene's JSON file (Blender's transforms_*.json, nerfstudio's transforms.json), local or in a bucket;
  malformed JSON is one sentence naming where."""
  try:
    if storage.is_url(path):
      return json.loads(storage.read_bytes(path))
    with open(path) as f:
      return json.load(f)
  except json.JSONDecodeError as e:
    raise UserError(f"{path} is not valid JSON ({e.msg} at line {e.lineno}, column {e.colno}); fix or "
                    f"regenerate the file.") from e
