"""The capture folder nerfpod prepare writes from a reconstruction: images/ (the registered images), sparse/0/
(the COLMAP model), images_2/4/8 for large images, poses_bounds.npy (LLFF's layout, as imgs2poses.py writes it),
transforms.json (nerfstudio's, as ns-process-data writes it), and the atomic JSON writes of prepare.json."""
import dataclasses
import json
import os
import shutil

import numpy as np
from PIL import Image

from nerfpod.prepare.progress import Progress

DOWNSCALES = (2, 4, 8)         # images_N/ folders, where the shrunk image's long side is still >= MIN_SHRUNK_SIDE
MIN_SHRUNK_SIDE = 200
PREPARE_JSON = "prepare.json"
# OpenCV/COLMAP cameras (x right, y down, looking down +z) -> OpenGL (x right, y up, looking down -z).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


# ---------------------------------------------------------------------------------------------------------------
# The writers (pure)


def downscale_factors(width: int, height: int) -> list[int]:
  """The images_N/ folders worth writing: N in 2, 4, 8 while the shrunk long side stays >= 200 pixels."""
  return [n for n in DOWNSCALES if max(width, height) // n >= MIN_SHRUNK_SIDE]


@dataclasses.dataclass(frozen=True)
class Model:
  """What the writers need of a reconstruction, in plain arrays, frames sorted by image name."""
  names: list[str]
  w2c: np.ndarray          # (N, 3, 4) world-to-camera, OpenCV axes (COLMAP's cam_from_world)
  camera_ids: list[int]    # per image
  cameras: dict            # camera id -> {"model", "width", "height", "params": [...]} (COLMAP's order)
  bounds: np.ndarray       # (N, 2) near/far: 0.1 and 99.9 percentile depths of the points each image sees

  def c2w_opencv(self) -> np.ndarray:
    """(N, 4, 4) camera-to-world, OpenCV axes."""
    w2c = np.concatenate([self.w2c, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(self.w2c), 1, 1))], axis=1)
    return np.linalg.inv(w2c)


def pinhole(camera: dict) -> dict:
  """A COLMAP camera as nerfstudio's keys: fl_x, fl_y, cx, cy, w, h and k1, k2, p1, p2 (zero where the
  model has none)."""
  p, model = list(camera["params"]), camera["model"]
  if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
    f, cx, cy, extra = p[0], p[1], p[2], p[3:]
    fx = fy = f
    k = dict(zip(("k1", "k2"), extra))
    k1, k2, p1, p2 = k.get("k1", 0.0), k.get("k2", 0.0), 0.0, 0.0
  elif model in ("PINHOLE", "OPENCV"):
    fx, fy, cx, cy = p[:4]
    k1, k2, p1, p2 = (list(p[4:8]) + [0.0] * 4)[:4]
  else:
    raise ValueError(f"camera model {model} is not one prepare writes")
  return {"w": int(camera["width"]), "h": int(camera["height"]), "fl_x": float(fx), "fl_y": float(fy),
          "cx": float(cx), "cy": float(cy), "k1": float(k1), "k2": float(k2), "p1": float(p1), "p2": float(p2)}


def poses_bounds(model: Model) -> np.ndarray:
  """LLFF's poses_bounds.npy (N, 17) as imgs2poses.py writes it, rows in image-name order: the camera-to-world
  3x4 with rotation columns [down, right, back], then [height, width, focal] at the images' full size (fx;
  LLFF has no principal point or distortion), then near and far."""
  c2w = model.c2w_opencv()[:, :3, :]
  # OpenCV's camera axes [x, y, z] are [right, down, forward]: LLFF's [down, right, back] is [y, x, -z].
  cols = np.stack([c2w[:, :, 1], c2w[:, :, 0], -c2w[:, :, 2], c2w[:, :, 3]], axis=2)
  hwf = np.array([[model.cameras[c]["height"], model.cameras[c]["width"], pinhole(model.cameras[c])["fl_x"]]
                  for c in model.camera_ids], np.float64)
  rows = np.concatenate([cols, hwf[:, :, None]], axis=2).reshape(len(c2w), 15)
  return np.concatenate([rows, model.bounds], axis=1)


def transforms_json(model: Model, image_dir: str = "images") -> dict:
  """nerfstudio's transforms.json (as ns-process-data writes it): the intrinsics at the top level where all
  images share one camera, else per frame; camera_model OPENCV (PINHOLE where the model has no distortion);
  file_path relative to the file; transform_matrix camera-to-world in OpenGL axes."""
  distorted = any(cam["model"] not in ("PINHOLE", "SIMPLE_PINHOLE") for cam in model.cameras.values())
  shared = len(set(model.camera_ids)) == 1
  out = {"camera_model": "OPENCV" if distorted else "PINHOLE"}
  if shared:
    out.update(pinhole(model.cameras[model.camera_ids[0]]))
  frames = []
  for name, cam_id, c2w in zip(model.names, model.camera_ids, model.c2w_opencv()):
    frame = {"file_path": f"{image_dir}/{name}", "transform_matrix": (c2w @ OPENCV_TO_OPENGL).tolist()}
    if not shared:
      frame.update(pinhole(model.cameras[cam_id]))
    frames.append(frame)
  out["frames"] = frames
  return out


def looks_forward_facing(c2w_opencv: np.ndarray) -> bool:
  """Whether every camera looks about the same way (LLFF's forward-facing captures): the mean of their
  viewing directions is longer than 0.9 (a 360-degree capture's is near 0)."""
  forward = c2w_opencv[:, :3, 2]
  forward = forward / np.linalg.norm(forward, axis=1, keepdims=True)
  return bool(np.linalg.norm(forward.mean(0)) > 0.9)


# ---------------------------------------------------------------------------------------------------------------
# The writing stage


def model_of(rec) -> Model:
  """The plain arrays of a pycolmap Reconstruction (its registered images, sorted by name)."""
  images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
  xyz = {pid: p.xyz for pid, p in rec.points3D.items()}
  all_xyz = np.array(list(xyz.values()), np.float64).reshape(-1, 3)
  w2c, bounds = [], []
  for im in images:
    m = np.asarray(im.cam_from_world().matrix(), np.float64)
    w2c.append(m)
    seen = np.array([xyz[p.point3D_id] for p in im.points2D if p.has_point3D()], np.float64).reshape(-1, 3)
    depth = seen @ m[2, :3] + m[2, 3]
    depth = depth[depth > 0]
    if depth.size == 0:  # sees no point: the depths of all points in front of it
      depth = all_xyz @ m[2, :3] + m[2, 3]
      depth = depth[depth > 0]
    bounds.append(np.percentile(depth, [0.1, 99.9]) if depth.size else [0.1, 100.0])
  cameras = {int(cid): {"model": cam.model.name, "width": int(cam.width), "height": int(cam.height),
                        "params": [float(v) for v in cam.params]} for cid, cam in rec.cameras.items()}
  return Model([im.name for im in images], np.array(w2c), [int(im.camera_id) for im in images], cameras,
               np.array(bounds, np.float64))


def shrink(path_in: str, path_out: str, factor: int):
  """The image shrunk `factor` times as nerfpod's loaders shrink on loading (crop to a multiple of the factor,
  then the mean of each factor x factor block), saved in the same format."""
  with Image.open(path_in) as im:
    im = im.convert("RGB")
    w, h = im.width // factor * factor, im.height // factor * factor
    small = im.crop((0, 0, w, h)).reduce(factor)
  if os.path.splitext(path_out)[1].lower() == ".png":
    small.save(path_out)
  else:
    small.save(path_out, quality=95)


def stage_writing(capture: str, image_dir: str, rec) -> tuple[Model, list[int]]:
  model = model_of(rec)
  if os.path.isdir(capture):
    shutil.rmtree(capture)
  os.makedirs(os.path.join(capture, "images"))
  for name in model.names:  # the registered images only (LLFF's loader wants one image per pose)
    s, d = os.path.join(image_dir, name), os.path.join(capture, "images", name)
    try:
      os.link(s, d)
    except OSError:
      shutil.copy2(s, d)
  sparse = os.path.join(capture, "sparse", "0")
  os.makedirs(sparse)
  rec.write_binary(sparse)
  sizes = {(c["width"], c["height"]) for c in model.cameras.values()}
  factors = downscale_factors(max(w for w, _ in sizes), max(h for _, h in sizes))
  if factors:
    progress = Progress("downscaling", len(model.names) * len(factors), "images")
    done = 0
    for n in factors:
      os.makedirs(os.path.join(capture, f"images_{n}"))
      for name in model.names:
        shrink(os.path.join(image_dir, name), os.path.join(capture, f"images_{n}", name), n)
        done += 1
        progress.update(done)
  np.save(os.path.join(capture, "poses_bounds.npy"), poses_bounds(model))
  write_json(os.path.join(capture, "transforms.json"), transforms_json(model))
  return model, factors


def write_json(path: str, obj):
  """Writes `obj` as JSON to `path` whole: to a .tmp file beside it, then renamed over it."""
  tmp = path + ".tmp"
  with open(tmp, "w") as f:
    json.dump(obj, f, indent=1)
    f.write("\n")
  os.replace(tmp, path)
