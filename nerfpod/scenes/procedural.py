"""The built-in scene: a few coloured solids on a plate, ray-traced exactly, so the default job needs no data.

Everything is generated from a fixed seed in well under a second: ray-surface intersection against a sphere,
a box, a cylinder and a thin round plate, Lambertian shading under one directional light plus ambient light,
composited on white. Cameras sit on the upper hemisphere at radius 4 looking at the origin, with the
Blender synthetic scenes' field of view, so what works here works there.
"""
import dataclasses
import functools

import numpy as np

from nerfpod.nerf.cameras import Intrinsics, image_rays, look_at
from nerfpod.scenes.base import Scene, Split

_LIGHT = np.array([0.4, -0.5, 0.77]) / np.linalg.norm([0.4, -0.5, 0.77])
_AMBIENT = 0.35
CAMERA_ANGLE_X = 0.6911112070083618  # the Blender lego camera's horizontal field of view, radians
RADIUS = 4.0
# traced_splits traces the rays of several frames in one call, about this many (a few MiB a solid): per frame, the
# Python of each solid's intersection cost more than its arithmetic at the small sizes the tests use
RAYS_PER_TRACE = 2**16


def _sphere(o, d, centre, radius):
  oc = o - centre
  a = np.sum(d * d, -1)
  b = np.sum(oc * d, -1)
  c = np.sum(oc * oc, -1) - radius**2
  disc = b * b - a * c
  t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
  t = np.where(t > 1e-6, t, np.inf)
  normal = (o + t[..., None] * d - centre) / radius
  return t, normal


def _box(o, d, lo, hi):
  with np.errstate(divide="ignore", invalid="ignore"):
    inv = 1.0 / d
    t0, t1 = (lo - o) * inv, (hi - o) * inv
  tmin, tmax = np.minimum(t0, t1), np.maximum(t0, t1)
  t_near, t_far = np.max(tmin, -1), np.min(tmax, -1)
  hit = (t_near <= t_far) & (t_near > 1e-6)
  t = np.where(hit, t_near, np.inf)
  axis = np.argmax(tmin, -1)
  normal = np.zeros_like(o)
  sign = -np.sign(np.take_along_axis(d, axis[..., None], -1))[..., 0]
  np.put_along_axis(normal, axis[..., None], sign[..., None], -1)
  return t, normal


def _cylinder(o, d, centre_xy, radius, z0, z1):
  """A closed cylinder with its axis along z, between heights z0 and z1."""
  ox, oy = o[..., 0] - centre_xy[0], o[..., 1] - centre_xy[1]
  a = d[..., 0]**2 + d[..., 1]**2
  b = ox * d[..., 0] + oy * d[..., 1]
  c = ox**2 + oy**2 - radius**2
  disc = b * b - a * c
  with np.errstate(divide="ignore", invalid="ignore"):
    t_side = np.where((disc >= 0) & (a > 0), (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
  z = o[..., 2] + t_side * d[..., 2]
  t_side = np.where((t_side > 1e-6) & (z >= z0) & (z <= z1), t_side, np.inf)
  with np.errstate(divide="ignore", invalid="ignore"):
    t_top = (z1 - o[..., 2]) / d[..., 2]
    t_bot = (z0 - o[..., 2]) / d[..., 2]
  best_t, best_n = t_side, np.stack([ox + t_side * d[..., 0], oy + t_side * d[..., 1],
                                     np.zeros_like(ox)], -1) / radius
  for t_cap, nz in ((t_top, 1.0), (t_bot, -1.0)):
    px, py = ox + t_cap * d[..., 0], oy + t_cap * d[..., 1]
    ok = (t_cap > 1e-6) & (px**2 + py**2 <= radius**2) & (t_cap < best_t)
    best_t = np.where(ok, t_cap, best_t)
    best_n = np.where(ok[..., None], np.array([0.0, 0.0, nz]), best_n)
  return best_t, best_n


def _objects():
  """(intersect function, albedo) of each solid."""
  return [
      (lambda o, d: _sphere(o, d, np.array([0.45, 0.35, 0.45]), 0.45), np.array([0.85, 0.2, 0.15])),
      (lambda o, d: _box(o, d, np.array([-0.8, -0.7, 0.0]), np.array([-0.1, 0.0, 0.7])),
       np.array([0.15, 0.35, 0.85])),
      (lambda o, d: _cylinder(o, d, (0.45, -0.55), 0.28, 0.0, 0.9), np.array([0.2, 0.75, 0.25])),
      (lambda o, d: _cylinder(o, d, (0.0, 0.0), 1.2, -0.08, 0.0), np.array([0.9, 0.75, 0.35])),
  ]


def trace(origins, directions, background=(1.0, 1.0, 1.0), return_alpha: bool = False):
  """Exact colours of rays (..., 3), by ray tracing: the nearest surface's shaded albedo, or the background.

  With return_alpha, also whether each ray hits a surface (1.0) or not (0.0), like an RGBA render's alpha.
  """
  return trace_solids(_objects(), origins, directions, background, return_alpha)


def untraced(origins, directions, background=(1.0, 1.0, 1.0), return_alpha: bool = False):
  """A stand-in for `trace` that traces nothing: every ray the background, alpha 0; for a scene's cameras alone
  (make(traced=False): a tool that reads only the cameras, scenes.cameras_only)."""
  colour = np.broadcast_to(np.asarray(background, np.float32), np.shape(origins)).copy()
  return (colour, np.zeros(np.shape(origins)[:-1], np.float32)) if return_alpha else colour


def trace_solids(objects, origins, directions, background, return_alpha: bool):
  """`trace` over any solids: (intersect(o, d) -> (t, normal), albedo) pairs, the albedo a colour (3,) or a
  function of the hit points (..., 3) -> (..., 3) (a texture; nerfpod/scenes/street.py's)."""
  o, d = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
  best_t = np.full(o.shape[:-1], np.inf)
  colour = np.broadcast_to(np.asarray(background, np.float64), o.shape).copy()
  for intersect, albedo in objects:
    with np.errstate(invalid="ignore"):
      t, normal = intersect(o, d)
    closer = t < best_t
    if callable(albedo):
      if not closer.any():
        continue
      albedo = albedo(o + np.where(closer, t, 0.0)[..., None] * d)
    normal = np.where(closer[..., None], normal, 0.0)
    shade = _AMBIENT + (1 - _AMBIENT) * np.clip(normal @ _LIGHT, 0.0, 1.0)
    colour = np.where(closer[..., None], albedo * shade[..., None], colour)
    best_t = np.where(closer, t, best_t)
  if return_alpha:
    return colour.astype(np.float32), np.isfinite(best_t).astype(np.float32)
  return colour.astype(np.float32)


def hemisphere_poses(n: int, seed: int, min_elevation=10.0, max_elevation=75.0) -> np.ndarray:
  """n camera-to-world poses at radius 4 looking at the origin, uniform in azimuth and in sin(elevation)."""
  rng = np.random.default_rng(seed)
  az = rng.uniform(0, 2 * np.pi, n)
  el = np.arcsin(rng.uniform(np.sin(np.deg2rad(min_elevation)), np.sin(np.deg2rad(max_elevation)), n))
  eyes = RADIUS * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
  return np.stack([look_at(e) for e in eyes]).astype(np.float32)


def load(path: str, data_config, shards=None) -> Scene:
  """The loader's signature (nerfpod.scenes.LOADERS): data.image_size and data.pixel_center; no file. Traced once
  per process for each (size, pixel centre): the same scene object again after, its arrays read-only."""
  return _loaded(int(data_config.image_size), float(data_config.pixel_center))


@functools.lru_cache(maxsize=4)
def _loaded(image_size: int, pixel_center: float) -> Scene:
  return read_only(make(image_size, pixel_center=pixel_center))


def read_only(scene: Scene) -> Scene:
  """`scene` with every array it holds read-only: a built-in scene is made once per process and handed to each
  caller, none of which may write into another's."""
  for split in scene.splits.values():
    for array in (split.pixels, split.poses, split.alphas, split.bounds, split.held,
                  *(getattr(split.cameras, field.name) for field in dataclasses.fields(split.cameras))):
      if isinstance(array, np.ndarray):
        array.flags.writeable = False
  scene.transform.flags.writeable = False
  return scene


def cameras(path: str, data_config) -> Scene:
  """load()'s scene with its images untraced (blank): its cameras only (scenes.cameras_only)."""
  return make(data_config.image_size, pixel_center=data_config.pixel_center, traced=False)


def make(image_size: int = 100, num_train: int = 100, num_val: int = 8, num_test: int = 8,
         pixel_center: float = 0.5, traced: bool = True) -> Scene:
  """The procedural scene; the same arguments always give the same pixels (`traced` False: the same cameras,
  every pixel the background, untraced)."""
  splits = traced_splits(trace if traced else untraced, lambda n, seed: hemisphere_poses(n, seed=seed), image_size,
                         CAMERA_ANGLE_X, {"train": num_train, "val": num_val, "test": num_test}, pixel_center)
  return Scene("procedural", splits, near=2.0, far=6.0, background=(1.0, 1.0, 1.0), kind="procedural")


def traced_splits(trace_fn, poses_fn, image_size: int, angle_x: float, counts: dict, pixel_center: float,
                  first_seed: int = 0) -> dict:
  """{split: Split} of a built-in scene: the images that `trace_fn(origins, directions, return_alpha=True)`
  gives from the poses `poses_fn(n, seed)` draws for each split (seeds first_seed, first_seed + 1, ... in the
  order of `counts`), square cameras of `image_size` pixels with a horizontal field of view of angle_x."""
  focal = 0.5 * image_size / np.tan(0.5 * angle_x)
  intr = Intrinsics.from_focal(image_size, image_size, focal)
  splits = {}
  per_call = max(1, RAYS_PER_TRACE // (image_size * image_size))  # frames traced together
  for seed, (name, n) in enumerate(counts.items(), start=first_seed):
    poses = poses_fn(n, seed)
    traced = []
    for start in range(0, n, per_call):
      rays = [image_rays(p, intr, pixel_center) for p in poses[start:start + per_call]]
      traced.append(trace_fn(np.stack([o for o, _ in rays]), np.stack([d for _, d in rays]), return_alpha=True))
    images = np.concatenate([rgb for rgb, _ in traced]) if traced else np.zeros((0, image_size, image_size, 3),
                                                                                np.float32)
    alphas = np.concatenate([a for _, a in traced]) if traced else np.zeros((0, image_size, image_size), np.float32)
    splits[name] = Split.from_images(images, poses, intr, [f"{name}_{i}" for i in range(n)], alphas=alphas)
  return splits
