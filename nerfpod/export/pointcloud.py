"""`nerfpod export pointcloud`: a coloured point cloud (PLY) of the trained scene, as nerfstudio's ns-export
pointcloud makes one.

Random pixels of the training views (--split) are rendered (the whole mesh's devices, chunk after chunk);
where a ray's opacity reaches --min_opacity, the point at its expected depth (the composited depth over the
opacity) is kept with the rendered colour, if it lies in the box [-b, b]^3 of the normalised scene (b: the
hash grid's bound, or 1 for a contracted scene: its unbounded background is left out; --bound sets b),
until --num_points are kept or every pixel was tried. Each point's normal is the field's (minus the
density's gradient, normalised). Points and normals are written in the capture's own coordinates (the
inverse of the run's capture -> scene similarity in scene.json), or in the normalised scene's with
--normalized. No outlier removal.
"""
import jax
import numpy as np
from absl import flags

from nerfpod.errors import UserError
from nerfpod.export import ply, shared
from nerfpod.nerf import cameras

ABOUT = "a coloured point cloud (PLY) from the training views' rendered depth"
DEFAULT_OUT = "pointcloud.ply"
MAX_PERMUTED = 20_000_000  # up to this many pixels, each is tried once (a permutation); past it, drawn at random


def define_flags(flag_values) -> None:
  flags.DEFINE_integer("num_points", 1_000_000, "Points to keep.", flag_values=flag_values)
  flags.DEFINE_float("min_opacity", 0.5, "A ray makes a point where its accumulated opacity is at least this.",
                     flag_values=flag_values)
  flags.DEFINE_string("split", "train", "The views whose pixels are rendered.", flag_values=flag_values)
  flags.DEFINE_float("bound", 0.0, "Keep points in [-b, b]^3 of the normalised scene (0: the field's box; 1 if "
                     "contracted).", flag_values=flag_values)
  flags.DEFINE_integer("seed", 0, "Seeds which pixels are rendered.", flag_values=flag_values)


def check(args) -> None:
  if args.num_points < 1:
    raise UserError(f"--num_points={args.num_points} must be at least 1.")
  if not 0 < args.min_opacity <= 1:
    raise UserError(f"--min_opacity={args.min_opacity} must be in (0, 1].")


def pixel_rays(split, pixel_ids, pixel_center: float):
  """(origins, directions) of flat pixel ids of a split (frame after frame, row-major)."""
  frames = np.searchsorted(split.offsets, pixel_ids, side="right") - 1
  within = pixel_ids - split.offsets[frames]
  widths = split.cameras.width[frames]
  rows, cols = within // widths, within % widths
  return cameras.frame_rays(split.poses[frames], split.cameras, frames, rows, cols, pixel_center)


def export(args, trained: shared.Trained, out: str) -> dict:
  """Writes the PLY to `out` (process 0); returns a summary."""
  config, comps = trained.config, trained.comps
  split = comps.scene.split(args.split)
  bound = shared.box_bound(trained, args.bound)
  total = split.num_pixels
  rng = np.random.default_rng(args.seed)
  order = rng.permutation(total) if total <= MAX_PERMUTED else None
  batch = max(comps.mesh.size, config.eval.chunk) * 8
  kept_points, kept_rgb, kept, tried = [], [], 0, 0
  progress = shared.Progress("pointcloud", args.num_points, "points")
  limit = total if order is not None else max(total, 4 * args.num_points)
  while kept < args.num_points and tried < limit:
    count = min(batch, limit - tried)
    ids = order[tried:tried + count] if order is not None else rng.integers(0, total, count)
    tried += count
    origins, directions = pixel_rays(split, ids, config.data.pixel_center)
    out_rays = shared.render_rays(trained, origins, directions, config.eval.chunk)
    points, hit = shared.hit_points(out_rays, origins, directions, config.render.space, args.min_opacity)
    keep = hit & (np.abs(points) <= bound).all(1)
    kept_points.append(points[keep])
    kept_rgb.append(np.clip(out_rays["rgb"][keep], 0, 1))
    kept += int(keep.sum())
    progress.update(min(kept, args.num_points), f" from {tried} rays")
  points = np.concatenate(kept_points)[:args.num_points] if kept_points else np.zeros((0, 3))
  rgb = np.concatenate(kept_rgb)[:args.num_points] if kept_rgb else np.zeros((0, 3))
  _, _, normals = shared.FieldQuery(trained, config.eval.chunk).query(points)
  comments = [f"nerfpod export pointcloud: step {trained.step} of {trained.workdir}",
              f"coordinates: {'normalized scene' if args.normalized else 'capture'}",
              f"rays tried {tried}, min_opacity {args.min_opacity}, box [-{bound:g}, {bound:g}]^3 (normalized)"]
  if jax.process_index() == 0:
    ply.write_ply(out, trained.points_out(points, args.normalized), rgb,
                  trained.directions_out(normals, args.normalized), comments=comments)
  shared.say(f"pointcloud: {len(points)} points (of {tried} rays) -> {out}")
  return {"points": len(points), "rays": tried}
