"""`nerfpod export depth`: per-view depth maps of a split, rendered over the whole mesh's devices.

Each view's depth is the distance along its camera's viewing axis (z-depth) to the point where its rays end
(the composited depth over the opacity), in the capture's units (or the normalised scene's with
--normalized); 0 where the opacity stays under --min_opacity (nothing there). --format png: 16-bit PNGs,
depth = value * scale, each view's scale chosen so that its farthest depth is 65535; npy: float32 arrays.
depth.json beside them lists each view's file, frame name, scale, pose (camera-to-world, OpenGL axes) and
intrinsics, in the same coordinates.
"""
import io

import jax
import numpy as np
from absl import flags
from PIL import Image

from nerfpod import storage
from nerfpod.workdir import files as workdir_files
from nerfpod.errors import UserError
from nerfpod.export import shared
from nerfpod.nerf import cameras

ABOUT = "per-view depth maps of a split (16-bit PNG with their scale, or .npy)"
FORMATS = ("png", "npy")


def default_out(args) -> str:
  return f"depth_{args.split}"


def define_flags(flag_values) -> None:
  flags.DEFINE_string("split", "train", "The views to render.", flag_values=flag_values)
  flags.DEFINE_string("format", "png", "png (16-bit, scale in depth.json) or npy (float32).", flag_values=flag_values)
  flags.DEFINE_float("min_opacity", 0.5, "Pixels whose accumulated opacity stays under this have depth 0.",
                     flag_values=flag_values)


def check(args) -> None:
  if args.format not in FORMATS:
    raise UserError(f"--format={args.format} is not one of {', '.join(FORMATS)}.")
  if not 0 < args.min_opacity <= 1:
    raise UserError(f"--min_opacity={args.min_opacity} must be in (0, 1].")


def z_depth(points_Nx3, c2w_4x4) -> np.ndarray:
  """Distance of points in front of a camera along its viewing axis (-z, OpenGL)."""
  c2w = np.asarray(c2w_4x4, np.float64)
  return (np.asarray(points_Nx3, np.float64) - c2w[:3, 3]) @ -c2w[:3, 2]


def export(args, trained: shared.Trained, out: str) -> dict:
  config, comps = trained.config, trained.comps
  split = comps.scene.split(args.split)
  folder = storage.path(out)
  units = 1.0 if args.normalized else 1.0 / trained.scale  # output units per scene unit
  poses = trained.poses_out(split.poses, args.normalized)
  views = []
  progress = shared.Progress(f"depth {args.split}", len(split), "views")
  for i in range(len(split)):
    intr = split.cameras[i]
    origins, directions = cameras.image_rays(split.poses[i], intr, config.data.pixel_center)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    rendered = shared.render_rays(trained, origins, directions, config.eval.chunk)
    points, hit = shared.hit_points(rendered, origins, directions, config.render.space, args.min_opacity)
    depth = np.where(hit, z_depth(points, split.poses[i]) * units, 0.0).reshape(intr.height, intr.width)
    depth = np.maximum(depth, 0.0)
    name = f"{args.split}_{i:04d}.{args.format}"
    view = {"file": name, "name": str(split.names[i]), "index": i, "transform_matrix": poses[i].tolist(),
            "fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx, "cy": intr.cy, "w": intr.width, "h": intr.height,
            "distortion": dict(zip(cameras.DISTORTION_PARAMS, map(float, intr.distortion)))}
    buffer = io.BytesIO()
    if args.format == "png":
      scale = float(depth.max()) / 65535.0 if depth.max() > 0 else 1.0
      Image.fromarray(np.round(depth / scale).astype(np.uint16)).save(buffer, format="PNG")
      view["scale"] = scale
    else:
      np.save(buffer, depth.astype(np.float32))
    if jax.process_index() == 0:
      folder.mkdir(parents=True, exist_ok=True)
      (folder / name).write_bytes(buffer.getvalue())
    views.append(view)
    progress.update(i + 1)
  meta = {"split": args.split, "format": args.format, "step": trained.step, "workdir": trained.workdir,
          "coordinates": "normalized scene" if args.normalized else "capture",
          "depth": "z-depth along each camera's viewing axis; 0 where nothing was hit"
                   + ("; png: depth = value * scale" if args.format == "png" else ""),
          "min_opacity": args.min_opacity, "views": views}
  if jax.process_index() == 0:
    workdir_files.write_json(folder / "depth.json", meta)
  shared.say(f"depth: {len(views)} views -> {out}")
  return {"views": len(views)}
