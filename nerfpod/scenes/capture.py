"""What the real-capture loaders (llff, colmap, nerfstudio) share: reading their images as uint8, the
images_N folders, the held-out frames, pose normalisation, their space and ray bounds.

Images are read straight into their split's final buffer (`scenes.base.Split.from_frames`): the loaders
learn the images' sizes from the files' headers (`image_sizes`), build the cameras and the splits, then
decode each image into its slot, READ_THREADS at a time. Loading N images of W x H pixels therefore takes
about N * W * H * 3 bytes of host memory, plus one decoded image per thread (docs/data.md).

Pose normalisation (data.orient, data.center, data.scale) is one similarity computed from every frame of
the capture (train and held-out alike, as the original LLFF code does) and applied to all of them; the
Scene records it (`Scene.transform`, capture -> scene) and training writes it to the workdir's scene.json.
"""
import dataclasses
import os

import numpy as np
from PIL import Image, UnidentifiedImageError

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.nerf import poses as pose_math
from nerfpod.nerf import cameras
from nerfpod.nerf.cameras import Cameras
from nerfpod.scenes.formats import LOADERS

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
UNBOUNDED_NEAR, UNBOUNDED_FAR = 0.2, 1e6  # mip-NeRF 360's ray bounds, in the normalised frame
# OpenCV/COLMAP cameras (x right, y down, looking down +z) -> OpenGL (x right, y up, looking down -z), as a
# 4x4: c2w_opengl = c2w_opencv @ OPENCV_TO_OPENGL (nerf/cameras.py's axes, the translation kept).
OPENCV_TO_OPENGL = np.diag([*np.diag(cameras.OPENCV_TO_OPENGL), 1.0])
# Images decoded at once while loading: decoding releases the GIL, so one thread per core (at most 8) keeps
# the cores busy; each thread holds one decoded image on top of the splits' buffers.
READ_THREADS = max(1, min(8, os.cpu_count() or 1))


def list_images(folder: str) -> list[str]:
  """The image files of a folder (png, jpg, jpeg in any case), sorted by name."""
  return sorted(f for f in storage.listdir(folder) if os.path.splitext(f)[1].lower() in IMAGE_EXTENSIONS)


def image_folder(root: str, downscale: int, base: str = "images") -> tuple[str, int]:
  """(folder, factor still to apply in memory): `base`_N/ where data.downscale = N > 1 and it exists, else
  `base`/ shrunk N times on loading. Refuses, naming the folders there are, where neither exists."""
  if downscale > 1 and storage.isdir(storage.join(root, f"{base}_{downscale}")):
    return storage.join(root, f"{base}_{downscale}"), 1
  if storage.isdir(storage.join(root, base)):
    return storage.join(root, base), downscale
  there = sorted(d for d in storage.listdir(root) if d.startswith(base) and storage.isdir(storage.join(root, d)))
  hint = (f"; it has {', '.join(d + '/' for d in there)}: pass --config.data.downscale="
          f"{there[0].rpartition('_')[2] if there[0] != base else 1}" if there else
          f"; put the capture's images in {base}/ (or {base}_N/ for images shrunk N times)")
  wanted = f"{base}_{downscale}/ nor {base}/" if downscale > 1 else f"{base}/"
  raise UserError(f"{root} has no {wanted} folder for data.downscale={downscale}{hint}.")


def unreadable_image(name: str, path: str, error: OSError) -> UserError:
  """The one sentence for an image file that exists but does not decode: cut off (a copy that stopped) or not
  an image at all (PIL's own words, less the file object it names)."""
  reason = "not an image format it reads" if isinstance(error, UnidentifiedImageError) else str(error)
  return UserError(f"frame {name!r}: {path} is not a readable image ({reason}); copy it again, or remove the "
                   f"frame.")


def read_image(path: str, name: str, downscale: int = 1) -> np.ndarray:
  """An image file as (H, W, 3) uint8, shrunk `downscale` times by averaging downscale^2 blocks (the image
  cropped to a multiple of it). An alpha channel is dropped: captures are opaque. A URL's file is fetched
  whole, in one request."""
  try:
    with Image.open(storage.open_binary(path) if storage.is_url(path) else path) as im:
      im = im.convert("RGB")
      if downscale > 1:  # PIL's reduce is the block average, in C
        w, h = im.width // downscale * downscale, im.height // downscale * downscale
        im = im.crop((0, 0, w, h)).reduce(downscale)
      return np.asarray(im)
  except FileNotFoundError as e:
    raise UserError(f"frame {name!r}: image file {path} not found; restore it or remove the frame.") from e
  except OSError as e:
    raise unreadable_image(name, path, e) from e


def image_size(path: str, name: str, downscale: int = 1) -> tuple[int, int]:
  """(width, height) of an image file as read_image gives it (shrunk `downscale` times), from its header
  alone: nothing is decoded (of a URL's file, only its first block is fetched)."""
  try:
    with storage.header_reader(path) as f, Image.open(f) as im:
      w, h = im.size
  except FileNotFoundError as e:
    raise UserError(f"frame {name!r}: image file {path} not found; restore it or remove the frame.") from e
  except OSError as e:
    raise unreadable_image(name, path, e) from e
  return (w // downscale, h // downscale) if downscale > 1 else (w, h)


def image_sizes(paths: list[str], names: list[str], downscale=1) -> tuple[np.ndarray, np.ndarray]:
  """(widths, heights), (N,) int64, of many image files as read_image gives them; `downscale` an int or one
  per file."""
  factors = np.broadcast_to(np.asarray(downscale, np.int64), (len(paths),))
  sizes = [image_size(p, n, int(f)) for p, n, f in zip(paths, names, factors)]
  return np.array([s[0] for s in sizes], np.int64), np.array([s[1] for s in sizes], np.int64)


def check_files_exist(paths: list[str], names: list[str], where: str) -> None:
  """One sentence naming every missing image (the first few of many) and the folder looked in; where that
  folder holds no image at all, it says so, and how to fill it."""
  missing = [(p, n) for p, n in zip(paths, names) if not storage.isfile(p)]
  if not missing:
    return
  shown = ", ".join(n for _, n in missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
  folders = sorted({os.path.dirname(p) for p, _ in missing})
  empty = not (storage.isdir(folders[0]) and list_images(folders[0]))
  if len(folders) == 1 and len(missing) == len(names) and empty:
    raise UserError(empty_folder_message(folders[0], f"{where} lists {len(names)} images ({shown}) to read from "
                                                     f"{folders[0]}/"))
  place = f"in {folders[0]}/" if len(folders) == 1 else f"in {len(folders)} folders ({', '.join(folders[:3])})"
  raise UserError(f"{where} lists {len(missing)} image(s) of its {len(names)} frames that do not exist {place} "
                  f"({shown}); restore them or remove those frames from it.")


def empty_folder_message(folder: str, what: str) -> str:
  """`what`, then that `folder` holds no images and how to fill it: for an images_N/ beside images/, the
  ways to images shrunk N times."""
  state = "holds no images" if storage.isdir(folder) else "does not exist"
  parent, base = os.path.split(storage.normpath(folder))
  stem, _, factor = base.rpartition("_")
  if stem and factor.isdigit() and storage.isdir(storage.join(parent, stem)):
    fix = (f"regenerate {base}/ as the images of {stem}/ shrunk {factor} times, delete the empty {base}/ to have "
           f"{stem}/ shrunk on loading, or use --config.data.downscale=1")
  else:
    fix = f"put the capture's images in {folder}/"
  return f"{what}, but that folder {state}; {fix}."


def heldout_indices(n: int, llffhold: int) -> np.ndarray:
  """Every `llffhold`-th frame from the first (0, 8, 16, ... for 8): the test frames of the LLFF and
  mip-NeRF 360 papers."""
  return np.arange(n)[::llffhold]


def normalization(poses_Nx4x4: np.ndarray, bounds_Nx2: np.ndarray | None, data_config, kind: str) -> np.ndarray:
  """The capture -> scene similarity that data.orient, data.center and data.scale ask for (4x4).

  'auto' means what the format's entry in LOADERS (scenes.formats) says: for LLFF, the original's recentring
  on the average camera (orient 'llff', centre 'poses') and its bounds rescale, s = 1 / (0.75 min near); for
  COLMAP and transforms.json: +z up, centred on the point the cameras look at (or their mean where they look
  the same way), the farthest camera at distance 1. A positive data.scale is a fixed factor instead.
  """
  loader = LOADERS[kind]
  poses = np.asarray(poses_Nx4x4, np.float64)
  positions = poses[:, :3, 3]
  orient = data_config.orient if data_config.orient != "auto" else loader.auto_orient
  center = data_config.center if data_config.center != "auto" else loader.auto_center
  if center == "focus":
    focus = pose_math.focus_point(poses)
    centre = positions.mean(0) if focus is None else focus
  elif center == "poses":
    centre = positions.mean(0)
  else:
    centre = np.zeros(3)
  if orient == "llff":
    rotation = pose_math.poses_avg(poses)[:3, :3].T
  elif orient == "up":
    rotation = pose_math.up_rotation(poses)
  elif orient == "pca":
    rotation = pose_math.pca_rotation(positions, poses)
  else:
    rotation = np.eye(3)
  scale = float(data_config.scale)
  if scale <= 0:
    if loader.scale_by_bounds and bounds_Nx2 is not None:
      scale = 1.0 / (float(np.min(bounds_Nx2)) * 0.75)
    else:
      farthest = float(np.max(np.linalg.norm(positions - centre, axis=1)))
      scale = 1.0 / farthest if farthest > 0 else 1.0
  return pose_math.similarity(scale, rotation, centre)


@dataclasses.dataclass(frozen=True)
class Framing:
  """Where a capture's frames go: poses and bounds normalised, which frames make which split, the space and
  ray bounds. (Assembling these into a Scene is the loaders' last step.)"""
  transform: np.ndarray        # (4, 4) capture -> scene similarity
  poses: np.ndarray            # (N, 4, 4) float32 camera-to-world OpenGL, in the scene's frame
  bounds: np.ndarray | None    # (N, 2) float32 near/far depths in the scene's units, where the format has them
  splits: dict[str, np.ndarray]  # split name -> frame indices
  space: str
  near: float
  far: float


def frame(poses_opengl: np.ndarray, bounds: np.ndarray | None, names: list[str], data_config, kind: str,
          where: str, default_space: str, split_lists: dict[str, np.ndarray] | None = None) -> Framing:
  """Normalises a capture's poses and bounds (data.orient/center/scale), splits its frames (explicit lists,
  else every data.llffhold-th frame held out as test and as val) and picks its space and ray bounds. The
  poses are rigid transforms: the loader has checked them (scenes.base.check_poses) before."""
  poses_opengl = np.asarray(poses_opengl, np.float64)
  transform = normalization(poses_opengl, bounds, data_config, kind)
  poses = pose_math.transform_poses(transform, poses_opengl).astype(np.float32)
  if bounds is not None:
    bounds = (np.asarray(bounds, np.float64) * pose_math.scale_of(transform)).astype(np.float32)
  n = len(poses)
  if split_lists is None:
    test = heldout_indices(n, int(data_config.llffhold))
    split_lists = {"train": np.setdiff1d(np.arange(n), test), "val": test, "test": test}
  split_lists = {k: np.asarray(v, np.int64) for k, v in split_lists.items() if len(v)}
  if "train" not in split_lists:
    raise UserError(f"{where}: no frame is left for training; lower the held-out share (data.llffhold) or "
                    f"list training frames.")
  space = data_config.space if data_config.space != "auto" else default_space
  if space == "unbounded":
    near, far = UNBOUNDED_NEAR, UNBOUNDED_FAR
  elif bounds is not None:  # the original LLFF code's bounds without NDC
    near, far = 0.9 * float(bounds.min()), float(bounds.max())
  else:  # cameras within distance ~1 of the centre: a box of a few units holds what they see
    near, far = 0.05, 4.0
  return Framing(transform, poses, bounds, split_lists, space, near, far)


def scaled_cameras(cams: Cameras, widths: np.ndarray, heights: np.ndarray, names: list[str], where: str,
                   downscale) -> Cameras:
  """The cameras of images `widths` x `heights` (image_sizes), shrunk `downscale` times (an int, or one per
  frame) from the cameras' size (an images_N folder, or shrunk on loading): focal lengths and principal
  points scaled by each image's size over its camera's. An image whose size is not its camera's divided by
  the factor (to within a pixel) is refused."""
  w, h = np.asarray(widths, np.int64), np.asarray(heights, np.int64)
  factor = np.broadcast_to(np.asarray(downscale, np.int64), w.shape)
  bad = np.flatnonzero((np.abs(w * factor - cams.width) > factor) | (np.abs(h * factor - cams.height) > factor))
  if bad.size:
    i = int(bad[0])
    shrunk = (f" ({cams.width[i] // factor[i]}x{cams.height[i] // factor[i]} shrunk {factor[i]} times)"
              if factor[i] > 1 else "")
    raise UserError(f"{where}: the image of frame {names[i]!r} is {w[i]}x{h[i]} pixels but its camera is "
                    f"{cams.width[i]}x{cams.height[i]}{shrunk}; use the images the camera model was made for "
                    f"(or the matching data.downscale).")
  sx, sy = w / cams.width, h / cams.height
  return Cameras(w, h, cams.fx * sx, cams.fy * sy, cams.cx * sx, cams.cy * sy, cams.distortion.copy())
