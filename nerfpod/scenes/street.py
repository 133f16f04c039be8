"""The built-in large scene: a street of textured buildings, trees and lamps, ray-traced exactly, with the
cameras along it, for fields bigger than one chip (model.regions, docs/scale.md#scenes-bigger-than-one-chip).

The street runs along x over [-LENGTH / 2, LENGTH / 2] (14 units, about 120 spacings of its training
cameras; `blocks` B > 1 makes it B times as long, 14 B units, laid out from the same seed, with B times the
training cameras at the same spacing: a scene with something for K = 8 or 16 regions to hold): a checkered road and pavements (z = 0), a row of buildings on each side (|y| from 2 to 3, 0.9 to 2.6
high, facades with windows), trees (a sphere on a trunk) and lamp posts between them. Every surface has
detail at several scales (the road's checks of 0.25, the windows' 0.33 x 0.4, each building its own colour),
so that a field sized for one CPU device is short of capacity over the whole street, and one per region of
it is not. Lambertian shading under one directional light plus ambient light, on a white sky, as the
procedural scene (nerfpod/scenes/procedural.py, whose ray-solid intersections this reuses).

Cameras stand at eye height (0.8 to 1.6) anywhere along the street, each looking at a point of a facade or
down the street a few units away; the training, validation and test cameras are drawn from the same
distribution with different seeds, so every held-out view is a new view of a part of the street the training
views saw. Everything comes from fixed seeds: the same arguments always give the same pixels.
"""
import functools

import numpy as np

from nerfpod.errors import UserError
from nerfpod.nerf.cameras import look_at
from nerfpod.scenes import procedural
from nerfpod.scenes.base import Scene
from nerfpod.scenes.procedural import _box, _cylinder, _sphere

LENGTH = 14.0         # the street's length along x (one block; `blocks` B: B x LENGTH)
HALF_WIDTH = 3.5      # the ground's half width along y
FIELD_OF_VIEW = 1.0   # horizontal, radians (57 degrees: a phone's main camera)
NEAR, FAR = 0.05, 16.0
_LAYOUT_SEED = 7


def _checker(points, size, dark, light):
  """Alternating colours in squares of `size` on the ground plane."""
  cells = np.floor(points[..., 0] / size) + np.floor(points[..., 1] / size)
  odd = (cells.astype(np.int64) % 2)[..., None]
  return np.where(odd == 1, np.asarray(dark), np.asarray(light))


def _facade(colour):
  """A building's albedo: its colour, with dark windows in rows and columns over its walls."""
  colour = np.asarray(colour, np.float64)

  def albedo(points):
    along = points[..., 0] + points[..., 1]  # walls facing the street or its cross streets
    window = (np.mod(along * 3.0, 1.0) > 0.35) & (np.mod(points[..., 2] * 2.5, 1.0) > 0.4) & (points[..., 2] > 0.3)
    return np.where(window[..., None], np.array([0.12, 0.16, 0.25]), colour)
  return albedo


def _objects(length: float = LENGTH):
  """(intersect function, albedo: a colour, or a function of the hit points) of every solid of a street of
  `length` (the layout from the same seed: LENGTH gives the street as it always was)."""
  rng = np.random.default_rng(_LAYOUT_SEED)
  half = length / 2
  objects = [
      # the road (|y| < 1.2) and the pavements, one slab whose top is the ground
      (lambda o, d: _box(o, d, np.array([-half - 0.5, -HALF_WIDTH, -0.1]), np.array([half + 0.5, HALF_WIDTH, 0.0])),
       lambda p: np.where((np.abs(p[..., 1]) < 1.2)[..., None],
                          _checker(p, 0.25, (0.25, 0.25, 0.28), (0.42, 0.42, 0.45)),
                          _checker(p, 0.5, (0.72, 0.66, 0.55), (0.82, 0.78, 0.68)))),
  ]
  for side in (-1.0, 1.0):
    x = -half
    while x < half:
      width = rng.uniform(0.9, 1.8)
      height = rng.uniform(0.9, 2.6)
      lo = np.array([x, 2.0 if side > 0 else -3.0, 0.0])
      hi = np.array([min(x + width, half), 3.0 if side > 0 else -2.0, height])
      colour = rng.uniform(0.35, 0.95, 3)
      objects.append((lambda o, d, lo=lo, hi=hi: _box(o, d, lo, hi), _facade(colour)))
      x += width + rng.uniform(0.05, 0.4)  # a gap or a narrow lane between buildings
    for x in np.arange(-half + 0.8, half, 1.6) + rng.uniform(-0.2, 0.2):
      y = 1.5 * side
      if rng.uniform() < 0.6:  # a tree: a trunk and a crown
        crown = np.array([x, y, rng.uniform(0.9, 1.2)])
        radius = rng.uniform(0.3, 0.45)
        objects.append((lambda o, d, c=crown, r=radius: _sphere(o, d, c, r),
                        rng.uniform([0.1, 0.4, 0.1], [0.3, 0.7, 0.25])))
        objects.append((lambda o, d, x=x, y=y, top=crown[2]: _cylinder(o, d, (x, y), 0.06, 0.0, top),
                        np.array([0.4, 0.28, 0.18])))
      else:  # a lamp post with its lamp
        objects.append((lambda o, d, x=x, y=y: _cylinder(o, d, (x, y), 0.04, 0.0, 1.5), np.array([0.2, 0.2, 0.22])))
        objects.append((lambda o, d, x=x, y=y: _sphere(o, d, np.array([x, y, 1.55]), 0.1),
                        np.array([0.95, 0.85, 0.4])))
  return objects


def trace(origins, directions, background=(1.0, 1.0, 1.0), return_alpha: bool = False, length: float = LENGTH):
  """Exact colours of rays (..., 3): the nearest surface's shaded albedo, or the background (the sky); with
  return_alpha also whether each ray hits a surface (1.0) or not (0.0). `length`: the street's."""
  return procedural.trace_solids(_objects(length), origins, directions, background, return_alpha)


def street_poses(n: int, seed: int, length: float = LENGTH) -> np.ndarray:
  """n camera-to-world poses at eye height along the street (of `length`), each looking at a facade or down
  the street."""
  rng = np.random.default_rng(seed)
  half = length / 2
  poses = []
  for _ in range(n):
    eye = np.array([rng.uniform(-half + 0.5, half - 0.5), rng.uniform(-1.0, 1.0), rng.uniform(0.8, 1.6)])
    if rng.uniform() < 0.7:  # a facade, a little ahead or behind
      target = np.array([eye[0] + rng.uniform(-1.5, 1.5), rng.choice([-2.0, 2.0]), rng.uniform(0.6, 1.6)])
    else:  # down the street
      target = np.array([eye[0] + rng.choice([-1.0, 1.0]) * rng.uniform(2.0, 5.0), rng.uniform(-0.8, 0.8),
                         rng.uniform(0.4, 1.2)])
    poses.append(look_at(eye, target))
  return np.stack(poses).astype(np.float32)


def blocks_of(path: str) -> int:
  """The street's blocks from data.path, which names no file for this built-in scene: '' (1, the street as
  it always was) or 'blocks=B' (configs/street.py:blocks=B writes it)."""
  if not path:
    return 1
  key, _, value = path.partition("=")
  if key != "blocks" or not value.isdigit() or int(value) < 1:
    raise UserError(f"data.kind=street takes data.path '' (one block) or 'blocks=B' (B >= 1), not {path!r}; "
                    f"use --config=configs/street.py:blocks=B.")
  return int(value)


def load(path: str, data_config, shards=None) -> Scene:
  """The loader's signature (nerfpod.scenes.LOADERS): data.image_size and data.pixel_center; no file;
  data.path '' or 'blocks=B' (blocks_of). Traced once per process for each (size, pixel centre, blocks): the
  same scene object again after, its arrays read-only (procedural.read_only)."""
  return _loaded(int(data_config.image_size), float(data_config.pixel_center), blocks_of(path))


@functools.lru_cache(maxsize=4)
def _loaded(image_size: int, pixel_center: float, blocks: int) -> Scene:
  return procedural.read_only(make(image_size, pixel_center=pixel_center, blocks=blocks))


def cameras(path: str, data_config) -> Scene:
  """load()'s scene with its images untraced (blank): its cameras only (scenes.cameras_only)."""
  return make(data_config.image_size, pixel_center=data_config.pixel_center, blocks=blocks_of(path), traced=False)


def make(image_size: int = 64, num_train: int = 120, num_val: int = 8, num_test: int = 8,
         pixel_center: float = 0.5, blocks: int = 1, traced: bool = True) -> Scene:
  """The street scene (module docstring); `blocks` B > 1: B times as long, with B times num_train (the same
  spacing of training cameras) and the held-out counts as given. `traced` False: the same cameras, every pixel
  the sky, untraced (tracing every frame against every solid grows as B^2: minutes at B = 8)."""
  length = LENGTH * blocks
  splits = procedural.traced_splits(
      (lambda o, d, **kw: trace(o, d, length=length, **kw)) if traced else procedural.untraced,
      lambda n, seed: street_poses(n, seed, length),
      image_size, FIELD_OF_VIEW, {"train": num_train * blocks, "val": num_val, "test": num_test}, pixel_center,
      first_seed=100)
  return Scene("street" if blocks == 1 else f"street_x{blocks}", splits, near=NEAR, far=FAR,
               background=(1.0, 1.0, 1.0), kind="street")
