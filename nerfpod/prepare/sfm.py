"""Structure from motion with pycolmap: the camera and matching choices, the image pairs, the SIFT features and
matches in the COLMAP database, the incremental and global mappers, and the choice between their models (the
most images, unless two models disagree on the poses of the images both placed: then the incremental mapper runs
again from other seeds, to confirm the global model or to place more itself).

Every random choice derives from one seed (--seed): pycolmap's own generator, each RANSAC of the geometric
verification, and the mappers' options; the matching and the mappers run on one thread (see seeded_options), so
that the same input and options give the same capture, whatever the thread timing."""
import math
import os
import shutil
import time

import numpy as np

from nerfpod.errors import UserError
from nerfpod.prepare.progress import Progress
from nerfpod.text import duration

MIN_IMAGES = 5                 # fewer cannot make a model worth training on (20+ is a good start)
EXHAUSTIVE_MAX_IMAGES = 300    # exhaustive matching up to this many images (n^2/2 pairs), sequential above
SEQUENTIAL_OVERLAP = 10        # sequential matching: each image with its next 10, and the next 2^k (COLMAP's)
LOOP_IMAGES = 20               # ... and all pairs among 20 evenly spaced images, to close a loop around an object
OTHER_MAPPER_MISSING = 0.05    # --mapper=auto: try the global mapper when incremental leaves more than this out
AGREE_DEGREES, AGREE_CENTRE = 5.0, 0.10  # two mappers' models agree: median orientation, centre differences
CAMERA_MODELS = ("SIMPLE_RADIAL", "OPENCV", "RADIAL", "PINHOLE", "SIMPLE_PINHOLE")  # nerfpod's loaders read all
DEFAULT_SEED = 0               # --seed: every random choice of prepare derives from it
MAX_SEED = 2**31 - 1           # COLMAP's seeds are C ints, and -1 there means "not seeded"
INCREMENTAL_RERUNS = 2         # a global model that disagrees: rerun the incremental mapper from up to 2 other seeds


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


def derived_seed(seed: int, k: int) -> int:
  """The seed of the k-th rerun of a mapper (k = 0: the run itself), from --seed: seed + k, wrapped into
  COLMAP's 0 .. MAX_SEED."""
  return (seed + k) % (MAX_SEED + 1)


def common_stats(per_image: dict | None, names) -> dict | None:
  """A model's mean reprojection error (pixels) and mean track length over its observations in the images
  `names` ({"images", "observations", "reprojection_error_px", "track_length"}), from its per-image figures
  (observation_stats); None where it has none (a hand-made candidate)."""
  if per_image is None:
    return None
  rows = [per_image[n] for n in names if n in per_image]
  count = sum(r["observations"] for r in rows)
  mean = (lambda key: sum(r[key] * r["observations"] for r in rows) / count) if count else (lambda key: None)
  return {"images": len(rows), "observations": count, "reprojection_error_px": mean("error_px"),
          "track_length": mean("track_length")}


def _rank(candidates: list[dict]) -> list[dict]:
  """The most registered images first, then the lower mean reprojection error, then the earlier run."""
  return sorted(candidates, key=lambda c: (-c["registered"], c["reprojection_error"]))


def _checked(glob: dict, run: dict) -> str:
  """Compares an incremental run with the global model on the images both placed: 'agrees', 'disagrees' or
  'unchecked' (fewer than 3 images in common), noting in `run` the agreement and its figures on those images,
  and the global model's on the same images in run["global_on_common_images"]."""
  names = sorted(set(glob["poses"]) & set(run["poses"]))
  run["agreement"] = pose_agreement(glob["poses"], run["poses"])
  run["on_common_images"] = common_stats(run.get("per_image"), names)
  run["global_on_common_images"] = common_stats(glob.get("per_image"), names)
  if run["agreement"]["common"] < 3:
    return "unchecked"
  return "agrees" if agrees(run["agreement"]) else "disagrees"


def choose_model(candidates: list[dict], rerun=None, reruns: int = INCREMENTAL_RERUNS) -> tuple[dict, str, dict]:
  """The best of the mappers' results ({"mapper", "seed", "registered", "reprojection_error", "poses",
  "per_image"?, ...}), a note saying why, and what to record of the choice ({"reason", "reruns": the extra
  incremental runs}). The most registered images win, then the lower mean reprojection error; but a global model
  that places more than an incremental one of MIN_IMAGES or more must agree with it on the images both placed (on
  the shared cup at 800x600 the global mapper placed all 77 images with a low reprojection error and wrong poses;
  see docs/prepare.md). Where it does not, `rerun(k)` (when given) runs the incremental mapper again from its
  k-th derived seed, k = 1 .. `reruns`, until a run agrees with the global model: then the global model (or that
  run, if it placed as many) is kept, two mappers having found the same cameras. Where none agrees, the
  incremental run that placed the most is kept. The reasons: "one mapper", "more images", "agreed", "agreed with
  a rerun", "disagreed", "unchecked" (see docs/prepare.md)."""
  best = _rank(candidates)[0]
  if len(candidates) == 1:
    return best, "", {"reason": "one mapper", "reruns": []}
  other = next(c for c in candidates if c is not best)
  incremental = next((c for c in candidates if c["mapper"] == "incremental"), None)
  if not (best["mapper"] == "global" and incremental is not None and incremental["registered"] >= MIN_IMAGES):
    if other["registered"] < best["registered"]:
      return best, f", which placed more than the {other['mapper']} mapper's {other['registered']}", {
          "reason": "more images", "reruns": []}
    return best, f"; the {other['mapper']} mapper also placed {other['registered']}", {
        "reason": "more images", "reruns": []}
  glob = best
  verdict = _checked(glob, incremental)
  agreement = glob["agreement"] = incremental["agreement"]  # (recorded as the global model's, as it always was)
  glob["on_common_images"] = incremental["global_on_common_images"]
  if verdict == "agrees":
    return glob, (f", which placed more than the {other['mapper']} mapper's {other['registered']} and agreed with "
                  f"it (median {agreement['rotation_deg']:.1f} degrees apart)"), {"reason": "agreed", "reruns": []}
  first = (f"the global mapper placed {glob['registered']} but shares fewer than 3 images with the incremental "
           f"model" if verdict == "unchecked" else
           f"the global mapper placed {glob['registered']} but disagreed with the incremental model on the "
           f"{agreement['common']} images both placed (median {agreement['rotation_deg']:.1f} degrees apart)")
  runs, verdicts = [incremental], [verdict]
  for k in range(1, reruns + 1 if rerun is not None else 1):
    run = rerun(k)
    runs.append(run)
    verdicts.append(_checked(glob, run) if run["registered"] >= MIN_IMAGES else "unchecked")
    if verdicts[-1] == "agrees":
      kept = _rank([glob, run])[0]
      seeds = ", ".join(str(r["seed"]) for r in runs[1:])
      return kept, (f"; {first}, so the incremental mapper ran again (seed {seeds}), and its run from seed "
                    f"{run['seed']} placed {run['registered']} and agreed with the global model (median "
                    f"{run['agreement']['rotation_deg']:.1f} degrees apart)"), {
          "reason": "agreed with a rerun", "reruns": runs[1:]}
  kept = _rank(runs)[0]
  if len(runs) == 1:
    why = "could not be checked and was not used" if verdict == "unchecked" else "was not used"
    return kept, f"; {first}, so its model {why}", {"reason": verdict.replace("disagrees", "disagreed"),
                                                       "reruns": []}
  seeds = ", ".join(str(r["seed"]) for r in runs[1:])
  which = (f"; the run from seed {kept['seed']} placed the most ({kept['registered']})" if kept is not incremental
           else "")
  reason = "disagreed" if "disagrees" in verdicts else "unchecked"
  return kept, (f"; {first}, nor did it agree with the incremental mapper's runs from seed {seeds}, so its model was "
                f"not used{which}"), {"reason": reason, "reruns": runs[1:]}


def mapping_record(best: dict, note: str, choice: dict, tried: list[dict]) -> dict:
  """prepare.json's "mapping": the model kept (its mapper and seed), the note, the reason (choose_model) and
  every run tried, in order, with its seed, counts, seconds, reprojection error and, where it was compared, its
  agreement with the other mapper's model and both models' figures on the images both placed (common_stats)."""
  def clean(value):
    if isinstance(value, float) and (math.isnan(value) or math.isinf(value)):
      return None
    return {k: clean(v) for k, v in value.items()} if isinstance(value, dict) else value

  def entry(r):
    out = {"mapper": r["mapper"], "seed": r.get("seed"), "registered": r["registered"], "models": r.get("models"),
           "other_models_images": r.get("others"), "seconds": round(r.get("seconds", 0.0), 2),
           "reprojection_error_px": clean(r["reprojection_error"])}
    if r.get("rerun"):
      out["rerun"] = True
    if "agreement" in r:
      out["agreement_with_incremental" if r["mapper"] == "global" else "agreement_with_global"] = clean(
          r["agreement"])
      out["on_common_images"] = clean(r.get("on_common_images"))
      if "global_on_common_images" in r:
        out["global_on_common_images"] = clean(r["global_on_common_images"])
    return out
  return {"kept": best["mapper"], "kept_seed": best.get("seed"), "note": note, "reason": choice["reason"],
          "tried": [entry(r) for r in tried]}


def untried_options(tried: list[dict], matching: str) -> list[str]:
  """The flags of a rerun that would try what this run did not: exhaustive matching where it was sequential, the
  other mapper where only one mapper ran (`tried`: the mapper runs, {"mapper", ...} each)."""
  flags = ["--matching=exhaustive"] if matching == "sequential" else []
  if {r["mapper"] for r in tried} in ({"incremental"}, {"global"}):
    flags.append(f"--mapper={'incremental' if tried[0]['mapper'] == 'global' else 'global'}")
  return flags


def too_few_message(registered: int, total: int, needed: int, tried: list[dict], matching: str,
                    work: str) -> str:
  """The sentence for a model with too few images: how many, and what to try that was not tried."""
  placed = ", ".join(f"the {r['mapper']} mapper{' from seed ' + str(r['seed']) if r.get('rerun') else ''} "
                     f"{r['registered']}" for r in tried)
  hints = ["take the photos or film with more overlap (each part of the scene in 3 or more views) and less "
           "motion blur"] + [f"try {flag}" for flag in untried_options(tried, matching)]
  return (f"only {registered} of {total} images could be placed ({placed}), fewer than the {needed} needed "
          f"(--min_registered); {', or '.join(hints)}; a rerun reuses the features and matches kept in {work}.")


# ---------------------------------------------------------------------------------------------------------------
# Stages (pycolmap)


def seeded_options(kind: str, seed: int, threads: int = 1):
  """pycolmap's options for one step, seeded from `seed`, with the threads that keep the step's result
  independent of thread timing (COLMAP 4.2's sources; docs/prepare.md has what it costs):
  - "extraction" (SIFT, --threads): each image's features are computed alone, by one thread; no randomness.
  - "matching": one thread, whatever --threads. The CPU matcher's nearest neighbours come from FLANN's
    randomised k-d trees, whose draws several threads evidently share: on 2 threads, 44 phone photos matched four times
    gave four different match tables (docs/prepare.md); on one, the same every time. (COLMAP's exact
    brute-force matcher is deterministic on any threads, but took 10 times as long there.)
  - its "verification": the RANSAC of each pair's geometric verification draws from COLMAP's generator, one per
    thread, which an unseeded RANSAC (-1) leaves going from one pair to the next; a seed reseeds it at the start
    of every RANSAC, the same for a pair whichever thread takes it. (The RANSAC itself runs on one thread.)
  - "incremental" and "global" mappers: one thread. With several, the incremental mapper looks for its initial
    pair in parallel and keeps the first that a thread finds, runs the RANSAC of structure-less registration on
    several threads that race for the best model, and both mappers' bundle adjustment (Ceres) sums in the order
    its threads finish. The seed goes to the pipeline's random_seed, which COLMAP passes on to the mapper,
    triangulation, RANSAC, rotation averaging and global positioning (set here on each as well)."""
  import pycolmap
  if kind == "extraction":
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = threads
  elif kind == "matching":
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = 1
  elif kind == "verification":
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.random_seed = seed
    options.ransac.num_threads = 1
  elif kind == "incremental":
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 1
    options.random_seed = options.mapper.random_seed = options.triangulation.random_seed = seed
  elif kind == "global":
    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = 1
    options.random_seed = options.mapper.random_seed = seed
    options.mapper.rotation_averaging.random_seed = seed
    options.mapper.global_positioning.random_seed = seed
    options.mapper.retriangulation.random_seed = seed
  else:
    raise ValueError(f"no options for {kind}")
  return options


def stage_features(db_path: str, image_dir: str, names: list[str], cameras: str, camera_model: str,
                   max_image_size: int, threads: int, seed: int = DEFAULT_SEED):
  import pycolmap
  pycolmap.set_random_seed(seed)  # this thread's generator (SIFT draws nothing; nothing is left to chance)
  pycolmap.Database.open(db_path).close()  # creates it
  mode = pycolmap.CameraMode.SINGLE if cameras == "shared" else pycolmap.CameraMode.PER_IMAGE
  reader = pycolmap.ImageReaderOptions()
  reader.camera_model = camera_model
  pycolmap.import_images(db_path, image_dir, mode, names, reader)  # cameras from EXIF where it has a focal length
  extraction = seeded_options("extraction", seed, threads)
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


def stage_matching(db_path: str, work: str, names: list[str], pairs: list[tuple[int, int]],
                   seed: int = DEFAULT_SEED):
  import pycolmap
  ids = _count(db_path, lambda db: {im.name: im.image_id for im in db.read_all_images()})
  todo = _count(db_path, lambda db: [(i, j) for i, j in pairs
                                     if not db.exists_two_view_geometry(ids[names[i]], ids[names[j]])])
  options = seeded_options("matching", seed)  # (one thread: seeded_options says why)
  verification = seeded_options("verification", seed)
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
    pycolmap.set_random_seed(seed)
    pycolmap.match_image_pairs(db_path, matching_options=options, pairing_options=pairing,
                               verification_options=verification)
    done += len(todo[start:start + batch])
    progress.update(done)
  verified = _count(db_path, lambda db: len(db.read_two_view_geometry_num_inliers()[0]))
  print(f"  {verified} of {len(pairs)} pairs verified (15 or more matches consistent with one relative pose)",
        flush=True)
  return {"pairs": len(pairs), "verified_pairs": verified}


def run_mapper(mapper: str, db_path: str, image_dir: str, out_dir: str, num_images: int,
               seed: int = DEFAULT_SEED) -> dict:
  """One mapper's models, from `seed`, on one thread (seeded_options): {"mapper", "seed",
  "registered", "reprojection_error", "models", "others", "seconds", "reconstruction", "poses"} with the largest
  model's figures."""
  import pycolmap
  if os.path.isdir(out_dir):
    shutil.rmtree(out_dir)
  os.makedirs(out_dir)
  start = time.monotonic()
  options = seeded_options(mapper, seed)
  options.min_model_size = 3
  pycolmap.set_random_seed(seed)  # the calling thread's generator, as another run in this process may have left it
  if mapper == "incremental":
    progress = Progress("incremental mapper", num_images, "images placed")
    placed = [2]  # the initial pair, then one per callback

    def next_image():
      placed[0] += 1
      progress.update(min(placed[0], num_images))
    models = pycolmap.incremental_mapping(db_path, image_dir, out_dir, options, next_image_callback=next_image)
  else:
    models = pycolmap.global_mapping(db_path, image_dir, out_dir, options)
  seconds = time.monotonic() - start
  models = sorted(models.values(), key=lambda r: -r.num_reg_images())
  label = f"{mapper} mapper" + (f" (seed {seed})" if seed != DEFAULT_SEED else "")
  if not models:
    print(f"  {label}: no model ({duration(seconds)})", flush=True)
    return {"mapper": mapper, "seed": seed, "registered": 0, "reprojection_error": math.inf, "models": 0,
            "others": 0, "seconds": seconds, "reconstruction": None, "poses": {}}
  best = models[0]
  placed = {im.name for im in best.images.values() if im.has_pose}
  elsewhere = {im.name for r in models[1:] for im in r.images.values() if im.has_pose} - placed
  result = {"mapper": mapper, "seed": seed, "registered": int(best.num_reg_images()),
            "reprojection_error": float(best.compute_mean_reprojection_error()), "models": len(models),
            "others": len(elsewhere), "seconds": seconds, "reconstruction": best, "poses": camera_poses(best)}
  others = (f"; {len(models) - 1} smaller model(s) held {len(elsewhere)} images it lacks" if elsewhere else "")
  print(f"  {label}: {result['registered']} of {num_images} images placed in {duration(seconds)}{others}",
        flush=True)
  return result


def stage_mapping(db_path: str, work: str, image_dir: str, num_images: int, mapper: str,
                  seed: int = DEFAULT_SEED):
  """(the kept result, its note, what to record of the choice, every result): --mapper=auto runs the incremental
  mapper, and the global one too where the incremental one leaves over OTHER_MAPPER_MISSING of the images out;
  choose_model decides, running the incremental mapper again from other seeds where the two disagree."""
  first = "incremental" if mapper == "auto" else mapper
  tried = [run_mapper(first, db_path, image_dir, os.path.join(work, f"sparse_{first}"), num_images, seed)]
  if mapper == "auto" and tried[0]["registered"] < (1 - OTHER_MAPPER_MISSING) * num_images:
    print(f"  it left {num_images - tried[0]['registered']} of {num_images} images out: trying the global mapper "
          f"on the same matches", flush=True)
    tried.append(run_mapper("global", db_path, image_dir, os.path.join(work, "sparse_global"), num_images, seed))
    for result in tried:  # what choose_model records of the models on the images both placed
      result["per_image"] = observation_stats(result["reconstruction"])

  def rerun(k):
    again = derived_seed(seed, k)
    print(f"  the incremental model does not confirm the global one: running the incremental mapper again from "
          f"seed {again}", flush=True)
    result = run_mapper("incremental", db_path, image_dir, os.path.join(work, f"sparse_incremental_{k}"),
                        num_images, again)
    result["rerun"] = True
    result["per_image"] = observation_stats(result["reconstruction"])
    return result
  best, note, choice = choose_model(tried, rerun)
  tried += choice["reruns"]
  if len(tried) > 1:
    print(f"  kept the {best['mapper']} mapper's model{note}", flush=True)
  return best, note, choice, tried


def observation_stats(rec) -> dict:
  """{image name: {"observations", "error_px", "track_length"}} of a Reconstruction's registered images (none
  for no model): how many of its keypoints have a 3D point, their mean reprojection error (pixels) and the mean
  track length of those points; what choose_model records of two models on the images both placed."""
  stats = {}
  if rec is None:
    return stats
  for im in rec.images.values():
    if not im.has_pose:
      continue
    observed = im.get_observation_points2D()
    if len(observed) == 0:
      stats[im.name] = {"observations": 0, "error_px": 0.0, "track_length": 0.0}
      continue
    points = [rec.points3D[p.point3D_id] for p in observed]
    xyz = np.array([p.xyz for p in points], np.float64)
    m = np.asarray(im.cam_from_world().matrix(), np.float64)
    projected = rec.cameras[im.camera_id].img_from_cam(xyz @ m[:, :3].T + m[:, 3], check_cheirality=False)
    error = np.linalg.norm(np.asarray(projected) - np.array([p.xy for p in observed], np.float64), axis=1)
    stats[im.name] = {"observations": len(points), "error_px": float(np.mean(error)),
                      "track_length": float(np.mean([p.track.length() for p in points]))}
  return stats


def camera_poses(rec) -> dict:
  """{image name: 4x4 camera-to-world (OpenCV axes)} of a Reconstruction's registered images."""
  poses = {}
  for im in rec.images.values():
    if im.has_pose:
      w2c = np.concatenate([np.asarray(im.cam_from_world().matrix(), np.float64), [[0.0, 0.0, 0.0, 1.0]]])
      poses[im.name] = np.linalg.inv(w2c)
  return poses


def clear_matches(db_path: str) -> None:
  """Removes the matches and the verified pairs from the COLMAP database at `db_path`; its images and features
  stay (matching again with other settings reuses them)."""
  _count(db_path, lambda db: (db.clear_matches(), db.clear_two_view_geometries()))


def _count(db_path: str, fn):
  import pycolmap
  db = pycolmap.Database.open(db_path)
  try:
    return fn(db)
  finally:
    db.close()
