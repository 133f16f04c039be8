"""`nerfpod prepare --input=PHOTOS_OR_VIDEO --out=DIR`: photos or a video -> a capture folder with camera poses.

Structure from motion with COLMAP's CPU pipeline as the `pycolmap` package ships it (the `colmap` extra):
SIFT features, matching with geometric verification, then COLMAP's incremental mapper or the global one
(GLOMAP's). The stages, in a work folder `DIR.partial/` beside DIR:

    images    a video's frames (the sharpest of each of --num_frames even windows in time), or the photos
              (hard links, copies, or upright copies where EXIF says the photo is rotated)
    features  SIFT per image into database.db (one shared camera for one camera, else one per image)
    matching  exhaustive, or sequential (neighbours in time + loop pairs among evenly spaced frames)
    mapping   the incremental mapper; where it leaves over 5% of the images out, also the global one on the
              same matches, keeping the model with more images (on a tie, the lower reprojection error) unless
              the global model disagrees with the incremental one on the images both placed: then the
              incremental mapper runs again from other seeds, to confirm the global model or place more
    writing   DIR/images/ (the registered images), sparse/0/, images_2/4/8 for large images,
              poses_bounds.npy (LLFF), transforms.json (nerfstudio), prepare.json

Every random choice derives from --seed, and the mappers run on one thread: the same input, options and seed
give the same capture (docs/prepare.md says what may still differ from one machine to another). When everything
is written the work folder's capture is renamed to DIR, so DIR is never half-written. An interrupted run leaves
DIR.partial/: the same command again reuses its finished stages (the frames, the features and matches in the
COLMAP database); --overwrite starts again. A user's mistake is one sentence on stderr and exit code 2.
Measurements and every message: docs/prepare.md.

Here: the command (its absl flags, read as every subcommand reads them: errors.parse_flags; the stages in
order, resuming them, the report). The stages' work is in
frames (the input: photos, a video's frames), sfm (pycolmap: features, matching, mapping, the model kept)
and capture (the capture folder's files); progress prints the progress lines.
"""
import json
import math
import os
import shutil
import sys
import time
import types

from absl import flags

from nerfpod.errors import Command, UserError
from nerfpod.prepare import capture, frames, sfm
from nerfpod.text import duration

STATE = "state.json"


def report(summary: dict) -> list[str]:
  """The final report's lines, from prepare.json's content."""
  c, out = summary["counts"], summary["out"]
  mapping = summary["mapping"]
  lines = [f"registered {c['registered']} of {c['images']} images"
           f" ({mapping['kept']} mapper{mapping['note']}); {c['points']:,} points, mean reprojection error "
           f"{c['reprojection_error_px']:.2f} px, mean track length {c['track_length']:.1f}"]
  times = ", ".join(f"{k} {duration(v)}" for k, v in summary["timings_s"].items())
  lines.append(f"time: {times}")
  written = ["images/", "sparse/0/"] + [f"images_{n}/" for n in summary["downscales"]] + [
      "poses_bounds.npy", "transforms.json", capture.PREPARE_JSON]
  lines.append(f"wrote {out}: {', '.join(written)}")
  quoted = out if " " not in out else f"'{out}'"
  name = os.path.basename(os.path.normpath(out)) or "capture"
  if summary["forward_facing"]:
    lines.append("the cameras all look one way (a forward-facing capture): train with")
    lines.append(f"  nerfpod train --config=configs/llff.py --config.data.path={quoted} --workdir=runs/{name}")
  else:
    lines.append("next: train on it with")
    lines.append(f"  nerfpod train --config=configs/capture.py:path={quoted} --workdir=runs/{name}")
  return lines


WELL_PLACED = 0.9  # a capture with fewer of its photos registered ends with a sentence naming those left out


def left_out_warning(summary: dict) -> str | None:
  """One sentence where fewer than WELL_PLACED of the photos were registered: which were left out, and what to
  try (another seed, and what the run did not try: sfm.untried_options); None otherwise."""
  c, options = summary["counts"], summary["options"]
  if c["registered"] >= WELL_PLACED * c["images"]:
    return None
  names = c["unregistered"]
  shown = ", ".join(names[:10]) + (f" and {len(names) - 10} more" if len(names) > 10 else "")
  hints = [f"--seed={options['seed'] + 1}", *sfm.untried_options(summary["mapping"]["tried"], options["matching"])]
  return (f"nerfpod: warning: only {c['registered']} of {c['images']} photos were placed (under "
          f"{WELL_PLACED:.0%}); left out: {shown}; try {', '.join(hints)} with --overwrite (or another --out), "
          f"or photos with more overlap of those parts of the scene.")


def _threads() -> int:
  try:
    return len(os.sched_getaffinity(0))
  except AttributeError:
    return os.cpu_count() or 1


ABOUT = "photos or a video -> a posed capture folder (COLMAP structure from motion)"
FLAGS = flags.FlagValues()  # its own: other subcommands define --out too
flags.DEFINE_string("input", None, "A folder of photos (.jpg, .jpeg, .png) or a video file (.mp4, .mov, ... anything "
                    "ffmpeg reads).", flag_values=FLAGS)
flags.DEFINE_string("out", None, "The capture folder to write (it must not exist, be empty, or hold an earlier "
                    "prepare's capture, replaced with --overwrite).", flag_values=FLAGS)
flags.DEFINE_integer("num_frames", frames.DEFAULT_NUM_FRAMES, "Video: how many frames to take, the sharpest of "
                     "each even window in time.", lower_bound=1, flag_values=FLAGS)
flags.DEFINE_enum("matching", "auto", ["auto", "exhaustive", "sequential"], "Which image pairs to match: auto = "
                  f"sequential for a video or over {sfm.EXHAUSTIVE_MAX_IMAGES} photos, else exhaustive.",
                  flag_values=FLAGS)
flags.DEFINE_enum("mapper", "auto", ["auto", "incremental", "global"], "auto = the incremental mapper, and the "
                  "global one too where it leaves over 5% of the images out, keeping the model with more images "
                  "unless the two disagree.", flag_values=FLAGS)
flags.DEFINE_enum("cameras", "auto", ["auto", "shared", "per_image"], "One camera for all images or one per image: "
                  "auto = shared for a video and for photos of one size from one camera (EXIF).", flag_values=FLAGS)
flags.DEFINE_enum("camera_model", "auto", ["auto", *sfm.CAMERA_MODELS], "COLMAP camera model: auto = "
                  "SIMPLE_RADIAL; OPENCV for wide-angle lenses.", flag_values=FLAGS)
flags.DEFINE_integer("max_image_size", 1600, "SIFT runs on images shrunk to this long side, in pixels.",
                     lower_bound=1, flag_values=FLAGS)
flags.DEFINE_float("min_registered", 0.5, "Fail unless at least this share of the images is registered.",
                   lower_bound=0.0, upper_bound=1.0, flag_values=FLAGS)
flags.DEFINE_integer("threads", _threads(), "CPU threads for SIFT and matching (default: this machine's cores); "
                     "the mappers run on one thread, for the same capture every run.", lower_bound=1,
                     flag_values=FLAGS)
flags.DEFINE_integer("seed", sfm.DEFAULT_SEED, "Every random choice (RANSAC, the mappers) derives from it: the same "
                     "photos, options and seed give the same capture.", lower_bound=0, upper_bound=sfm.MAX_SEED,
                     flag_values=FLAGS)
flags.DEFINE_bool("overwrite", False, "Start again: replace an earlier prepare's capture at --out and its "
                  "unfinished work.", flag_values=FLAGS)
flags.DEFINE_bool("skip_bad_images", False, "Photos: leave out those that are damaged (truncated, or not "
                  "decoding), with a warning naming them, rather than stopping.", flag_values=FLAGS)
flags.DEFINE_bool("verbose", False, "Show COLMAP's own log.", flag_values=FLAGS)


def _after_ctrl_c() -> str:
  """What Ctrl-C's sentence adds: the same command resumes from the finished stages (once --out is read)."""
  if not FLAGS.is_parsed():
    return ""
  return (f"the same command resumes from the finished stages in {os.path.normpath(FLAGS.out)}.partial "
          f"(--overwrite starts again)")


COMMAND = Command("nerfpod prepare", ABOUT, FLAGS, required=("input", "out"),
                  examples={"input": "my_photos/", "out": "captures/mine"}, after_ctrl_c=_after_ctrl_c)


def _probe(folder: str):
  """Makes `folder` (and the folders above it that are missing), writes and removes a file in it, then removes
  the folders it made: OSError where this user cannot write there; nothing is left either way."""
  missing, up = [], os.path.abspath(folder)
  while not os.path.exists(up):
    missing.append(up)
    up = os.path.dirname(up)
  try:
    os.makedirs(folder, exist_ok=True)
    probe = os.path.join(folder, f".nerfpod-prepare-probe-{os.getpid()}")
    with open(probe, "w"):
      pass
    os.remove(probe)
  finally:
    for made in missing:  # deepest first
      try:
        os.rmdir(made)
      except OSError:
        break


def _check_out(out: str, overwrite: bool, input_path: str):
  """Refuses an --out that is not ours to write, before any work: its folder is probed (_probe), as the work
  folder DIR.partial and DIR itself are made there."""
  if os.path.abspath(out) == os.path.abspath(input_path):
    raise UserError(f"--out {out} is the input itself; pass a new folder for the capture, e.g. "
                    f"--out={out}_capture.")
  if os.path.isfile(out):
    raise UserError(f"--out {out} is a file; pass a folder path for the capture (it is created).")
  if os.path.isdir(out) and os.listdir(out):
    if not os.path.isfile(os.path.join(out, capture.PREPARE_JSON)):
      raise UserError(f"--out {out} already holds other files (it has no {capture.PREPARE_JSON}, so it is not a "
                      f"capture prepare wrote); pass a new or empty folder.")
    if not overwrite:
      raise UserError(f"--out {out} already holds a prepared capture; pass --overwrite to prepare it again, or "
                      f"choose another --out.")
  parent = os.path.dirname(os.path.abspath(out))
  above = parent
  while not os.path.exists(above):
    above = os.path.dirname(above)
  if not os.path.isdir(above):
    raise UserError(f"--out {out} is inside {above}, which is a file, not a folder; pass a folder path for the "
                    f"capture (it is created).")
  try:
    _probe(parent)
  except OSError as e:
    raise UserError(f"--out {out} cannot be written ({e.strerror or e}); pass a folder path this user may "
                    f"write.") from None


def _load_state(work: str) -> dict:
  try:
    with open(os.path.join(work, STATE)) as f:
      state = json.load(f)
    return state if isinstance(state, dict) else {}
  except (OSError, ValueError):
    return {}


def prepare(args) -> dict:
  """The whole command: returns prepare.json's content."""
  t0 = time.monotonic()
  src = frames.scan_input(args.input)
  out = os.path.normpath(args.out)
  _check_out(out, args.overwrite, args.input)
  if src.kind == "photos":  # every photo decoded before the long stages; a damaged one named now
    warning = frames.check_photos(src, args.skip_bad_images, args.threads)
    if warning:
      print(f"nerfpod: warning: {warning}", file=sys.stderr, flush=True)
  try:
    import pycolmap
  except ImportError as e:
    raise UserError("nerfpod prepare needs the pycolmap package: pip install 'nerfpod[colmap]' (or pip install "
                    "pycolmap).") from e
  if not args.verbose:
    pycolmap.logging.minloglevel = 3  # COLMAP logs every step at INFO; what goes wrong, prepare says itself
  sizes = src.sizes if src.kind == "photos" else [(src.video["width"], src.video["height"])]
  cameras = sfm.choose_cameras(src.kind, sizes, src.makers or [None], args.cameras)
  camera_model = sfm.choose_camera_model(args.camera_model)
  work = out + ".partial"
  if args.overwrite and os.path.isdir(work):
    shutil.rmtree(work)
  os.makedirs(work, exist_ok=True)
  state = _load_state(work)
  signature = src.signature()
  if state and state.get("input") != signature:
    print(f"nerfpod prepare: {work} holds an earlier run for other input; starting again", flush=True)
    shutil.rmtree(work)
    os.makedirs(work)
    state = {}
  state["input"] = signature
  stages = state.setdefault("stages", {})
  image_dir, db_path = os.path.join(work, "images"), os.path.join(work, "database.db")
  timings, counts = {}, {}
  what = (f"{len(src.files)} photos in {src.path}" if src.kind == "photos" else
          f"video {src.path} ({src.video['frames']} frames, {src.video['width']}x{src.video['height']}, "
          f"{src.video['duration_s']:.1f} s)")
  print(f"nerfpod prepare: {what} -> {out} ({args.threads} threads, seed {args.seed}; work in {work})", flush=True)

  def save_state():
    capture._write_json(os.path.join(work, STATE), state)

  # 1. images
  key = {"num_frames": args.num_frames} if src.kind == "video" else {}
  t = time.monotonic()
  if stages.get("images", {}).get("key") == key and os.path.isdir(image_dir):
    names, info = stages["images"]["names"], stages["images"]["info"]
    print(f"[1/5] {'frames' if src.kind == 'video' else 'images'}: {len(names)} reused from the earlier run",
          flush=True)
  else:
    windows = len(frames.frame_windows(src.video["frames"], args.num_frames)) - 1 if src.kind == "video" else 0
    print("[1/5] " + (f"frames: the sharpest of each of {windows} even windows in time" if src.kind == "video"
                      else f"images: linking {len(src.files)} photos"), flush=True)
    for later in ("images", "features", "matching"):
      stages.pop(later, None)
    if os.path.exists(db_path):
      os.remove(db_path)
    try:
      names, info = frames.stage_images(src, image_dir, args.num_frames)
    except UserError:  # the input's fault (a video that breaks off): nothing here is worth keeping
      shutil.rmtree(work, ignore_errors=True)
      raise
    stages["images"] = {"key": key, "names": names, "info": info}
    save_state()
  timings["frames" if src.kind == "video" else "images"] = time.monotonic() - t
  counts["images"] = len(names)

  # 2. features
  key = {"cameras": cameras, "camera_model": camera_model, "max_image_size": args.max_image_size}
  t = time.monotonic()
  print(f"[2/5] features: SIFT on {len(names)} images, {'one shared' if cameras == 'shared' else 'one per image'} "
        f"{camera_model} camera", flush=True)
  if stages.get("features", {}).get("key") != key:  # not started with these settings: start them afresh
    stages.pop("features", None)
    stages.pop("matching", None)
    if os.path.exists(db_path):
      os.remove(db_path)
    stages["features"] = {"key": key}
    save_state()
  counts.update(sfm.stage_features(db_path, image_dir, names, cameras, camera_model, args.max_image_size,
                                   args.threads, args.seed))
  timings["features"] = time.monotonic() - t

  # 3. matching
  matching = sfm.choose_matching(src.kind, len(names), args.matching)
  pairs = sfm.image_pairs(len(names), matching)
  key = {"matching": matching, "seed": args.seed}  # the seed of the verification's RANSAC
  t = time.monotonic()
  order = " (neighbours in time, and loop pairs)" if matching == "sequential" else ""
  print(f"[3/5] matching: {matching}{order}, {len(pairs):,} pairs", flush=True)
  if stages.get("matching", {}).get("key") != key:
    if "matching" in stages:
      sfm._count(db_path, lambda db: (db.clear_matches(), db.clear_two_view_geometries()))
    stages["matching"] = {"key": key}
    save_state()
  counts.update(sfm.stage_matching(db_path, work, names, pairs, args.threads, args.seed))
  timings["matching"] = time.monotonic() - t

  # 4. mapping
  t = time.monotonic()
  print("[4/5] mapping: " + (f"the {args.mapper} mapper" if args.mapper != "auto" else
                              "the incremental mapper (and the global one if it leaves over 5% out)"), flush=True)
  best, note, choice, tried = sfm.stage_mapping(db_path, work, image_dir, len(names), args.mapper, args.seed)
  timings["mapping"] = time.monotonic() - t
  needed = max(sfm.MIN_IMAGES, math.ceil(args.min_registered * len(names)))
  if best["registered"] < needed:
    raise UserError(sfm.too_few_message(best["registered"], len(names), needed, tried, matching, work))
  rec = best["reconstruction"]

  # 5. writing
  t = time.monotonic()
  print("[5/5] writing the capture", flush=True)
  capture_dir = os.path.join(work, "capture")
  model, factors = capture.stage_writing(capture_dir, image_dir, rec)
  timings["writing"] = time.monotonic() - t
  registered = set(model.names)
  counts.update({"registered": len(model.names), "unregistered": [n for n in names if n not in registered],
                 "points": int(rec.num_points3D()),
                 "reprojection_error_px": float(rec.compute_mean_reprojection_error()),
                 "track_length": float(rec.compute_mean_track_length()),
                 "other_models": best["models"] - 1, "other_models_images": best["others"]})
  if best["others"]:
    note += f"; {best['models'] - 1} smaller model(s) held {best['others']} images it lacks"
  timings["total"] = time.monotonic() - t0
  summary = {
      "version": 1,
      "out": out,
      "input": {"path": os.path.abspath(src.path), "kind": src.kind, **info,
                **({"damaged_left_out": src.damaged} if src.damaged else {})},
      "options": {"num_frames": args.num_frames, "matching": matching, "mapper": args.mapper,
                  "cameras": cameras, "camera_model": camera_model, "max_image_size": args.max_image_size,
                  "min_registered": args.min_registered, "threads": args.threads, "seed": args.seed},
      "versions": _versions(),
      "counts": counts,
      "mapping": sfm.mapping_record(best, note, choice, tried),
      "downscales": factors,
      "forward_facing": capture.looks_forward_facing(model.c2w_opencv()),
      "timings_s": {k: round(v, 2) for k, v in timings.items()},
  }
  capture._write_json(os.path.join(capture_dir, capture.PREPARE_JSON), summary)
  # Only now does --out appear, whole: an earlier capture there (--overwrite) is replaced.
  if os.path.isdir(out):
    shutil.rmtree(out)
  os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
  os.replace(capture_dir, out)
  shutil.rmtree(work, ignore_errors=True)
  return summary


def _versions() -> dict:
  import pycolmap
  versions = {"pycolmap": getattr(pycolmap, "__version__", "?"),
              "colmap": getattr(pycolmap, "COLMAP_version", "?")}
  try:
    from importlib.metadata import version
    versions["nerfpod"] = version("nerfpod")
  except Exception:  # not installed (a checkout on sys.path)
    versions["nerfpod"] = "?"
  try:
    import imageio_ffmpeg
    versions["ffmpeg"] = imageio_ffmpeg.get_ffmpeg_version()
  except Exception:  # only videos need it
    pass
  return versions


def run(argv=None) -> int:
  """`nerfpod prepare ...` and `python -m nerfpod.prepare ...`; argv: the arguments after `prepare` (None:
  sys.argv[1:]). Returns 0 when the capture is written; a user's mistake is one sentence on stderr and exit code
  2; Ctrl-C exits 130, keeping the finished stages for the same command to resume (errors.Command.run)."""
  def work():
    summary = prepare(types.SimpleNamespace(**FLAGS.flag_values_dict()))
    print("nerfpod prepare: done")
    for line in report(summary):
      print("  " + line)
    sys.stdout.flush()
    warning = left_out_warning(summary)
    if warning:
      print(warning, file=sys.stderr, flush=True)
  COMMAND.run(argv, work)
  return 0
