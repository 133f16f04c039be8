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

Here: the command (its absl flags, read as every subcommand reads them: errors.parse_flags; STAGES, the table of
the stages in order, each resuming what the work folder holds by the one rule, Job.resume; the report). The
stages' work is in
frames (the input: photos, a video's frames), sfm (pycolmap: features, matching, mapping, the model kept)
and capture (the capture folder's files); progress prints the progress lines.
"""
import dataclasses
import json
import math
import os
import shutil
import sys
import time
import types
import typing

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
flags.DEFINE_integer("threads", _threads(), "CPU threads for SIFT (default: this machine's cores); matching and "
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


@dataclasses.dataclass
class Job:
  """One prepare as its stages see it: the command's options (`args`), the input (`src`), the capture folder
  (`out`) and the work folder beside it (`work`: the staged images, the COLMAP database, state.json) with its
  `state` (the input's signature, and a record per stage begun: the settings it was begun with), the cameras
  chosen; and what the stages find, in order: the image names and the input's `info`, the matching and the
  pairs, the model kept (`best`, `note`, `choice`, `tried`), the capture written (`model`, `factors`), the
  counts and the timings of prepare.json."""
  args: types.SimpleNamespace
  src: frames.Source
  out: str
  work: str
  state: dict
  cameras: str
  camera_model: str
  names: list = None
  info: dict = None
  matching: str = None
  pairs: list = None
  best: dict = None
  note: str = None
  choice: str = None
  tried: list = None
  model: capture.Model = None
  factors: list = None
  counts: dict = dataclasses.field(default_factory=dict)
  timings: dict = dataclasses.field(default_factory=dict)

  @property
  def image_dir(self) -> str:
    return os.path.join(self.work, "images")

  @property
  def db_path(self) -> str:
    return os.path.join(self.work, "database.db")

  @property
  def capture_dir(self) -> str:
    return os.path.join(self.work, "capture")

  def save_state(self) -> None:
    capture.write_json(os.path.join(self.work, STATE), self.state)

  def resume(self, stage: str, key: dict, ready: bool = True) -> bool:
    """The one resume rule: True where the work folder holds `stage` begun with this run's settings (`key`, and
    `ready`: its work is there), to be reused or continued; else False, with the records of `stage` and of
    every stage after it dropped from the state (the caller discards their work and records `key`)."""
    stages = self.state["stages"]
    if stages.get(stage, {}).get("key") == key and ready:
      return True
    for later in RESUMED[RESUMED.index(stage):]:
      stages.pop(later, None)
    return False

  def begin(self, stage: str, record: dict) -> None:
    """Records `stage` (its key, and what a later run reuses) in the state, saved."""
    self.state["stages"][stage] = record
    self.save_state()


def _open_job(args) -> Job:
  """The checks before any work (the input, --out, every photo decoded, pycolmap), the cameras chosen, and the
  work folder with its state: reused where it holds an earlier run of the same input, else started again."""
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
  state.setdefault("stages", {})
  return Job(args, src, out, work, state, cameras, camera_model)


def _remove(path: str) -> None:
  if os.path.exists(path):
    os.remove(path)


def _images(job: Job, label: str) -> None:
  """A video's frames or the photos into the work folder's images/ (reused where they are there); new images
  discard the features and matches (the database)."""
  args, src = job.args, job.src
  key = {"num_frames": args.num_frames} if src.kind == "video" else {}
  if job.resume("images", key, ready=os.path.isdir(job.image_dir)):
    job.names, job.info = job.state["stages"]["images"]["names"], job.state["stages"]["images"]["info"]
    print(f"{label} {'frames' if src.kind == 'video' else 'images'}: {len(job.names)} reused from the earlier run",
          flush=True)
  else:
    windows = len(frames.frame_windows(src.video["frames"], args.num_frames)) - 1 if src.kind == "video" else 0
    print(f"{label} " + (f"frames: the sharpest of each of {windows} even windows in time" if src.kind == "video"
                         else f"images: linking {len(src.files)} photos"), flush=True)
    _remove(job.db_path)
    try:
      job.names, job.info = frames.stage_images(src, job.image_dir, args.num_frames)
    except UserError:  # the input's fault (a video that breaks off): nothing here is worth keeping
      shutil.rmtree(job.work, ignore_errors=True)
      raise
    job.begin("images", {"key": key, "names": job.names, "info": job.info})
  job.counts["images"] = len(job.names)


def _features(job: Job, label: str) -> None:
  """SIFT features into the database; begun with other settings, it starts afresh (a new database)."""
  args = job.args
  key = {"cameras": job.cameras, "camera_model": job.camera_model, "max_image_size": args.max_image_size}
  print(f"{label} features: SIFT on {len(job.names)} images, "
        f"{'one shared' if job.cameras == 'shared' else 'one per image'} {job.camera_model} camera", flush=True)
  if not job.resume("features", key):  # not started with these settings: start them afresh
    _remove(job.db_path)
    job.begin("features", {"key": key})
  job.counts.update(sfm.stage_features(job.db_path, job.image_dir, job.names, job.cameras, job.camera_model,
                                       args.max_image_size, args.threads, args.seed))


def _matching(job: Job, label: str) -> None:
  """The image pairs matched and verified; begun with other settings, its matches are cleared first."""
  args = job.args
  job.matching = sfm.choose_matching(job.src.kind, len(job.names), args.matching)
  job.pairs = sfm.image_pairs(len(job.names), job.matching)
  key = {"matching": job.matching, "seed": args.seed}  # the seed of the verification's RANSAC
  order = " (neighbours in time, and loop pairs)" if job.matching == "sequential" else ""
  print(f"{label} matching: {job.matching}{order}, {len(job.pairs):,} pairs", flush=True)
  begun = "matching" in job.state["stages"]
  if not job.resume("matching", key):
    if begun:
      sfm.clear_matches(job.db_path)
    job.begin("matching", {"key": key})
  job.counts.update(sfm.stage_matching(job.db_path, job.work, job.names, job.pairs, args.seed))


def _mapping(job: Job, label: str) -> None:
  """The mappers on the matches, and the model kept (sfm.stage_mapping; run whole every time); fewer images
  registered than --min_registered asks (and sfm.MIN_IMAGES) is one sentence."""
  args = job.args
  print(f"{label} mapping: " + (f"the {args.mapper} mapper" if args.mapper != "auto" else
                                "the incremental mapper (and the global one if it leaves over 5% out)"), flush=True)
  job.best, job.note, job.choice, job.tried = sfm.stage_mapping(job.db_path, job.work, job.image_dir,
                                                                len(job.names), args.mapper, args.seed)
  needed = max(sfm.MIN_IMAGES, math.ceil(args.min_registered * len(job.names)))
  if job.best["registered"] < needed:
    raise UserError(sfm.too_few_message(job.best["registered"], len(job.names), needed, job.tried, job.matching,
                                        job.work))


def _writing(job: Job, label: str) -> None:
  """The capture's files into the work folder's capture/."""
  print(f"{label} writing the capture", flush=True)
  job.model, job.factors = capture.stage_writing(job.capture_dir, job.image_dir, job.best["reconstruction"])


class Stage(typing.NamedTuple):
  """A stage of prepare: its name (in prepare.json's timings; a video's `images` is `frames`), and `run(job,
  label)`, which prints its line, beginning with `label` ('[i/5]'), and does it, resuming what the work folder
  holds of it (Job.resume)."""
  name: str
  run: typing.Callable


STAGES = (Stage("images", _images), Stage("features", _features), Stage("matching", _matching),
          Stage("mapping", _mapping), Stage("writing", _writing))
RESUMED = ("images", "features", "matching")  # the stages a run resumes, in order (state.json's records)


def prepare(args) -> dict:
  """The whole command: returns prepare.json's content."""
  t0 = time.monotonic()
  job = _open_job(args)
  src = job.src
  what = (f"{len(src.files)} photos in {src.path}" if src.kind == "photos" else
          f"video {src.path} ({src.video['frames']} frames, {src.video['width']}x{src.video['height']}, "
          f"{src.video['duration_s']:.1f} s)")
  print(f"nerfpod prepare: {what} -> {job.out} ({args.threads} threads, seed {args.seed}; work in {job.work})",
        flush=True)
  for number, stage in enumerate(STAGES, 1):
    t = time.monotonic()
    stage.run(job, f"[{number}/{len(STAGES)}]")
    job.timings["frames" if stage.name == "images" and src.kind == "video" else stage.name] = time.monotonic() - t
  return _finish(job, t0)


def _finish(job: Job, t0: float) -> dict:
  """prepare.json written into the capture, which then replaces --out whole; returns its content."""
  args, src, best, rec, note = job.args, job.src, job.best, job.best["reconstruction"], job.note
  registered = set(job.model.names)
  job.counts.update({"registered": len(job.model.names),
                     "unregistered": [n for n in job.names if n not in registered],
                     "points": int(rec.num_points3D()),
                     "reprojection_error_px": float(rec.compute_mean_reprojection_error()),
                     "track_length": float(rec.compute_mean_track_length()),
                     "other_models": best["models"] - 1, "other_models_images": best["others"]})
  if best["others"]:
    note += f"; {best['models'] - 1} smaller model(s) held {best['others']} images it lacks"
  job.timings["total"] = time.monotonic() - t0
  summary = {
      "version": 1,
      "out": job.out,
      "input": {"path": os.path.abspath(src.path), "kind": src.kind, **job.info,
                **({"damaged_left_out": src.damaged} if src.damaged else {})},
      "options": {"num_frames": args.num_frames, "matching": job.matching, "mapper": args.mapper,
                  "cameras": job.cameras, "camera_model": job.camera_model, "max_image_size": args.max_image_size,
                  "min_registered": args.min_registered, "threads": args.threads, "seed": args.seed},
      "versions": _versions(),
      "counts": job.counts,
      "mapping": sfm.mapping_record(best, note, job.choice, job.tried),
      "downscales": job.factors,
      "forward_facing": capture.looks_forward_facing(job.model.c2w_opencv()),
      "timings_s": {k: round(v, 2) for k, v in job.timings.items()},
  }
  capture.write_json(os.path.join(job.capture_dir, capture.PREPARE_JSON), summary)
  # Only now does --out appear, whole: an earlier capture there (--overwrite) is replaced.
  if os.path.isdir(job.out):
    shutil.rmtree(job.out)
  os.makedirs(os.path.dirname(os.path.abspath(job.out)), exist_ok=True)
  os.replace(job.capture_dir, job.out)
  shutil.rmtree(job.work, ignore_errors=True)
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
