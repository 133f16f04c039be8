"""Structure from motion with pycolmap: the camera and matching choices, the image pairs, the SIFT features and
matches in the COLMAP database, the incremental and global mappers, and the choice between their models (the
most images, unless two models disagree on the poses of the images both placed)."""
import math
import os
import shutil
import time

import numpy as np

from nerfpod.errors import UserError
from nerfpod.prepare.progress import Progress, duration

MIN_IMAGES = 5                 # fewer cannot make a model worth training on (20+ is a good start)
EXHAUSTIVE_MAX_IMAGES = 300    # exhaustive matching up to this many images (n^2/2 pairs), sequential above
SEQUENTIAL_OVERLAP = 10        # sequential matching: each image with its next 10, and the next 2^k (COLMAP's)
LOOP_IMAGES = 20               # ... and all pairs among 20 evenly spaced images, to close a loop around an object
OTHER_MAPPER_MISSING = 0.05    # --mapper=auto: try the global mapper when incremental leaves more than this out
AGREE_DEGREES, AGREE_CENTRE = 5.0, 0.10  # two mappers' models agree: median orientation, centre differences
CAMERA_MODELS = ("SIMPLE_RADIAL", "OPENCV", "RADIAL", "PINHOLE", "SIMPLE_PINHOLE")  # nerfpod's loaders read all


# ---------------------------------------------------------------------------------------------------------------
# Choices, pairs and models (pure)


def choose_cameras(kind: str, sizes: list[tuple[int, int]], makers: list, forced: str = "auto") -> str:
  """'shared' (one camera for all images) or 'per_image': shared for a video, and for photos of one size from
  one camera (EXIF make and model, or none at all); --cameras forces it. Forcing one camera on images of
  several sizes is refused."""
  distinct = sorted(set(sizes))
  if forced == "shared":
    if len(distinct) > 1:
      shown = ", ".join(f"{w}x{h}" for w, h in distinct[:4]) + (" ..." if len(distinct) > 4 else "")
      raise UserError(f"--cameras=shared needs images of one size, but these have {len(distinct)} sizes "
                      f"({shown}); leave --cameras=auto (one camera per image) or resize them to one size.")
    return "shared"
  if forced == "per_image":
    return "per_image"
  if kind == "video":
    return "shared"
  return "shared" if len(distinct) == 1 and len(set(makers)) == 1 else "per_image"


def choose_camera_model(forced: str = "auto") -> str:
  """COLMAP camera model, shared or per image: SIMPLE_RADIAL (one focal length, one radial distortion term)
  unless forced: on the shared test captures it gave poses as good as or better than OPENCV's eight parameters,
  which small or few images cannot pin down (docs/prepare.md); OPENCV suits wide-angle lenses."""
  return "SIMPLE_RADIAL" if forced == "auto" else forced


def choose_matching(kind: str, num_images: int, forced: str = "auto") -> str:
  """'sequential' for a video's frames and for more than EXHAUSTIVE_MAX_IMAGES photos (taken in name order),
  else 'exhaustive'; --matching forces it."""
  if forced != "auto":
    return forced
  return "sequential" if kind == "video" or num_images > EXHAUSTIVE_MAX_IMAGES else "exhaustive"


def image_pairs(n: int, matching: str, overlap: int = SEQUENTIAL_OVERLAP,
                loop_images: int = LOOP_IMAGES) -> list[tuple[int, int]]:
  """The pairs (i < j) of n images (in time or name order) to match. Exhaustive: all n (n - 1) / 2.
  Sequential: each image with its next `overlap` and the ones 2^k after it (k < overlap, COLMAP's quadratic
  overlap), plus all pairs among `loop_images` evenly spaced images, which close a loop around an object."""
  if matching == "exhaustive":
    return [(i, j) for i in range(n) for j in range(i + 1, n)]
  pairs = set()
  for i in range(n):
    for d in list(range(1, overlap + 1)) + [2**k for k in range(overlap)]:
      if i + d < n:
        pairs.add((i, i + d))
  keys = np.unique(np.round(np.linspace(0, n - 1, min(n, loop_images))).astype(int)) if n else []
  pairs.update((int(a), int(b)) for a in keys for b in keys if a < b)
  return sorted(pairs)


def similarity(src_Nx3: np.ndarray, dst_Nx3: np.ndarray, src_rot_Nx3x3=None, dst_rot_Nx3x3=None,
               ) -> tuple[float, np.ndarray, np.ndarray]:
  """The similarity (s, R, t) minimising sum |s R src + t - dst|^2 (Umeyama 1991). With orientations
  (camera-to-world rotations of the same N cameras), R also minimises sum |R src_rot - dst_rot|^2 (the chordal
  distance), the centres' term in units of their spreads so that both weigh alike: where the centres lie near
  a line or a plane and leave R loose about it, the orientations fix it."""
  ms, md = src_Nx3.mean(0), dst_Nx3.mean(0)
  x, y = src_Nx3 - ms, dst_Nx3 - md
  var = (x**2).sum(1).mean()
  covariance = y.T @ x / len(x)
  if src_rot_Nx3x3 is not None:
    spreads = np.sqrt(var * (y**2).sum(1).mean())
    covariance = covariance / (spreads if spreads > 0 else 1.0) + np.mean(dst_rot_Nx3x3 @ np.swapaxes(
        src_rot_Nx3x3, -1, -2), axis=0)
  u, _, vt = np.linalg.svd(covariance)
  d = np.eye(3)
  d[2, 2] = 1.0 if np.linalg.det(u @ vt) >= 0 else -1.0
  r = u @ d @ vt
  s = float(np.sum(y * (x @ r.T)) / len(x) / var) if var > 0 else 1.0
  return s, r, md - s * r @ ms


def pose_agreement(a: dict, b: dict) -> dict:
  """How two models' cameras ({name: 4x4 camera-to-world}) agree on the images both have, after the similarity
  that best aligns a's camera centres and orientations to b's (`similarity` with both): {"common",
  "rotation_deg" (median angle between the orientations), "centre" (median centre distance over b's mean
  distance of cameras from their centroid)}. The centres alone fix the rotation poorly where the cameras lie
  near a line (a straight walk) or a plane: a little noise in them would turn every orientation of a model
  that agrees away from the other's."""
  names = sorted(set(a) & set(b))
  if len(names) < 3:
    return {"common": len(names), "rotation_deg": math.nan, "centre": math.nan}
  pa = np.array([a[n][:3, 3] for n in names])
  pb = np.array([b[n][:3, 3] for n in names])
  s, r, t = similarity(pa, pb, np.array([a[n][:3, :3] for n in names]), np.array([b[n][:3, :3] for n in names]))
  spread = np.linalg.norm(pb - pb.mean(0), axis=1).mean()
  centre = np.linalg.norm((s * (r @ pa.T)).T + t - pb, axis=1) / (spread if spread > 0 else 1.0)
  cos = [(np.trace((r @ a[n][:3, :3]).T @ b[n][:3, :3]) - 1) / 2 for n in names]
  rotation = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
  return {"common": len(names), "rotation_deg": float(np.median(rotation)), "centre": float(np.median(centre))}


def agrees(agreement: dict) -> bool:
  """Two models agree when, on the images both placed, the median orientation differs by under 5 degrees and the
  median camera centre by under 10% of the cameras' spread."""
  return agreement["rotation_deg"] < AGREE_DEGREES and agreement["centre"] < AGREE_CENTRE


def choose_model(candidates: list[dict]) -> tuple[dict, str]:
  """The best of the mappers' results ({"mapper", "registered", "reprojection_error", "poses", ...}) and a note
  saying why: the most registered images, then the lower mean reprojection error; but a global model that
  disagrees with the incremental one on the images both placed is not trusted over it (on the shared cup at
  800x600 the global mapper placed all 77 images with a low reprojection error and wrong poses; see
  docs/prepare.md). An incremental model with fewer than MIN_IMAGES images cannot check anything."""
  best = min(candidates, key=lambda c: (-c["registered"], c["reprojection_error"]))
  if len(candidates) == 1:
    return best, ""
  other = next(c for c in candidates if c is not best)
  incremental = next((c for c in candidates if c["mapper"] == "incremental"), None)
  if best["mapper"] == "global" and incremental is not None and incremental["registered"] >= MIN_IMAGES:
    agreement = pose_agreement(best["poses"], incremental["poses"])
    best["agreement"] = agreement
    if agreement["common"] < 3:
      return incremental, (f"; the global mapper placed {best['registered']} but shares fewer than 3 images with "
                           f"it, so its model could not be checked and was not used")
    if not agrees(agreement):
      return incremental, (f"; the global mapper placed {best['registered']} but disagreed with it on the "
                           f"{agreement['common']} images both placed (median {agreement['rotation_deg']:.1f} "
                           f"degrees apart), so its model was not used")
    return best, (f", which placed more than the {other['mapper']} mapper's {other['registered']} and agreed with "
                  f"it (median {agreement['rotation_deg']:.1f} degrees apart)")
  if other["registered"] < best["registered"]:
    return best, f", which placed more than the {other['mapper']} mapper's {other['registered']}"
  return best, f"; the {other['mapper']} mapper also placed {other['registered']}"


def too_few_message(registered: int, total: int, needed: int, tried: list[dict], matching: str,
                    work: str) -> str:
  """The sentence for a model with too few images: how many, and what to try that was not tried."""
  placed = ", ".join(f"the {r['mapper']} mapper {r['registered']}" for r in tried)
  hints = ["take the photos or film with more overlap (each part of the scene in 3 or more views) and less "
           "motion blur"]
  if matching == "sequential":
    hints.append("try --matching=exhaustive")
  if len(tried) == 1:
    hints.append(f"try --mapper={'incremental' if tried[0]['mapper'] == 'global' else 'global'}")
  return (f"only {registered} of {total} images could be placed ({placed}), fewer than the {needed} needed "
          f"(--min_registered); {', or '.join(hints)}; a rerun reuses the features and matches kept in {work}.")


# ---------------------------------------------------------------------------------------------------------------
# Stages (pycolmap)


def stage_features(db_path: str, image_dir: str, names: list[str], cameras: str, camera_model: str,
                   max_image_size: int, threads: int):
  import pycolmap
  pycolmap.Database.open(db_path).close()  # creates it
  mode = pycolmap.CameraMode.SINGLE if cameras == "shared" else pycolmap.CameraMode.PER_IMAGE
  reader = pycolmap.ImageReaderOptions()
  reader.camera_model = camera_model
  pycolmap.import_images(db_path, image_dir, mode, names, reader)  # cameras from EXIF where it has a focal length
  extraction = pycolmap.FeatureExtractionOptions()
  extraction.num_threads = threads
  extraction.max_image_size = max_image_size
  have = _count(db_path, lambda db: {im.name for im in db.read_all_images() if db.exists_keypoints(im.image_id)})
  todo = [n for n in names if n not in have]
  if have:
    print(f"  {len(names) - len(todo)} of {len(names)} images have their features from an earlier run", flush=True)
  progress = Progress("features", len(names), "images", already=len(names) - len(todo))
  batch = max(4 * threads, math.ceil(len(todo) / 20))
  for start in range(0, len(todo), batch):  # in batches, for the progress line
    pycolmap.extract_features(db_path, image_dir, image_names=todo[start:start + batch], camera_mode=mode,
                              reader_options=reader, extraction_options=extraction)
    progress.update(len(names) - len(todo) + min(len(todo), start + batch))
  keypoints = _count(db_path, lambda db: db.num_keypoints())
  print(f"  {keypoints:,} features in {len(names)} images ({keypoints / max(1, len(names)):.0f} per image)",
        flush=True)
  return {"features": keypoints}


def stage_matching(db_path: str, work: str, names: list[str], pairs: list[tuple[int, int]], threads: int):
  import pycolmap
  ids = _count(db_path, lambda db: {im.name: im.image_id for im in db.read_all_images()})
  todo = _count(db_path, lambda db: [(i, j) for i, j in pairs
                                     if not db.exists_two_view_geometry(ids[names[i]], ids[names[j]])])
  options = pycolmap.FeatureMatchingOptions()
  options.num_threads = threads
  done = len(pairs) - len(todo)
  progress = Progress("matching", len(pairs), "pairs", already=done)
  if done:
    print(f"  {done} of {len(pairs)} pairs were matched by an earlier run", flush=True)
  batch = max(50, math.ceil(len(todo) / 20))
  pairs_file = os.path.join(work, "pairs.txt")
  for start in range(0, len(todo), batch):
    with open(pairs_file, "w") as f:
      f.writelines(f"{names[i]} {names[j]}\n" for i, j in todo[start:start + batch])
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pairs_file
    pycolmap.match_image_pairs(db_path, matching_options=options, pairing_options=pairing)
    done += len(todo[start:start + batch])
    progress.update(done)
  verified = _count(db_path, lambda db: len(db.read_two_view_geometry_num_inliers()[0]))
  print(f"  {verified} of {len(pairs)} pairs verified (15 or more matches consistent with one relative pose)",
        flush=True)
  return {"pairs": len(pairs), "verified_pairs": verified}


def run_mapper(mapper: str, db_path: str, image_dir: str, out_dir: str, num_images: int, threads: int) -> dict:
  """One mapper's models: {"mapper", "registered", "reprojection_error", "models", "others", "seconds",
  "reconstruction"} with the largest model's figures."""
  import pycolmap
  if os.path.isdir(out_dir):
    shutil.rmtree(out_dir)
  os.makedirs(out_dir)
  start = time.monotonic()
  if mapper == "incremental":
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.min_model_size = 3
    options.random_seed = 0
    progress = Progress("incremental mapper", num_images, "images placed")
    placed = [2]  # the initial pair, then one per callback

    def next_image():
      placed[0] += 1
      progress.update(min(placed[0], num_images))
    models = pycolmap.incremental_mapping(db_path, image_dir, out_dir, options, next_image_callback=next_image)
  else:
    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = threads
    options.min_model_size = 3
    options.random_seed = 0
    models = pycolmap.global_mapping(db_path, image_dir, out_dir, options)
  seconds = time.monotonic() - start
  models = sorted(models.values(), key=lambda r: -r.num_reg_images())
  if not models:
    print(f"  {mapper} mapper: no model ({duration(seconds)})", flush=True)
    return {"mapper": mapper, "registered": 0, "reprojection_error": math.inf, "models": 0, "others": 0,
            "seconds": seconds, "reconstruction": None, "poses": {}}
  best = models[0]
  placed = {im.name for im in best.images.values() if im.has_pose}
  elsewhere = {im.name for r in models[1:] for im in r.images.values() if im.has_pose} - placed
  result = {"mapper": mapper, "registered": int(best.num_reg_images()),
            "reprojection_error": float(best.compute_mean_reprojection_error()), "models": len(models),
            "others": len(elsewhere), "seconds": seconds, "reconstruction": best, "poses": camera_poses(best)}
  others = (f"; {len(models) - 1} smaller model(s) held {len(elsewhere)} images it lacks" if elsewhere else "")
  print(f"  {mapper} mapper: {result['registered']} of {num_images} images placed in {duration(seconds)}"
        f"{others}", flush=True)
  return result


def stage_mapping(db_path: str, work: str, image_dir: str, num_images: int, mapper: str, threads: int):
  """(the kept result, its note, every result): --mapper=auto runs the incremental mapper, and the global one
  too where the incremental one leaves over OTHER_MAPPER_MISSING of the images out (choose_model decides)."""
  first = "incremental" if mapper == "auto" else mapper
  tried = [run_mapper(first, db_path, image_dir, os.path.join(work, f"sparse_{first}"), num_images, threads)]
  if mapper == "auto" and tried[0]["registered"] < (1 - OTHER_MAPPER_MISSING) * num_images:
    print(f"  it left {num_images - tried[0]['registered']} of {num_images} images out: trying the global mapper "
          f"on the same matches", flush=True)
    tried.append(run_mapper("global", db_path, image_dir, os.path.join(work, "sparse_global"), num_images,
                            threads))
  best, note = choose_model(tried)
  if len(tried) > 1:
    print(f"  kept the {best['mapper']} mapper's model{note}", flush=True)
  return best, note, tried


def camera_poses(rec) -> dict:
  """{image name: 4x4 camera-to-world (OpenCV axes)} of a Reconstruction's registered images."""
  poses = {}
  for im in rec.images.values():
    if im.has_pose:
      w2c = np.concatenate([np.asarray(im.cam_from_world().matrix(), np.float64), [[0.0, 0.0, 0.0, 1.0]]])
      poses[im.name] = np.linalg.inv(w2c)
  return poses


def _count(db_path: str, fn):
  import pycolmap
  db = pycolmap.Database.open(db_path)
  try:
    return fn(db)
  finally:
    db.close()
