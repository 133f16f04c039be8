"""Rendered channels to viewable media: a colour map, mp4 and gif writers, a PNG contact sheet.

Everything here takes plain NumPy frames; nerfpod.render.archive reads them from an archive. Depth and disparity
are colour-mapped with turbo, near things warm and far things cold, over one value range for the whole
video (so colours do not flicker from frame to frame).
"""
import contextlib
import os
import warnings

import imageio.v2 as imageio
import numpy as np

from nerfpod.nerf import compositing

FORMATS = ("mp4", "gif", "png")


def mp4_available() -> bool:
  """Whether imageio finds an ffmpeg to write mp4s with (imageio-ffmpeg's own binary, or IMAGEIO_FFMPEG_EXE):
  a machine given nerfpod's code without its dependencies (an accelerator image, packages carried by hand)
  may have none."""
  try:
    import imageio_ffmpeg
    return os.path.exists(imageio_ffmpeg.get_ffmpeg_exe())
  except (ImportError, RuntimeError):
    return False

# Polynomial fit of Google's turbo colour map (Anton Mikhailov, 2019), per channel: coefficients of
# 1, x, ..., x^5. It follows the map closely except below x = 0.02, where it turns grey.
_TURBO_FIT_START = 0.02
_TURBO = np.array([
    [0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943],
    [0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604],
    [0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973],
])


def turbo(x) -> np.ndarray:
  """Values in [0, 1] (clipped) -> turbo colours (..., 3) in [0, 1]: 0 dark blue, 0.5 green, 1 dark red."""
  x = np.clip(np.asarray(x, np.float64), _TURBO_FIT_START, 1.0)
  powers = x[..., None] ** np.arange(6)
  return np.clip(powers @ _TURBO.T, 0.0, 1.0)


def depth_image(depth_HxW, near: float, far: float) -> np.ndarray:
  """Depth mapped to [0, 1] between the ray bounds (near white, far black), for TensorBoard."""
  return np.clip((far - np.asarray(depth_HxW)) / (far - near), 0.0, 1.0)


def to_uint8(image) -> np.ndarray:
  return np.round(np.clip(np.asarray(image, np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)


def value_range(values, weights, fallback: tuple[float, float], low_pct: float = 2.0,
                high_pct: float = 98.0) -> tuple[float, float]:
  """Robust (low, high) percentiles of `values` where `weights` > 0.5 (where something was hit);
  `fallback` (e.g. the near/far bounds) where too little was hit for percentiles to mean anything."""
  values, weights = np.asarray(values, np.float64), np.asarray(weights, np.float64)
  hit = values[(weights > 0.5) & np.isfinite(values)]
  if hit.size < 16:
    return float(fallback[0]), float(fallback[1])
  low, high = np.percentile(hit, [low_pct, high_pct])
  return (float(low), float(high)) if high > low else (float(fallback[0]), float(fallback[1]))


def expected_depth(depth, acc) -> np.ndarray:
  """The depth of the surface a ray hits (depth / acc): the rendered depth averages in 0 for the part of
  the ray that hits nothing, which would make half-transparent edges look near."""
  return np.asarray(depth, np.float64) / np.maximum(np.asarray(acc, np.float64), 1e-6)


class ChannelStyle:
  """How each rendered channel becomes an RGB uint8 image; value ranges fixed once per video."""

  def __init__(self, depth_range: tuple[float, float], disparity_range: tuple[float, float]):
    self.depth_range, self.disparity_range = depth_range, disparity_range

  @classmethod
  def fit(cls, sample_frames: list[dict], near: float, far: float) -> "ChannelStyle":
    """Ranges from robust percentiles of some frames, with the ray bounds as the fallback."""
    acc = np.stack([f["acc"] for f in sample_frames])
    depth = np.stack([expected_depth(f["depth"], f["acc"]) for f in sample_frames])
    disparity = np.stack([f["disparity"] for f in sample_frames])
    nearest = max(near, 1e-3 * far)  # near may be 0
    return cls(value_range(depth, acc, (near, far)), value_range(disparity, acc, (1.0 / far, 1.0 / nearest)))

  def image(self, channel: str, frame: dict) -> np.ndarray:
    """(H, W, 3) uint8 picture of one channel of one frame."""
    if channel == "rgb":
      rgb = np.asarray(frame["rgb"])
      return rgb if rgb.dtype == np.uint8 else to_uint8(rgb)
    acc = np.clip(np.asarray(frame["acc"], np.float64), 0.0, 1.0)
    if channel == "acc":
      return to_uint8(np.repeat(acc[..., None], 3, axis=-1))
    if channel == "depth":
      lo, hi = self.depth_range
      normalised = (hi - expected_depth(frame["depth"], frame["acc"])) / (hi - lo)  # near: 1 (red)
      return to_uint8(turbo(normalised) * acc[..., None])  # fades to black where nothing is hit
    if channel == "disparity":
      lo, hi = self.disparity_range
      # acc / depth is 1 / (mean t) even on nearly empty rays, where it means nothing: fade those to black.
      return to_uint8(turbo((np.asarray(frame["disparity"], np.float64) - lo) / (hi - lo)) * acc[..., None])
    raise ValueError(f"unknown channel {channel!r}; known: {compositing.OUTPUTS}")


def _even(image: np.ndarray) -> np.ndarray:
  """Pads an odd height or width by repeating the last row/column: H.264 in yuv420p needs even sizes."""
  h, w = image.shape[:2]
  return np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") if h % 2 or w % 2 else image


@contextlib.contextmanager
def quiet_fork_warning():
  """ffmpeg runs as a child process (fork, then exec at once): JAX's warning about fork does not apply. It is
  a RuntimeWarning attributed to `subprocess`, which forks (tests/test_library_texts.py pins both)."""
  with warnings.catch_warnings():
    warnings.filterwarnings("ignore", category=RuntimeWarning, module=r"subprocess\Z")
    yield


class VideoWriter:
  """Streams frames to an mp4 (H.264, yuv420p: plays everywhere) or an endlessly looping gif."""

  def __init__(self, path: str, fps: float):
    self.path = path
    if path.endswith(".mp4"):
      # macro_block_size=1: keep the frame size (imageio would otherwise resize to multiples of 16).
      with quiet_fork_warning():
        self._writer = imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                          quality=8, pixelformat="yuv420p", macro_block_size=1,
                                          ffmpeg_log_level="error")
      self._prepare = _even
    elif path.endswith(".gif"):
      self._writer = imageio.get_writer(path, mode="I", duration=1000.0 / fps, loop=0)
      self._prepare = lambda image: image
    else:
      raise ValueError(f"{path}: only .mp4 and .gif are written")

  def append(self, image_HxWx3: np.ndarray) -> None:
    with quiet_fork_warning():  # the first frame starts ffmpeg
      self._writer.append_data(self._prepare(np.ascontiguousarray(image_HxWx3, np.uint8)))

  def close(self) -> None:
    with quiet_fork_warning():
      self._writer.close()


def contact_sheet(rows: list[list[np.ndarray]], gap: int = 2) -> np.ndarray:
  """Images (all the same size) laid out in a grid with white gaps: one row per list."""
  h, w = rows[0][0].shape[:2]
  columns = max(len(r) for r in rows)
  sheet = np.full((len(rows) * (h + gap) - gap, columns * (w + gap) - gap, 3), 255, np.uint8)
  for r, images in enumerate(rows):
    for c, image in enumerate(images):
      sheet[r * (h + gap):r * (h + gap) + h, c * (w + gap):c * (w + gap) + w] = image
  return sheet


def sheet_frames(num_frames: int, max_columns: int = 8) -> list[int]:
  """Up to `max_columns` frame indices spread evenly over the orbit, first frame included."""
  count = min(num_frames, max_columns)
  return sorted({int(i) for i in np.linspace(0, num_frames, count, endpoint=False)})


def write_png(path: str, image: np.ndarray) -> None:
  imageio.imwrite(path, image, format="PNG")


def check_formats(formats) -> tuple[str, ...]:
  formats = tuple(f.strip().lower() for f in formats if f.strip())
  unknown = sorted(set(formats) - set(FORMATS))
  if unknown or not formats:
    raise ValueError(f"unknown export format(s) {unknown or formats}; choose from {', '.join(FORMATS)}")
  return formats


def output_paths(out_dir: str, prefix: str, formats) -> dict:
  """{(channel, format): path}: PREFIX_CHANNEL.mp4/.gif per channel, and PREFIX_sheet.png."""
  paths = {}
  for fmt in formats:
    if fmt == "png":
      paths[("sheet", "png")] = os.path.join(out_dir, f"{prefix}_sheet.png")
    else:
      for channel in compositing.OUTPUTS:
        paths[(channel, fmt)] = os.path.join(out_dir, f"{prefix}_{channel}.{fmt}")
  return paths


def write_media(read_frame, num_frames: int, near: float, far: float, out_dir: str, prefix: str, fps: float,
                formats=("mp4", "png")) -> tuple[list[str], np.ndarray]:
  """Writes the videos and contact sheet of frames read_frame(0 .. num_frames-1) (dicts of channels).

  Frames are streamed: one frame is in memory at a time, plus the contact sheet's few. Each file is written
  under a temporary name and renamed when complete. Returns (paths written, the contact sheet image).
  """
  formats = check_formats(formats)
  os.makedirs(out_dir, exist_ok=True)
  paths = output_paths(out_dir, prefix, formats)
  picked = sheet_frames(num_frames)
  samples = {i: read_frame(i) for i in picked}
  style = ChannelStyle.fit(list(samples.values()), near, far)
  temporary = {key: f"{path[:-4]}.partial{path[-4:]}" for key, path in paths.items()}
  writers = {key: VideoWriter(temporary[key], fps) for key in paths if key[1] != "png"}
  try:
    if writers:
      for i in range(num_frames):
        frame = samples[i] if i in samples else read_frame(i)
        for (channel, _), writer in writers.items():
          writer.append(style.image(channel, frame))
  finally:
    for writer in writers.values():
      writer.close()
  sheet = contact_sheet([[style.image(channel, samples[i]) for i in picked]
                        for channel in compositing.OUTPUTS])
  if ("sheet", "png") in paths:
    write_png(temporary[("sheet", "png")], sheet)
  for key, path in paths.items():
    os.replace(temporary[key], path)
  return list(paths.values()), sheet
