"""The orbit: a camera path around the scene, rendered frame by frame into a render archive.

The path is `orbit.path`: 'orbit', the Tiny NeRF tutorial's circle around the origin; 'spiral', the original
NeRF's forward-facing spiral, and 'ellipse', mip-NeRF 360's path, both drawn from the scene's own cameras
(nerf/paths.py); 'file', a user's nerfstudio camera_path.json (`orbit.path_file`, nerfpod.render.camera_path),
whose cameras, size and frame rate are used as they are.

The archive (nerfpod.render.archive) is renders/orbit.zarr in the workdir, a local folder or a gs:// URL.

Work split: frame i belongs to process i % P, which alone renders and writes it. The rendering itself is
one program over every device of every host: the run's renderer (comps.renderer, compiled once on the
run's mesh), as a pod requires (TPU v5e refuses a program on one host's chips of a slice of 32 or more;
every compiled program of a run spans the whole slice). In each call every process feeds one chunk of its
own current frame (orbit.chunk rays, padded as before) onto its own devices (distributed.make_mesh orders
the mesh host by host), and reads back only the rows its own devices computed: the program has no
collective, nothing is gathered across hosts, and each device renders exactly the rays, in the very
blocks, it rendered when each host had a renderer of its own, so the frames are those of a one-host render.
Hosts take part in every call, so a host with fewer frames left (the last of an uneven split, or after a
resume) feeds a padding chunk, whose results it drops. Barriers frame the render: after process 0 has
created or validated the archive, after every process has read which frames are done (the plan of calls is
computed alike on all of them), and before process 0 exports the videos.

Resuming: a render cut off mid-frame leaves that frame incomplete, and the next render redoes exactly the
incomplete frames. An archive of another checkpoint step, camera path or model is replaced, not resumed.
"""
import concurrent.futures
import dataclasses
import json
import os
import time

import jax
import numpy as np
from absl import logging
from jax.experimental import multihost_utils
from jax.sharding import Mesh

from nerfpod.render import archive as archives
from nerfpod import distributed, storage
from nerfpod.render import camera_path, renderer, video
from nerfpod.errors import UserError
from nerfpod.nerf import cameras, compositing, paths


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
  if not width and not height:
    width, height = reference.width, reference.height
  elif not height:
    height = max(1, round(reference.height * width / reference.width))
  elif not width:
    width = max(1, round(reference.width * height / reference.height))
  focal = float(orbit_config.focal) or reference.fx * width / reference.width
  return cameras.Intrinsics.from_focal(width, height, focal)


def scene_poses(scene) -> np.ndarray:
  """(N, 4, 4) float64: every camera of the scene once (the capture, as the paths see it). Frames in
  several splits (the captures' val and test are the same held-out frames) count once, by name."""
  poses = {}
  for split in scene.splits.values():
    for name, pose in zip(split.names, split.poses):
      poses.setdefault(name, np.asarray(pose, np.float64))
  return np.stack(list(poses.values()))


def scene_depth_bounds(scene) -> tuple[float, float]:
  """The smallest and largest depth bound of the capture: its frames' bounds where the format has them
  (LLFF's, in the scene's frame), else the scene's near and far."""
  bounds = [split.bounds for split in scene.splits.values() if split.bounds is not None]
  if bounds:
    return float(min(b.min() for b in bounds)), float(max(b.max() for b in bounds))
  return float(scene.near), float(scene.far)


@dataclasses.dataclass(frozen=True)
class PathCameras:
  """The cameras of the path to render: poses, one intrinsics for all frames or one per frame, fps."""
  poses: np.ndarray  # (N, 4, 4) float32 camera-to-world, OpenGL
  intrinsics: tuple[cameras.Intrinsics, ...]  # one, or one per frame (a camera path file's own fov each)
  fps: float


def path_cameras(config, scene) -> PathCameras:
  """The cameras of config.orbit.path for `scene` (see the module's docstring)."""
  oc = config.orbit
  if oc.path == "file":
    path = camera_path.read(oc.path_file)
    intrinsics = tuple(path.intrinsics(i) for i in range(len(path)))
    if len(set(intrinsics)) == 1:
      intrinsics = intrinsics[:1]
    return PathCameras(path.poses.astype(np.float32), intrinsics, path.fps)
  intr = orbit_intrinsics(oc, scene.split(config.eval.split).intrinsics)
  if oc.path == "orbit":
    poses = orbit_poses(oc.num_frames, oc.elevation, oc.radius)
  elif oc.path == "spiral":
    poses = paths.spiral(scene_poses(scene), *scene_depth_bounds(scene), num_frames=oc.num_frames)
  elif oc.path == "ellipse":
    poses = paths.ellipse(scene_poses(scene), oc.num_frames)
  else:
    raise ValueError(f"unknown orbit.path {oc.path!r}")  # nerfpod.schema refuses it first
  return PathCameras(poses.astype(np.float32), (intr,), float(oc.fps))


def _identity(attributes: dict) -> dict:
  """What must match for an existing archive to be resumed rather than replaced."""
  config = attributes.get("config", {})
  return {k: attributes.get(k) for k in ("step", "scene", "near", "far", "background", "poses", "intrinsics",
                                         "frame_intrinsics", "pixel_center")} | {
                                             k: config.get(k) for k in ("model", "render")}


def _barrier(name: str) -> None:
  if jax.process_count() > 1:
    multihost_utils.sync_global_devices(name)


def open_for_render(path: str, attributes: dict) -> archives.Archive:
  """Process 0 resumes the archive at `path` if it is of the same render, else replaces it; then every
  process opens it. Collective: every process must call it."""
  if jax.process_index() == 0:
    try:
      archive = archives.Archive.open(path)
    except UserError:  # none there, or not one of ours
      archive = None
    if archive is not None and _identity(archive.attributes) != _identity(attributes):
      print(f"orbit: {path} holds another render (step {archive.attributes.get('step')}); replacing it",
            flush=True)
      archive = None
    if archive is None:
      archives.Archive.create(path, attributes)
  _barrier("nerfpod_orbit_archive_ready")
  return archives.Archive.open(path)


def chunk_rays(chunk: int, num_rays: int, mesh: Mesh) -> int:
  """Rays per call that each process feeds for one frame of `num_rays` rays, as renderer.render_rays picks
  them on one host (renderer.balanced_chunk): as few calls as `chunk` (orbit.chunk) allows, of equal size,
  a multiple of this process's devices."""
  return renderer.balanced_chunk(chunk, num_rays, _local_device_count(mesh))


def _local_device_count(mesh: Mesh) -> int:
  counts = {}
  for device in mesh.devices.flat:
    counts[device.process_index] = counts.get(device.process_index, 0) + 1
  if len(set(counts.values())) != 1:
    raise UserError(f"the orbit needs the same number of devices on every process; this run has "
                    f"{sorted(counts.values())}.")
  return counts[jax.process_index()]


def _own_rows(array: jax.Array) -> np.ndarray:
  """This process's rows of an array sharded over the mesh's data axis, in order: what its own devices
  computed (no transfer from other hosts)."""
  shards = sorted(array.addressable_shards, key=lambda s: s.index[0].start or 0)
  return np.concatenate([np.asarray(s.data) for s in shards])


class FrameRenderer:
  """Renders one frame per process per round with the run's renderer over the whole mesh (see the module's
  docstring). Collective: every process calls render() the same number of times, with or without a frame."""

  def __init__(self, renderer, params, mesh: Mesh, intr: cameras.Intrinsics, pixel_center: float, chunk: int,
               filler_pose):
    self.renderer, self.params, self.mesh = renderer, params, mesh
    self.height, self.width, self.pixel_center = intr.height, intr.width, pixel_center
    self.num_rays = intr.height * intr.width
    self.chunk = chunk_rays(chunk, self.num_rays, mesh)
    self.calls = -(-self.num_rays // self.chunk)
    # What a process without a frame this round feeds: one real ray (of `filler_pose`) repeated.
    self.filler = tuple(np.repeat(x.reshape(-1, 3)[:1], self.chunk, axis=0)
                        for x in cameras.image_rays(filler_pose, intr, pixel_center))

  def render(self, c2w_4x4=None, intr: cameras.Intrinsics | None = None) -> dict | None:
    """This process's frame (rgb uint8, depth, acc, disparity), or None without one (a padding round)."""
    if c2w_4x4 is not None:
      origins, directions = cameras.image_rays(c2w_4x4, intr, self.pixel_center)
      origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
      padded = self.calls * self.chunk
      if padded > self.num_rays:  # the last chunk padded with the frame's last ray, as render_rays pads
        origins, directions = (np.concatenate([x, np.repeat(x[-1:], padded - self.num_rays, axis=0)])
                               for x in (origins, directions))
    pieces = []
    for call in range(self.calls):
      rows = (self.filler if c2w_4x4 is None else
              (origins[call * self.chunk:(call + 1) * self.chunk],
               directions[call * self.chunk:(call + 1) * self.chunk]))
      pieces.append(self.renderer(self.params, *distributed.to_global(self.mesh, rows)))
    if c2w_4x4 is None:
      jax.block_until_ready(pieces)
      return None
    out = {k: np.concatenate([_own_rows(p[k]) for p in pieces])[:self.num_rays] for k in compositing.OUTPUTS}
    out = {k: v.reshape((self.height, self.width) + v.shape[1:]) for k, v in out.items()}
    out["rgb"] = video.to_uint8(out["rgb"])
    return out


def archive_attributes(comps, step: int) -> dict:
  """Everything stored beside the frames: the cameras, the checkpoint step, the scene and the config."""
  config, scene = comps.config, comps.scene
  oc = config.orbit
  cams = path_cameras(config, scene)
  attributes = {
      "num_frames": len(cams.poses), "step": int(step), "scene": scene.name, "path": oc.path,
      "near": float(comps.near), "far": float(comps.far), "background": [float(b) for b in scene.background],
      "elevation": float(oc.elevation), "radius": float(oc.radius), "fps": float(cams.fps),
      "pixel_center": float(config.data.pixel_center), "intrinsics": archives.intrinsics_json(cams.intrinsics[0]),
      "poses": cams.poses.astype(np.float64).tolist(), "config": json.loads(config.to_json_best_effort())}
  if len(cams.intrinsics) > 1:
    attributes["frame_intrinsics"] = [archives.intrinsics_json(intr) for intr in cams.intrinsics]
  return attributes


def render_orbit(comps, params, workdir: str, step: int, writer=None) -> dict:
  """Renders the orbit of config.orbit into workdir/renders/orbit.zarr, skipping frames already there, then
  (process 0) exports the videos and contact sheet and shows the sheet in TensorBoard.

  Collective: every process calls it with the same arguments. Returns {"archive", "rendered" (the frames
  this process rendered), "skipped" (frames found complete), "files" (process 0: the exported files)}.
  """
  config = comps.config
  attributes = archive_attributes(comps, step)
  path = storage.join(workdir, archives.ORBIT)
  archive = open_for_render(path, attributes)
  written = archive.written_by()
  me, count = jax.process_index(), jax.process_count()
  mine = [i for i in range(archive.num_frames) if i % count == me]
  todo = [i for i in mine if written[i] == archives.NOT_WRITTEN]
  skipped = [i for i in range(archive.num_frames) if written[i] != archives.NOT_WRITTEN]
  if me == 0:
    print(f"orbit: {archive.num_frames} frames of {archive.intrinsics.width}x{archive.intrinsics.height} at "
          f"step {step}, {len(skipped)} already written, over {count} process(es)", flush=True)

  logging.info("orbit: process %d of %d renders frames %s", me, count, todo)
  # Every process plans the same rounds from the same `written`, read before any process writes a frame.
  _barrier("nerfpod_orbit_planned")
  rounds = max(len([i for i in range(p, archive.num_frames, count) if written[i] == archives.NOT_WRITTEN])
               for p in range(count))
  if rounds:
    frames = FrameRenderer(comps.renderer, params, comps.mesh, archive.frame_intrinsics(0),
                           attributes["pixel_center"], config.orbit.chunk, archive.poses[0])
    start = time.perf_counter()
    # Writing frame i overlaps rendering frame i + 1.
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
      pending = None
      for round_ in range(rounds):
        if round_ >= len(todo):
          frames.render()  # this process's frames are done: it feeds padding, as the program spans all hosts
          continue
        index = todo[round_]
        frame = frames.render(archive.poses[index], archive.frame_intrinsics(index))
        if pending is not None:
          pending.result()
        pending = pool.submit(archive.write_frame, index, frame, me)
      if pending is not None:
        pending.result()
    if me == 0 and todo:
      seconds = time.perf_counter() - start
      print(f"orbit: process 0 rendered {len(todo)} frames in {seconds:.1f} s "
            f"({seconds / len(todo):.2f} s/frame)", flush=True)

  _barrier("nerfpod_orbit_frames_written")
  files = []
  if me == 0:
    formats = ("mp4", "png") if video.mp4_available() else ("gif", "png")
    if "gif" in formats:
      print("orbit: no ffmpeg for mp4s (pip install imageio-ffmpeg): writing gifs instead", flush=True)
    files, sheet = archive.export(fps=attributes["fps"], formats=formats)
    shown = [f.removeprefix(str(workdir)).lstrip("/") if storage.is_url(f) else os.path.relpath(f, workdir)
             for f in files]
    print(f"orbit: wrote {', '.join(shown)}", flush=True)
    if writer is not None:
      writer.add_image("orbit/contact_sheet", sheet, step, dataformats="HWC")
      writer.flush()
  return {"archive": path, "rendered": todo, "skipped": skipped, "files": files}
