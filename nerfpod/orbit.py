"""The orbit: a camera path around the scene, rendered frame by frame into a tensorstore archive.

The archive, renders/orbit.zarr, is a zarr v3 group:

    zarr.json    group attributes: poses (N, 4, 4), intrinsics, checkpoint step, scene, near/far, the config
    rgb          (N, H, W, 3) uint8
    depth, acc, disparity   (N, H, W) float32
    written_by   (N,) int16: the process that completed frame i; -1 (the fill value) while it is not complete

with one chunk per frame in every array, so a frame is written without touching any other. The workdir may
be a local folder or a gs:// URL: tensorstore writes either; the videos are made locally and copied there.

Work split: frame i belongs to process i % P, and each process renders its frames on its own devices only
(a process-local mesh; a frame's rays are split over those devices in chunks of orbit.chunk rays). Frames
are independent, so this needs no collective while rendering: hosts never wait for each other between
frames, nothing is gathered across hosts, and each host writes exactly the chunks it rendered. (Rendering
every frame with all hosts together, as the evaluator does, would keep them in lockstep and gather every
pixel on every host, for no gain: a frame is small next to a device's memory.) Two barriers frame the
render: one after process 0 has created or validated the archive, one before it exports the videos.

Resuming: a frame's written_by entry is written only once its four data chunks are committed, so a render
cut off mid-frame leaves that frame incomplete, and the next render redoes exactly the incomplete frames.
An archive of another checkpoint step, camera path or model is replaced, not resumed.
"""
import concurrent.futures
import functools
import json
import os
import tempfile
import time

import jax
import numpy as np
import tensorstore as ts
from absl import logging
from etils import epath
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from nerfpod import distributed, render, video, xla_options
from nerfpod.errors import UserError
from nerfpod.nerf import cameras

ARCHIVE = "renders/orbit.zarr"  # in the workdir
FORMAT = "nerfpod-orbit/1"  # written into the group attributes; what readers check they are given
_NOT_WRITTEN = -1


def orbit_poses(num_frames: int, elevation_deg: float, radius: float) -> np.ndarray:
  """(N, 4, 4) float32 camera-to-world poses: the Tiny NeRF tutorial's path, azimuth 0..360 (exclusive) in
  N equal steps at a fixed elevation (its convention: -30 is 30 degrees above the z = 0 plane) and radius,
  every camera looking at the origin."""
  azimuths = np.linspace(0.0, 360.0, num_frames, endpoint=False)
  return np.stack([cameras.spherical_pose(a, elevation_deg, radius) for a in azimuths]).astype(np.float32)


def orbit_intrinsics(orbit_config, reference: cameras.Intrinsics) -> cameras.Intrinsics:
  """The orbit camera: orbit.width/height/focal, each 0 meaning the reference (eval split) camera's.

  A size given for one side only keeps the reference aspect ratio; the default focal length is the
  reference's scaled with the width, i.e. the same field of view.
  """
  width, height = int(orbit_config.width), int(orbit_config.height)
  if width < 0 or height < 0 or orbit_config.focal < 0:
    raise UserError(f"orbit.width={width}, orbit.height={height} and orbit.focal={orbit_config.focal} must "
                    f"be positive numbers, or 0 for the eval split's camera.")
  if not width and not height:
    width, height = reference.width, reference.height
  elif not height:
    height = max(1, round(reference.height * width / reference.width))
  elif not width:
    width = max(1, round(reference.width * height / reference.height))
  focal = float(orbit_config.focal) or reference.fx * width / reference.width
  return cameras.Intrinsics.from_focal(width, height, focal)


def _intrinsics_json(intr: cameras.Intrinsics) -> dict:
  return {"width": intr.width, "height": intr.height, "fx": intr.fx, "fy": intr.fy, "cx": intr.cx,
          "cy": intr.cy}


def is_url(path: str) -> bool:
  return "://" in str(path)


def join(folder: str, *names: str) -> str:
  """A path under `folder`, a local path or a URL (gs://bucket/...)."""
  return "/".join([str(folder).rstrip("/"), *names]) if is_url(folder) else os.path.join(folder, *names)


def _kvstore(path: str, name: str = ""):
  """Tensorstore's key-value store for a folder: the local file system, or a URL it knows (gs://...)."""
  if is_url(path):
    return join(path, name).rstrip("/") + "/"
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

  @property
  def poses(self) -> np.ndarray:
    return np.asarray(self.attributes["poses"], np.float32)

  @staticmethod
  def _spec(path: str, name: str) -> dict:
    return {"driver": "zarr3", "kvstore": _kvstore(path, name)}

  @staticmethod
  def _array_metadata(name: str, num_frames: int, height: int, width: int) -> dict:
    if name == "written_by":
      shape, chunk, dtype, fill = [num_frames], [1], "int16", _NOT_WRITTEN
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
    for name in video.CHANNELS + ("written_by",):
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
    for name in video.CHANNELS + ("written_by",):
      try:
        arrays[name] = ts.open(cls._spec(path, name), open=True).result()
      except ValueError as e:
        raise UserError(f"orbit archive {path} lacks its {name!r} array; render it again.") from e
    return cls(path, attributes, arrays)

  def written_by(self) -> np.ndarray:
    """(N,) int: which process completed each frame, -1 for frames not (completely) written."""
    return np.asarray(self.arrays["written_by"].read().result())

  def missing_frames(self) -> list[int]:
    return [int(i) for i in np.flatnonzero(self.written_by() == _NOT_WRITTEN)]

  def write_frame(self, index: int, frame: dict, process_index: int) -> None:
    """Commits the frame's channels, then (only then) marks it written."""
    futures = [self.arrays[name][index].write(np.asarray(frame[name])) for name in video.CHANNELS]
    for future in futures:
      future.result()
    self.arrays["written_by"][index].write(np.int16(process_index)).result()

  def read_frame(self, index: int) -> dict:
    futures = {name: self.arrays[name][index].read() for name in video.CHANNELS}
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
    nerfpod.video.export. Returns (paths written, contact sheet image)."""
    self.check_complete()
    parent, name = str(self.path).rstrip("/").rsplit("/", 1) if is_url(self.path) else os.path.split(
        os.path.abspath(os.path.normpath(self.path)))
    out_dir = out_dir or parent
    export = functools.partial(video.export, self.read_frame, self.num_frames, self.attributes["near"],
                               self.attributes["far"], prefix=name.removesuffix(".zarr"),
                               fps=fps or self.attributes.get("fps", 30), formats=formats)
    if not is_url(out_dir):
      return export(out_dir)
    with tempfile.TemporaryDirectory() as local:  # ffmpeg writes local files; then they are copied over
      files, sheet = export(local)
      copies = []
      for file in files:
        copies.append(join(out_dir, os.path.basename(file)))
        epath.Path(file).copy(epath.Path(copies[-1]), overwrite=True)
    return copies, sheet


def _identity(attributes: dict) -> dict:
  """What must match for an existing archive to be resumed rather than replaced."""
  config = attributes.get("config", {})
  return {k: attributes.get(k) for k in ("step", "scene", "near", "far", "background", "poses", "intrinsics",
                                         "pixel_center")} | {k: config.get(k) for k in ("model", "render")}


def _barrier(name: str) -> None:
  if jax.process_count() > 1:
    multihost_utils.sync_global_devices(name)


def open_for_render(path: str, attributes: dict) -> Archive:
  """Process 0 resumes the archive at `path` if it is of the same render, else replaces it; then every
  process opens it. Collective: every process must call it."""
  if jax.process_index() == 0:
    try:
      archive = Archive.open(path)
    except UserError:  # none there, or not one of ours
      archive = None
    if archive is not None and _identity(archive.attributes) != _identity(attributes):
      print(f"orbit: {path} holds another render (step {archive.attributes.get('step')}); replacing it",
            flush=True)
      archive = None
    if archive is None:
      Archive.create(path, attributes)
  _barrier("nerfpod_orbit_archive_ready")
  return Archive.open(path)


def local_mesh() -> Mesh:
  """This process's own devices, on the data axis: frames are rendered without other hosts."""
  return Mesh(np.array(jax.local_devices()), (distributed.DATA_AXIS,))


def to_local(params, mesh: Mesh):
  """Replicated (possibly multi-host) parameters -> replicated over this process's devices only."""
  def local(x):
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
      if not x.is_fully_replicated:
        raise ValueError("orbit rendering needs replicated parameters")
      x = x.addressable_data(0)
    return jax.device_put(x, NamedSharding(mesh, P()))
  return jax.tree.map(local, params)


def render_frame(render_fn, params, mesh: Mesh, c2w, intr: cameras.Intrinsics, pixel_center: float,
                 chunk: int) -> dict:
  """One frame on this process's devices (`mesh`), rgb as uint8."""
  out = render.render_image(render_fn, params, mesh, c2w, intr, pixel_center, chunk)
  out["rgb"] = video.to_uint8(out["rgb"])
  return out


def archive_attributes(config, scene, step: int, near: float, far: float) -> dict:
  """Everything stored beside the frames: the cameras, the checkpoint step, the scene and the config."""
  oc = config.orbit
  if oc.num_frames <= 0:
    raise UserError(f"orbit.num_frames={oc.num_frames} must be a positive number of frames.")
  if oc.radius <= 0:
    raise UserError(f"orbit.radius={oc.radius} must be a positive distance.")
  if oc.fps <= 0 or oc.chunk <= 0:
    raise UserError(f"orbit.fps={oc.fps} and orbit.chunk={oc.chunk} must be positive numbers.")
  intr = orbit_intrinsics(oc, scene.split(config.eval.split).intrinsics)
  poses = orbit_poses(oc.num_frames, oc.elevation, oc.radius)
  return {"num_frames": int(oc.num_frames), "step": int(step), "scene": scene.name,
          "near": float(near), "far": float(far), "background": [float(b) for b in scene.background],
          "elevation": float(oc.elevation), "radius": float(oc.radius), "fps": float(oc.fps),
          "pixel_center": float(config.data.pixel_center), "intrinsics": _intrinsics_json(intr),
          "poses": poses.astype(np.float64).tolist(), "config": json.loads(config.to_json_best_effort())}


def render_orbit(config, scene, model, params, workdir: str, step: int, writer=None) -> dict:
  """Renders the orbit of config.orbit into workdir/renders/orbit.zarr, skipping frames already there, then
  (process 0) exports the videos and contact sheet and shows the sheet in TensorBoard.

  Collective: every process calls it with the same arguments. Returns {"archive", "rendered" (the frames
  this process rendered), "skipped" (frames found complete), "files" (process 0: the exported files)}.
  """
  from nerfpod.train import ray_bounds  # the trainer imports this module
  near, far = ray_bounds(config, scene)
  attributes = archive_attributes(config, scene, step, near, far)
  path = join(workdir, ARCHIVE)
  archive = open_for_render(path, attributes)
  written = archive.written_by()
  me, count = jax.process_index(), jax.process_count()
  mine = [i for i in range(archive.num_frames) if i % count == me]
  todo = [i for i in mine if written[i] == _NOT_WRITTEN]
  skipped = [i for i in range(archive.num_frames) if written[i] != _NOT_WRITTEN]
  if me == 0:
    print(f"orbit: {archive.num_frames} frames of {archive.intrinsics.width}x{archive.intrinsics.height} at "
          f"step {step}, {len(skipped)} already written, over {count} process(es)", flush=True)

  logging.info("orbit: process %d of %d renders frames %s", me, count, todo)
  if todo:
    mesh = local_mesh()
    local_params = to_local(params, mesh)
    render_fn = render.make_render_fn(model, mesh, near, far, scene.background,
                                      xla_options.compiler_options(config))
    start = time.perf_counter()
    # Writing frame i overlaps rendering frame i + 1.
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
      pending = None
      for index in todo:
        frame = render_frame(render_fn, local_params, mesh, archive.poses[index], archive.intrinsics,
                             attributes["pixel_center"], config.orbit.chunk)
        if pending is not None:
          pending.result()
        pending = pool.submit(archive.write_frame, index, frame, me)
      pending.result()
    if me == 0:
      seconds = time.perf_counter() - start
      print(f"orbit: process 0 rendered {len(todo)} frames in {seconds:.1f} s "
            f"({seconds / len(todo):.2f} s/frame)", flush=True)

  _barrier("nerfpod_orbit_frames_written")
  files = []
  if me == 0:
    files, sheet = archive.export(fps=config.orbit.fps, formats=("mp4", "png"))
    shown = [f.removeprefix(str(workdir)).lstrip("/") if is_url(f) else os.path.relpath(f, workdir)
             for f in files]
    print(f"orbit: wrote {', '.join(shown)}", flush=True)
    if writer is not None:
      writer.add_image("orbit/contact_sheet", sheet, step, dataformats="HWC")
      writer.flush()
  return {"archive": path, "rendered": todo, "skipped": skipped, "files": files}


def render_workdir(config, workdir: str) -> dict:
  """--mode=render: the orbit of workdir's newest checkpoint."""
  from nerfpod import train
  trained = train.load_trained(config, workdir)
  writer = distributed.summary_writer(workdir)
  try:
    return render_orbit(config, trained.scene, trained.model, trained.state.params, workdir,
                        trained.step, writer=writer)
  finally:
    if writer is not None:
      writer.close()
