"""`nerfpod export cameras`: the run's cameras and images as a nerfstudio transforms.json, so that a scene
trained here can be handed to another tool (nerfstudio, instant-ngp, 3D Gaussian Splatting's loaders, and
nerfpod's own nerfstudio loader).

Every frame of every split: its image as nerfpod loaded it (the pixels the cameras describe, after
data.downscale) written to images/SPLIT_NNNN.png beside the JSON, its camera-to-world pose (OpenGL axes, as
nerfstudio's) and its own intrinsics (fl_x, fl_y, cx, cy, w, h and the distortion k1, k2, k3, k4, p1, p2;
camera_model OPENCV where any frame is distorted, else PINHOLE), and the splits as train_filenames,
val_filenames and test_filenames. Poses are in the capture's own coordinates (the inverse of the run's
capture -> scene similarity in scene.json), or in the normalised scene's with --normalized. A run trained
with pose refinement (train.pose_refine) exports its training frames' corrected poses, the ones its field was
fitted to, and keeps each one's given pose as "nerfpod_given_transform_matrix"; held-out frames keep their
given poses (they were evaluated from them).
"""
import io
import os

import jax
import numpy as np
from PIL import Image

from nerfpod import storage
from nerfpod.workdir import files as workdir_files
from nerfpod.errors import UserError
from nerfpod.export import shared
from nerfpod.nerf import pose_correction
from nerfpod.nerf.cameras import DISTORTION_PARAMS

ABOUT = "the cameras, poses and images as a nerfstudio transforms.json"
DEFAULT_OUT = os.path.join("cameras", "transforms.json")


def define_flags(flag_values) -> None:
  del flag_values  # --workdir, --out and --normalized only


def check(args) -> None:
  if args.out and not str(args.out).endswith(".json"):
    raise UserError(f"--out={args.out} must be the .json file to write (e.g. DIR/transforms.json); the images "
                    f"go to images/ beside it.")


def export(args, trained: shared.Trained, out: str) -> dict:
  scene = trained.comps.scene
  corrections = pose_correction.of_params(trained.params)
  folder = storage.path(out).parent
  frames, lists, written = [], {}, {}  # written: id(split) -> its file names (val and test may be one split)
  distorted = any(s.cameras.is_distorted for s in scene.splits.values())
  total = sum(len(s) for s in scene.splits.values())
  progress = shared.Progress("cameras", total, "frames")
  done = 0
  for name, split in scene.splits.items():
    if id(split) in written:
      lists[name] = written[id(split)]
      continue
    given = trained.poses_out(split.poses, args.normalized)
    corrected = name == "train" and corrections is not None
    poses = (trained.poses_out(pose_correction.corrected_poses(split.poses, corrections), args.normalized)
             if corrected else given)
    files = []
    for i in range(len(split)):
      file_path = f"images/{name}_{i:04d}.png"
      files.append(file_path)
      if jax.process_index() == 0:
        buffer = io.BytesIO()
        Image.fromarray(split.image_uint8(i)).save(buffer, format="PNG")
        (folder / "images").mkdir(parents=True, exist_ok=True)
        (folder / file_path).write_bytes(buffer.getvalue())
      cams = split.cameras
      frame = {"file_path": file_path, "transform_matrix": poses[i].tolist(), "fl_x": float(cams.fx[i]),
               "fl_y": float(cams.fy[i]), "cx": float(cams.cx[i]), "cy": float(cams.cy[i]), "w": int(cams.width[i]),
               "h": int(cams.height[i]), "nerfpod_name": str(split.names[i])}
      frame.update({k: float(v) for k, v in zip(DISTORTION_PARAMS, cams.distortion[i])})
      if corrected:
        frame["nerfpod_given_transform_matrix"] = given[i].tolist()
      frames.append(frame)
      done += 1
      progress.update(done)
    written[id(split)] = lists[name] = files
  meta = {"camera_model": "OPENCV" if distorted else "PINHOLE", "frames": frames,
          **{f"{name}_filenames": files for name, files in lists.items() if name in ("train", "val", "test")},
          "nerfpod": {"workdir": trained.workdir, "step": trained.step, "scene": scene.name,
                      "coordinates": "normalized scene" if args.normalized else "capture",
                      "pose_refined": corrections is not None,
                      "capture_to_scene": np.asarray(trained.capture_to_scene).tolist()}}
  if jax.process_index() == 0:
    workdir_files.write_json(out, meta)
  shared.say(f"cameras: {len(frames)} frames -> {out}")
  return {"frames": len(frames)}
