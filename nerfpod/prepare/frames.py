"""nerfpod prepare's input: a folder of photos (scanned: sizes, EXIF camera and orientation) or a video (probed
with the ffmpeg that imageio-ffmpeg ships), and the images structure from motion reads: the photos linked (or
upright copies), or a video's frames, the sharpest (variance of the Laplacian) of each even window in time."""
import concurrent.futures
import dataclasses
import hashlib
import json
import os
import re
import shutil

import numpy as np
from PIL import Image, ImageFile, ImageOps

from nerfpod.errors import UserError
from nerfpod.prepare.progress import Progress
from nerfpod.prepare.sfm import MIN_IMAGES

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png")  # what COLMAP and nerfpod's loaders both read
HEIF_EXTENSIONS = (".heic", ".heif")
VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mts", ".3gp")  # messages; ffmpeg decides
DEFAULT_NUM_FRAMES = 150       # from a video: one every 0.4-0.8 s of a 1-2 minute clip
MAX_NAMED = 5                  # damaged photos named in one sentence; past these, "and N more"


# ---------------------------------------------------------------------------------------------------------------
# Frame selection and names (pure)


def sharpness(rgb: np.ndarray) -> float:
  """Variance of the Laplacian of an image's luminance: high for a sharp frame, low for a blurred one. Frames
  of 1,000 pixels or more are subsampled first (every 2nd pixel, every 3rd from 2,000, ...): the ranking of a
  video's frames, all of one size, stays."""
  step = 1 + max(rgb.shape[:2]) // 1000
  g = rgb[::step, ::step, :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
  if min(g.shape) < 3:
    return 0.0
  lap = 4.0 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:]
  return float(lap.var())


def frame_windows(total: int, num_frames: int) -> np.ndarray:
  """Edges (k + 1,) of k = min(num_frames, total) windows of a video's `total` frames, even in time: window i
  holds frames edges[i] .. edges[i + 1] - 1."""
  k = max(1, min(int(num_frames), int(total)))
  return np.round(np.linspace(0, total, k + 1)).astype(np.int64)


def window_of(index: int, edges: np.ndarray) -> int:
  """The window of frame `index` (frames past the end, where a video has more than it said, go to the last)."""
  return int(min(max(np.searchsorted(edges, index, side="right") - 1, 0), len(edges) - 2))


def pick_sharpest(scores, num_frames: int) -> list[int]:
  """The frame of each window (frame_windows) with the highest sharpness score."""
  scores = np.asarray(scores, np.float64)
  edges = frame_windows(len(scores), num_frames)
  return [int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def safe_names(names: list[str]) -> dict[str, str]:
  """Original file name -> the name in the capture: whitespace becomes '_' (COLMAP's pair lists are split on
  spaces), made unique where that collides."""
  out, taken = {}, set()
  for name in names:
    safe = re.sub(r"\s+", "_", name)
    stem, ext = os.path.splitext(safe)
    k = 1
    while safe.lower() in taken:
      safe, k = f"{stem}_{k}{ext}", k + 1
    taken.add(safe.lower())
    out[name] = safe
  return out


# ---------------------------------------------------------------------------------------------------------------
# Input


@dataclasses.dataclass
class Source:
  kind: str                          # "photos" or "video"
  path: str
  files: list[str] = dataclasses.field(default_factory=list)   # photos: file names in the folder, sorted
  sizes: list = dataclasses.field(default_factory=list)        # photos: (w, h) upright
  makers: list = dataclasses.field(default_factory=list)       # photos: (EXIF make, model) or None
  rotated: list = dataclasses.field(default_factory=list)      # photos: EXIF orientation says rotate/flip
  video: dict = dataclasses.field(default_factory=dict)        # video: size, fps, duration, frames
  damaged: dict = dataclasses.field(default_factory=dict)      # photos: name -> why it does not decode

  def signature(self) -> str:
    """What identifies the input for resuming: names, sizes and times of the files."""
    if self.kind == "video":
      st = os.stat(self.path)
      items = [self.path, st.st_size, st.st_mtime_ns]
    else:
      items = [self.path] + [(f, os.stat(os.path.join(self.path, f)).st_size,
                              os.stat(os.path.join(self.path, f)).st_mtime_ns) for f in self.files]
    return hashlib.sha256(json.dumps(items).encode()).hexdigest()[:16]


def _too_few(folder: str, count: int, left_out: int = 0) -> UserError:
  after = f" (after leaving out {left_out} damaged)" if left_out else ""
  return UserError(f"{folder} holds {count} image(s){after}, and structure from motion needs at least {MIN_IMAGES} "
                   f"overlapping views (a NeRF wants 20 or more); take more photos around the subject.")


def _reason(e: Exception, path: str) -> str:
  """PIL's message for a file, without the file's own name (the sentence names it), folded and short."""
  text = " ".join(str(e).replace(repr(path), "").replace(path, "").split()).strip(" :'\"") or type(e).__name__
  return text if len(text) <= 100 else text[:97] + "..."


def scan_photos(folder: str) -> Source:
  """The photos' sizes, cameras and orientations, from their headers; a file whose header PIL cannot read is
  noted in `damaged` (check_photos decides what becomes of it)."""
  entries = sorted(f for f in os.listdir(folder) if os.path.isfile(os.path.join(folder, f)))
  files = [f for f in entries if os.path.splitext(f)[1].lower() in IMAGE_EXTENSIONS]
  if not files:
    heif = [f for f in entries if os.path.splitext(f)[1].lower() in HEIF_EXTENSIONS]
    videos = [f for f in entries if os.path.splitext(f)[1].lower() in VIDEO_EXTENSIONS]
    if heif:
      raise UserError(f"{folder} holds {len(heif)} HEIC/HEIF photo(s) but no JPEG or PNG, and prepare reads only "
                      f".jpg, .jpeg and .png; convert them to JPEG first (e.g. `sips -s format jpeg` on a Mac, "
                      f"ImageMagick's `magick mogrify -format jpg *.heic`, or the phone's 'most compatible' "
                      f"setting).")
    if videos:
      raise UserError(f"{folder} holds no photos (.jpg, .jpeg, .png) but holds the video {videos[0]}; pass "
                      f"--input={os.path.join(folder, videos[0])}.")
    raise UserError(f"{folder} holds no images (.jpg, .jpeg or .png files, directly in the folder); pass a folder "
                    f"of photos or a video file as --input.")
  if len(files) < MIN_IMAGES:
    raise _too_few(folder, len(files))
  src = Source("photos", folder, files)
  for f in files:
    path = os.path.join(folder, f)
    try:
      with Image.open(path) as im:
        exif = im.getexif()
        orientation = int(exif.get(0x0112, 1) or 1)
        w, h = im.size
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
      src.damaged[f] = _reason(e, path)
      orientation, (w, h), exif = 1, (0, 0), {}
    if orientation in (5, 6, 7, 8):  # rotated by 90 degrees: the upright image is h x w
      w, h = h, w
    src.sizes.append((w, h))
    make, model = exif.get(0x010F), exif.get(0x0110)
    src.makers.append((str(make).strip(), str(model).strip()) if make or model else None)
    src.rotated.append(orientation not in (0, 1))
  return src


def decode_error(path: str) -> str | None:
  """Why the image at `path` does not decode whole (a truncated or damaged file), or None where it does. Every
  byte of it is decoded; a JPEG only to 1/8 of its size (libjpeg still reads all its coefficients: 12 MP in
  about 0.15 s rather than 0.25 s)."""
  try:
    with Image.open(path) as im:
      if im.format == "JPEG":
        im.draft(im.mode, (max(1, im.size[0] // 8), max(1, im.size[1] // 8)))
      im.load()
  except (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError) as e:
    return _reason(e, path)
  return None


def damaged_message(folder: str, damaged: dict[str, str]) -> str:
  """The one sentence for damaged photos (name -> reason): each named with its reason, up to MAX_NAMED."""
  if len(damaged) == 1:
    (name, reason), = damaged.items()
    return (f"{os.path.join(folder, name)} is damaged ({reason}); remove it, or pass --skip_bad_images to go on "
            f"without it.")
  named = [f"{name} ({reason})" for name, reason in list(damaged.items())[:MAX_NAMED]]
  more = len(damaged) - len(named)
  listed = ", ".join(named) + (f" and {more} more" if more else "")
  return (f"{len(damaged)} images in {folder} are damaged: {listed}; remove them, or pass --skip_bad_images to go "
          f"on without them.")


def check_photos(src: Source, skip_bad: bool, threads: int = 1) -> str | None:
  """Decodes every photo (decode_error, on `threads` threads) before the long stages. Any damaged: one
  UserError naming them, or with `skip_bad` they are left out of `src` and the warning returned says which
  (a UserError where too few images remain). None where all decode."""
  todo = [f for f in src.files if f not in src.damaged]
  truncated, ImageFile.LOAD_TRUNCATED_IMAGES = ImageFile.LOAD_TRUNCATED_IMAGES, False  # a truncated file fails
  try:
    with concurrent.futures.ThreadPoolExecutor(max(1, threads)) as pool:  # PIL decodes without the GIL
      errors = dict(zip(todo, pool.map(lambda f: decode_error(os.path.join(src.path, f)), todo)))
  finally:
    ImageFile.LOAD_TRUNCATED_IMAGES = truncated
  damaged = {f: src.damaged.get(f) or errors[f] for f in src.files if f in src.damaged or errors[f]}
  if not damaged:
    return None
  if not skip_bad:
    raise UserError(damaged_message(src.path, damaged))
  keep = [i for i, f in enumerate(src.files) if f not in damaged]
  for name in ("files", "sizes", "makers", "rotated"):
    setattr(src, name, [getattr(src, name)[i] for i in keep])
  src.damaged = damaged
  if len(src.files) < MIN_IMAGES:
    raise _too_few(src.path, len(src.files), len(damaged))
  listed = ", ".join(f"{name} ({reason})" for name, reason in damaged.items())
  return f"leaving out {len(damaged)} damaged image(s) in {src.path} (--skip_bad_images): {listed}"


def ffmpeg_reason(error: BaseException, limit: int = 200) -> str:
  """What ffmpeg said went wrong, for a sentence: the last line of `error`'s text (imageio-ffmpeg ends it with
  ffmpeg's own stderr), less its '[demuxer @ 0x...]' prefix, at most `limit` characters cut between words."""
  lines = [line.strip() for line in str(error).splitlines() if line.strip()]
  if not lines:
    return type(error).__name__
  last = re.sub(r"^\[[^\]]*@ 0x[0-9a-fA-F]+\]\s*", "", lines[-1])
  last = " ".join(last.split())
  return last if len(last) <= limit else last[:limit].rsplit(" ", 1)[0] + " ..."


def probe_video(path: str) -> Source:
  import imageio_ffmpeg
  try:
    gen = imageio_ffmpeg.read_frames(path)
    try:
      meta = gen.__next__()
    finally:
      gen.close()
  except (OSError, RuntimeError, StopIteration, ValueError) as e:
    reason = ffmpeg_reason(e)
    kind = ("a video" if os.path.splitext(path)[1].lower() in VIDEO_EXTENSIONS else
            "a video (or a folder of photos)")
    raise UserError(f"{path} is not {kind} that ffmpeg can read ({reason}); pass a folder of .jpg/.png photos "
                    f"or a video such as .mp4 or .mov, re-encoding a damaged one (e.g. ffmpeg -i IN -c:v libx264 "
                    f"OUT.mp4).") from None
  try:
    frames = int(imageio_ffmpeg.count_frames_and_secs(path)[0])
  except (OSError, RuntimeError, ValueError):
    frames = int(round(float(meta.get("duration") or 0) * float(meta.get("fps") or 0)))
  if frames <= 0:
    raise UserError(f"ffmpeg finds no video frames in {path}; pass a video with a picture track (or a folder of "
                    f"photos).")
  size = tuple(int(v) for v in meta["size"])
  return Source("video", path, video={"width": size[0], "height": size[1], "fps": float(meta.get("fps") or 0),
                                      "duration_s": float(meta.get("duration") or 0), "frames": frames,
                                      "codec": str(meta.get("codec", ""))})


def scan_input(path: str) -> Source:
  """The photos folder or video at `path`, checked (UserError for what cannot be prepared)."""
  if not os.path.exists(path):
    raise UserError(f"--input {path} does not exist; pass a folder of photos or a video file.")
  if os.path.isdir(path):
    return scan_photos(path)
  if os.path.splitext(path)[1].lower() in IMAGE_EXTENSIONS + HEIF_EXTENSIONS:
    raise UserError(f"--input {path} is a single image; pass the folder that holds all the photos "
                    f"(--input={os.path.dirname(path) or '.'}).")
  return probe_video(path)


# ---------------------------------------------------------------------------------------------------------------
# The images stage


def stage_images(src: Source, image_dir: str, num_frames: int) -> tuple[list[str], dict]:
  """Fills image_dir with the images SfM reads; returns their names (sorted) and what to record."""
  if os.path.isdir(image_dir):
    shutil.rmtree(image_dir)
  os.makedirs(image_dir)
  if src.kind == "video":
    return extract_frames(src, image_dir, num_frames)
  renamed = safe_names(src.files)
  for f, rotated in zip(src.files, src.rotated):
    s, d = os.path.join(src.path, f), os.path.join(image_dir, renamed[f])
    if rotated:  # write it upright, so COLMAP and nerfpod's loaders (which ignore EXIF orientation) agree
      with Image.open(s) as im:
        up = ImageOps.exif_transpose(im)
        if os.path.splitext(d)[1].lower() == ".png":
          up.save(d)
        else:
          up.convert("RGB").save(d, quality=95, exif=up.getexif())
      continue
    try:
      os.link(s, d)
    except OSError:  # another file system, or links not allowed: copy
      shutil.copy2(s, d)
  return sorted(renamed.values()), {
      "photos": len(src.files), "upright_copies": int(sum(src.rotated)),
      "renamed": {k: v for k, v in renamed.items() if k != v}}


def extract_frames(src: Source, image_dir: str, num_frames: int) -> tuple[list[str], dict]:
  """The sharpest frame of each of num_frames even windows of the video, as frame_NNNNNN.jpg (the frame's
  index), decoding it once."""
  import imageio_ffmpeg
  total = src.video["frames"]
  edges = frame_windows(total, num_frames)
  w, h = src.video["width"], src.video["height"]
  progress = Progress("frames", total, "frames decoded")
  kept, best, current, decoded = [], None, 0, 0

  def flush():
    if best is not None:
      name = f"frame_{best[1]:06d}.jpg"
      Image.fromarray(best[2]).save(os.path.join(image_dir, name), quality=95)
      kept.append(name)

  gen = imageio_ffmpeg.read_frames(src.path)
  try:
    gen.__next__()
    for index, raw in enumerate(gen):
      frame = np.frombuffer(raw, np.uint8)
      if frame.size != w * h * 3:
        raise UserError(f"ffmpeg gave a frame of {frame.size} bytes for a {w}x{h} video in {src.path}; "
                        f"re-encode it (ffmpeg -i IN -c:v libx264 OUT.mp4) and pass that.")
      frame = frame.reshape(h, w, 3)
      window = window_of(index, edges)
      if window != current:
        flush()
        best, current = None, window
      score = sharpness(frame)
      if best is None or score > best[0]:
        best = (score, index, frame)  # a view of this frame's own bytes
      decoded = index + 1
      if decoded < total:
        progress.update(decoded, f", {len(kept)} kept")
    flush()
  except (OSError, RuntimeError) as e:
    reason = ffmpeg_reason(e)
    raise UserError(f"ffmpeg stopped reading {src.path} after {decoded} of {total} frames ({reason}); re-encode "
                    f"it (ffmpeg -i IN -c:v libx264 OUT.mp4) and pass that.") from None
  finally:
    gen.close()
  progress.update(decoded, f", {len(kept)} kept", force=True)
  if len(kept) < MIN_IMAGES:
    raise UserError(f"{src.path} gave only {len(kept)} frame(s), and structure from motion needs at least "
                    f"{MIN_IMAGES}; raise --num_frames or film a longer clip.")
  print(f"  took {len(kept)} frames of {decoded} (the sharpest of each window of about "
        f"{decoded / max(1, len(kept)):.1f}), {w}x{h}", flush=True)
  return sorted(kept), {"video_frames": decoded, "taken": len(kept), "fps": src.video["fps"],
                        "duration_s": src.video["duration_s"], "size": [w, h]}
