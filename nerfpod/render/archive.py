"""The render archive: frames of a camera path in a tensorstore zarr v3 group, local or on gs://.

    zarr.json    group attributes: poses (N, 4, 4), intrinsics, checkpoint step, scene, near/far, the config
    rgb          (N, H, W, 3) uint8
    depth, acc, disparity   (N, H, W) float32
    written_by   (N,) int16: the process that completed frame i; -1 (the fill value) while it is not complete

with one chunk per frame in every array, so a frame is written without touching any other. A frame's
written_by entry is written only once its four data chunks are committed, so a render cut off mid-frame
leaves that frame incomplete. `Archive.export` turns a complete archive into videos and a contact sheet
(nerfpod.render.video); the videos are made locally and copied where the archive is.
"""
import functools
import json
import os
import tempfile

import numpy as np
import tensorstore as ts

from nerfpod import storage
from nerfpod.render import video
from nerfpod.errors import UserError
from nerfpod.nerf import cameras, compositing

ORBIT = "renders/orbit.zarr"  # the orbit's archive, in the workdir
FORMAT = "nerfpod-orbit/1"  # written into the group attributes; what readers check they are given
NOT_WRITTEN = -1


def intrinsics_json(intr: cameras.Intrinsics) -> dict:
  return {"width": intr.width, "height": intr.height, "fx": intr.fx, "fy": intr.fy, "cx": intr.cx,
          "cy": intr.cy}


def _kvstore(path: str, name: str = ""):
  """Tensorstore's key-value store for a folder: the local file system, or a URL it knows (gs://...)."""
  if storage.is_url(path):
    return storage.join(path, name).rstrip("/") + "/"
  return {"driver": "file", "path": os.path.join(os.path.abspath(path), name).rstrip("/") + "/"}


def _group_store(path: str):
  """The archive folder as a tensorstore key-value store (for the group's zarr.json)."""
  return ts.KvStore.open(_kvstore(path)).result()


class Archive:
  """An orbit archive (tensorstore, zarr v3, one chunk per frame) in a local folder or at a gs:// URL."""

  def __init__(self, path: str, attributes: dict, arrays: dict):
    self.path, self.attributes, self.arrays = path, attributes, arrays

  @property
  def num_frames(self) -> int:
    return int(self.attributes["num_frames"])

  @property
  def intrinsics(self) -> cameras.Intrinsics:
    return cameras.Intrinsics(**self.attributes["intrinsics"])

  def frame_intrinsics(self, index: int) -> cameras.Intrinsics:
    """Frame `index`'s camera: its own where the path gives each frame one (a camera path file's fov),
    else the archive's one camera. Every frame has the archive's width and height."""
    per_frame = self.attributes.get("frame_intrinsics")
    return cameras.Intrinsics(**per_frame[index]) if per_frame else self.intrinsics

  @property
  def poses(self) -> np.ndarray:
    return np.asarray(self.attributes["poses"], np.float32)

  @staticmethod
  def _spec(path: str, name: str) -> dict:
    return {"driver": "zarr3", "kvstore": _kvstore(path, name)}

  @staticmethod
  def _array_metadata(name: str, num_frames: int, height: int, width: int) -> dict:
    if name == "written_by":
      shape, chunk, dtype, fill = [num_frames], [1], "int16", NOT_WRITTEN
    elif name == "rgb":
      shape, chunk, dtype, fill = [num_frames, height, width, 3], [1, height, width, 3], "uint8", 0
    else:
      shape, chunk, dtype, fill = [num_frames, height, width], [1, height, width], "float32", 0.0
    return {"shape": shape, "data_type": dtype, "fill_value": fill,
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": chunk}},
            "codecs": [{"name": "bytes", "configuration": {"endian": "little"}},
                       {"name": "zstd", "configuration": {"level": 3}}]}

  @classmethod
  def create(cls, path: str, attributes: dict) -> "Archive":
    """A new, empty archive at `path`, replacing any there. The group metadata is written last, so an
    archive whose creation was cut off is never taken for a valid one."""
    attributes = dict(attributes, format=FORMAT)
    intr = attributes["intrinsics"]
    kvstore = _group_store(path)
    kvstore.delete_range(ts.KvStore.KeyRange("zarr.json", "zarr.json\0")).result()
    arrays = {}
    for name in compositing.OUTPUTS + ("written_by",):
      metadata = cls._array_metadata(name, attributes["num_frames"], intr["height"], intr["width"])
      arrays[name] = ts.open(dict(cls._spec(path, name), metadata=metadata), create=True,
                             delete_existing=True).result()
    group = {"zarr_format": 3, "node_type": "group", "attributes": attributes}
    kvstore.write("zarr.json", json.dumps(group).encode()).result()
    return cls(path, attributes, arrays)

  @classmethod
  def open(cls, path: str) -> "Archive":
    """The archive at `path`; UserError if there is none (or not a complete one)."""
    group = _group_store(path).read("zarr.json").result()
    if group.state != "value":
      raise UserError(f"no orbit archive at {path}; render one with `python -m nerfpod.main --mode=render "
                      f"--config=CONFIG --workdir=WORKDIR`.")
    try:
      attributes = json.loads(group.value).get("attributes", {})
    except ValueError:
      attributes = {}
    if attributes.get("format") != FORMAT:
      raise UserError(f"{path} is not a nerfpod orbit archive (its zarr.json has no format {FORMAT!r}).")
    arrays = {}
    for name in compositing.OUTPUTS + ("written_by",):
      try:
        arrays[name] = ts.open(cls._spec(path, name), open=True).result()
      except ValueError as e:
        raise UserError(f"orbit archive {path} lacks its {name!r} array; render it again.") from e
    return cls(path, attributes, arrays)

  def written_by(self) -> np.ndarray:
    """(N,) int: which process completed each frame, -1 for frames not (completely) written."""
    return np.asarray(self.arrays["written_by"].read().result())

  def missing_frames(self) -> list[int]:
    return [int(i) for i in np.flatnonzero(self.written_by() == NOT_WRITTEN)]

  def write_frame(self, index: int, frame: dict, process_index: int) -> None:
    """Commits the frame's channels, then (only then) marks it written."""
    futures = [self.arrays[name][index].write(np.asarray(frame[name])) for name in compositing.OUTPUTS]
    for future in futures:
      future.result()
    self.arrays["written_by"][index].write(np.int16(process_index)).result()

  def read_frame(self, index: int) -> dict:
    futures = {name: self.arrays[name][index].read() for name in compositing.OUTPUTS}
    return {name: np.asarray(future.result()) for name, future in futures.items()}

  def check_complete(self) -> None:
    """UserError naming the frames that are missing, if any are."""
    missing = self.missing_frames()
    if missing:
      shown = ", ".join(map(str, missing[:20])) + (", ..." if len(missing) > 20 else "")
      raise UserError(f"orbit archive {self.path} is incomplete: {len(missing)} of {self.num_frames} frames "
                      f"are missing ({shown}); finish it with `python -m nerfpod.main --mode=render` on its "
                      f"workdir, which renders only the missing frames.")

  def export(self, out_dir: str | None = None, fps: float | None = None, formats=("mp4", "png")):
    """Videos and contact sheet of a complete archive, named after it (orbit_rgb.mp4, ...); see
    nerfpod.render.video.write_media. Returns (paths written, contact sheet image)."""
    self.check_complete()
    parent, name = str(self.path).rstrip("/").rsplit("/", 1) if storage.is_url(self.path) else os.path.split(
        os.path.abspath(os.path.normpath(self.path)))
    out_dir = out_dir or parent
    write = functools.partial(video.write_media, self.read_frame, self.num_frames, self.attributes["near"],
                              self.attributes["far"], prefix=name.removesuffix(".zarr"),
                              fps=fps or self.attributes.get("fps", 30), formats=formats)
    if not storage.is_url(out_dir):
      return write(out_dir)
    with tempfile.TemporaryDirectory() as local:  # ffmpeg writes local files; then they are copied over
      files, sheet = write(local)
      copies = []
      for file in files:
        copies.append(storage.join(out_dir, os.path.basename(file)))
        storage.path(file).copy(storage.path(copies[-1]), overwrite=True)
    return copies, sheet
