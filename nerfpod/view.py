"""The live viewer: a web page (viser) showing a workdir's newest checkpoint, rendered by nerfpod's renderer.

    nerfpod view --workdir=DIR [--port=7007] [--host=127.0.0.1]      # or: python -m nerfpod.view ...

What it reads, and only reads: DIR/config.json (the run's resolved config: the scene, the model, the ray
bounds, so a user passes nothing else) and DIR/checkpoints (restored read-only, as --mode=eval does, so
it never writes, cleans or locks anything a running training job owns). DIR may be local or gs://.
Training may still be running: the newest complete checkpoint is polled every `poll_seconds` and a newer
one replaces the parameters on screen, without a restart.

A damaged checkpoint (a step that does not read back whole: a file truncated, emptied or deleted) is
skipped as `--mode=eval` skips it: the viewer shows the newest step before it that reads back whole, says
so in one warning line and on the page ("step 10 (step 20 does not read back whole: ...)"), and leaves the
damaged step where it is (a training run on the workdir sets it aside). A damaged step is not read again;
a newer one that reads back whole replaces what is on screen as usual. No step reading back whole at
start-up is one sentence (exit code 2).

What the page shows: the scene from the camera the user drags, rendered on this machine's JAX devices (CPU
or GPU) by the same compiled renderer evaluation and orbits use; the channel picked (rgb, depth, acc,
disparity, coloured as the orbit videos are); the training and held-out cameras as frustums holding their
images (the training cameras at their corrected poses where the run refined them: train.pose_refine); the
checkpoint's step. A region model (model.regions > 1, docs/scale.md) also shows its regions, each in a colour
of its own (region_colour): its cell (nerf/regions.py's cells: the region within the field's box, a column
over a polygon of the ground plane: a grid's cells are boxes, a camera cut's the Voronoi cells of its
centres) as a wireframe, a marker and a label at its centre (the mean of its training cameras: a camera cut's
k-means centre), and each training camera in the colour of the region its centre lies in ("Show regions"
hides them). Rendering is progressive and never blocks the page: each browser has its own render
thread; a moved camera is drawn first at `coarse_resolution` (one renderer call), and at full resolution
(the canvas's size, at most the page's "Max resolution") once the camera has been still for `STILL_SECONDS`;
a full render is abandoned between chunks as soon as the camera moves again. Every call
to the renderer has the same number of rays (the last chunk padded), so it compiles once.

Camera paths: "Add keyframe" records the browser's camera; "Save path" writes the keyframes' path
(nerf/keyframes.py) as nerfstudio's camera_path.json (nerfpod.render.camera_path) into `paths_dir`, a local
folder (default ./camera_paths; never the workdir, which belongs to the training job).

Viewer cameras are viser's (OpenCV: looking down +z, +y down); nerfpod's poses are OpenGL (looking down -z,
+y up): nerf/cameras.py converts them (pose_from_opencv, pose_to_opencv).
"""
import dataclasses
import os
import signal
import socket
import sys
import threading
import time
import types

import jax
import numpy as np
from absl import flags, logging

from nerfpod import distributed
from nerfpod.render import camera_path as camera_paths
from nerfpod.render import renderer, video
from nerfpod.run import trained as run_trained
from nerfpod.workdir import failures, quiet
from nerfpod.errors import Command, UserError
from nerfpod.nerf import cameras, compositing, keyframes, pose_correction
from nerfpod.nerf import regions as nerf_regions

STILL_SECONDS = 0.2       # a camera unchanged this long is "still": render it at full resolution
THUMBNAIL_PIXELS = 64     # longest side of the images shown in the frustums
INITIAL_PULL_BACK = 1.3   # a new page's camera: this many times farther back than the first held-out camera
# The regions' colours, region k the k-th (mod 16): Sasha Trubetskoy's distinct colours, lightest left out.
REGION_COLOURS = ((230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
                  (70, 240, 240), (240, 50, 230), (210, 245, 60), (0, 128, 128), (220, 190, 255), (170, 110, 40),
                  (128, 0, 0), (128, 128, 0), (0, 0, 128), (128, 128, 128))


# The region of each point, one compiled program (not one per operation): the training cameras' regions.
_region_of = jax.jit(nerf_regions.region_of)


def region_colour(k: int) -> tuple[int, int, int]:
  return REGION_COLOURS[int(k) % len(REGION_COLOURS)]


def check_port_free(host: str, port: int) -> None:
  """Refuses a port that another program holds (viser would quietly move to the next free one, and the
  user would open the wrong page). Port 0: any free port, picked when the server starts.

  The probe binds as viser's server will (websockets on asyncio's create_server: SO_REUSEADDR on POSIX), so a
  port whose only users are connections in TIME_WAIT (a viewer that served pages and stopped, for a minute
  after) passes, as the server's own bind would; on Linux and macOS SO_REUSEADDR never binds over a listening
  socket, so a port another program serves on is still refused. (On Windows it would: left off there.)"""
  if port == 0:
    return
  with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
    if os.name == "posix":
      s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
      s.bind((host, port))
    except OSError as e:
      raise UserError(f"cannot listen on {host}:{port} ({e.strerror or e}); another program uses it: pick "
                      f"another with --port (or stop that program).") from None


def fit_resolution(width: int, height: int, longest: int) -> tuple[int, int]:
  """(width, height) scaled down (never up) so that the longer side is at most `longest`, aspect kept."""
  scale = min(1.0, longest / max(width, height, 1))
  return max(1, round(width * scale)), max(1, round(height * scale))


@dataclasses.dataclass
class Frame:
  """What a browser was last sent: the camera it was rendered for and the picture."""
  pose: np.ndarray               # (4, 4) OpenGL camera-to-world
  intrinsics: cameras.Intrinsics
  channel: str
  step: int                      # the checkpoint's step
  full: bool                     # full resolution (else the coarse preview)
  image: np.ndarray              # (H, W, 3) uint8, as sent
  seconds: float                 # render time
  version: int                   # the page camera's version it was rendered for (_Browser.version)


class _Browser:
  """One connected page: its camera's version (bumped by every change) and its render thread."""

  def __init__(self, client):
    self.client = client
    self.version = 0
    self.changed_at = 0.0
    self.wake = threading.Event()
    self.frames = 0
    self.coarse_frames = 0  # of those, the quick previews
    self.last: Frame | None = None
    self.closed = False

  def changed(self):
    self.version += 1
    self.changed_at = time.monotonic()
    self.wake.set()


class Viewer:
  """The viser server of one workdir; `close()` stops it. Construction restores the newest checkpoint (and
  refuses a workdir without one) and starts serving."""

  def __init__(self, workdir: str, host: str = "127.0.0.1", port: int = 7007, max_resolution: int = 512,
               coarse_resolution: int = 64, paths_dir: str = "camera_paths", poll_seconds: float = 2.0):
    try:
      import viser
    except ImportError:
      raise UserError("the viewer needs viser: pip install 'nerfpod[viewer]' (or pip install viser).") from None
    self.workdir, self.paths_dir, self.poll_seconds = str(workdir), paths_dir, poll_seconds
    run_trained.check(self.workdir)  # no config.json or checkpoint: one sentence before the port is looked at
    check_port_free(host, port)
    # The viewer is a process of its own, never one of a pod run's processes (it starts no jax.distributed):
    # its mesh, every device of this process (nerfpod.run.trained.restore's), is all the devices its runtime
    # has, so its renderer is not a program on a subset of anyone's slice.
    trained = run_trained.restore(self.workdir)
    self.config, self.comps = trained.config, trained.comps
    # A region model's regions (nerf_regions.Partition, as the restored model cuts them), drawn on the page.
    self.partition = self.comps.model.partition if self.comps.model.regions > 1 else None
    mesh = self.comps.mesh
    self.damaged = dict(trained.damaged)  # {step: why it does not read back whole}: skipped, never read again
    self._poll_error = ""  # the last poll's error, said once
    self.step, self.params = trained.step, trained.params  # the step on screen and its parameters
    self.chunk = max(mesh.size, self.config.orbit.chunk - self.config.orbit.chunk % mesh.size)
    self.max_resolution, self.coarse_resolution = int(max_resolution), int(coarse_resolution)
    self.keyframes: list[tuple[np.ndarray, float]] = []  # (OpenGL pose, vertical fov in degrees)
    self._browsers: dict[int, _Browser] = {}
    self._lock = threading.Lock()
    self._stop = threading.Event()
    self.server = viser.ViserServer(host=host, port=port, label="nerfpod", verbose=False)
    if port and self.server.get_port() != port:  # taken between our check and viser's bind
      self.server.stop()
      raise UserError(f"cannot listen on {host}:{port}: another program took it; pick another with --port.")
    self._build_page()
    self.server.on_client_connect(self._connected)
    self.server.on_client_disconnect(self._disconnected)
    self._poller = threading.Thread(target=self._poll_checkpoints, name="nerfpod-view-poll", daemon=True)
    self._poller.start()

  @property
  def url(self) -> str:
    host = self.server.get_host()
    return f"http://{'localhost' if host in ('0.0.0.0', '::') else host}:{self.server.get_port()}"

  # ---- checkpoints --------------------------------------------------------------------------------------

  def poll(self) -> bool:
    """One look for a newer checkpoint (the poller's, every `poll_seconds`): the newest step after the one
    on screen that reads back whole replaces it and every page is re-rendered; newer steps that do not read
    back whole are said on the page and skipped, and what is on screen stays. Returns whether the step on
    screen changed. An unlistable workdir (a bucket's network) or a checkpoint of another model is said once
    and looked at again at the next poll."""
    damaged = len(self.damaged)
    try:
      # (the one door's: damaged steps are said once, remembered in `self.damaged` and left in place)
      newest = run_trained.newer(self.workdir, self.comps, self.step, self.damaged)
    except Exception as e:  # noqa: BLE001 (keep serving the checkpoint on screen)
      reason = failures.reason(e)
      if reason != self._poll_error:
        print(f"nerfpod: view: could not read the newest checkpoint ({reason}); still showing step {self.step}, "
              f"trying again", file=sys.stderr, flush=True)
      self._poll_error = reason
      return False
    self._poll_error = ""
    if newest is not None:
      step, self.params = newest
      self.step = step  # after the parameters: a frame is never labelled with a step it does not show
    if newest is not None or len(self.damaged) != damaged:
      self._step_text.content = self._step_markdown()
    if newest is None:
      return False
    print(f"nerfpod: view: now showing step {self.step}", flush=True)
    self._all_changed()
    return True

  def _poll_checkpoints(self):
    while not self._stop.wait(self.poll_seconds):
      self.poll()

  # ---- rendering ----------------------------------------------------------------------------------------

  def render(self, pose_4x4, intr: cameras.Intrinsics, channel: str = "rgb", params=None,
             cancelled=lambda: False) -> np.ndarray | None:
    """One picture (H, W, 3) uint8 of `channel` from camera (pose, intrinsics); None if `cancelled()` turned
    true between chunks. Every renderer call has `self.chunk` rays (the last padded): one compilation."""
    params = self.params if params is None else params
    origins, directions = cameras.image_rays(np.asarray(pose_4x4, np.float64), intr,
                                             self.config.data.pixel_center)
    rays = renderer.render_rays(self.comps.renderer, params, self.comps.mesh, origins.reshape(-1, 3),
                              directions.reshape(-1, 3), self.chunk, cancelled=cancelled, fixed_chunk=True)
    if rays is None:
      return None
    frame = {k: v.reshape((intr.height, intr.width) + v.shape[1:]) for k, v in rays.items()}
    style = video.ChannelStyle.fit([frame], self.comps.near, self.comps.far)
    return style.image(channel, frame)

  def _render_for(self, browser: _Browser, full: bool) -> bool:
    """Renders the browser's current camera and sends it; False if the camera moved meanwhile."""
    camera = browser.client.camera
    version, step, params = browser.version, self.step, self.params
    width, height = camera.image_width, camera.image_height
    if width < 1 or height < 1:
      return True
    width, height = fit_resolution(width, height, int(self._max_resolution.value) if full
                                   else self.coarse_resolution)
    pose = cameras.pose_from_opencv(camera.wxyz, camera.position)
    intr = cameras.intrinsics_from_fov(camera.fov, width, height)
    channel = self._channel.value
    started = time.perf_counter()
    image = self.render(pose, intr, channel, params,
                        cancelled=lambda: browser.version != version or browser.closed or self._stop.is_set())
    if image is None:
      return False
    seconds = time.perf_counter() - started
    # PNG for the full picture (exact, what the tests compare); JPEG for the quick coarse ones.
    browser.client.scene.set_background_image(image, format="png" if full else "jpeg", jpeg_quality=90)
    browser.last = Frame(pose, intr, channel, step, full, image, seconds, version)
    browser.frames += 1
    browser.coarse_frames += not full
    if full:
      self._frame_text.content = f"{width}x{height} {channel} in {seconds * 1000:.0f} ms"
    return True

  def _render_loop(self, browser: _Browser):
    """A coarse picture as soon as the camera changes; the full one once it has been still."""
    coarse_done = full_done = -1
    while not (browser.closed or self._stop.is_set()):
      browser.wake.wait(0.05)
      browser.wake.clear()
      version = browser.version
      try:
        if version != coarse_done and version != full_done:
          if self._render_for(browser, full=False):
            coarse_done = version
        elif version != full_done and time.monotonic() - browser.changed_at >= STILL_SECONDS:
          if self._render_for(browser, full=True):
            full_done = version
      except Exception as e:  # noqa: BLE001 (a closed page mid-frame; keep the server alive)
        if not browser.closed:
          print(f"nerfpod: view: a frame failed ({e})", file=sys.stderr)
        time.sleep(0.2)

  # ---- the page -----------------------------------------------------------------------------------------

  def _step_markdown(self) -> str:
    """The step on screen, and why any newer step is not (e.g. "step 10 (step 20 does not read back whole:
    ...)")."""
    skipped = "; ".join(f"step {s} does not read back whole: `{r.replace('`', chr(39))}`"
                        for s, r in sorted(self.damaged.items(), reverse=True) if s > self.step)
    return f"**Checkpoint** step {self.step}{f' ({skipped})' if skipped else ''}  \n`{self.workdir}`"

  def _build_page(self):
    gui, scene = self.server.gui, self.server.scene
    gui.configure_theme(control_width="medium")
    self._step_text = gui.add_markdown(self._step_markdown())
    self._channel = gui.add_dropdown("Output", compositing.OUTPUTS, initial_value="rgb")
    self._max_resolution = gui.add_slider("Max resolution", 64, 2048, 32, self.max_resolution)
    self._show_cameras = gui.add_checkbox("Show cameras", True)
    if self.partition is not None:
      self._show_regions = gui.add_checkbox("Show regions", True)
      self._show_regions.on_update(lambda _: self._set_regions_visible(self._show_regions.value))
    self._frame_text = gui.add_markdown("")
    for handle in (self._channel, self._max_resolution):
      handle.on_update(lambda _: self._all_changed())
    self._show_cameras.on_update(lambda _: self._set_cameras_visible(self._show_cameras.value))
    with gui.add_folder("Camera path"):
      add, clear = gui.add_button("Add keyframe"), gui.add_button("Clear keyframes")
      intr = self.comps.scene.split(self.config.eval.split).intrinsics
      self._path_frames = gui.add_number("Frames", 120, min=1, max=10000, step=1)
      self._path_fps = gui.add_number("FPS", 30.0, min=1.0, max=240.0, step=1.0)
      self._path_width = gui.add_number("Width", intr.width, min=1, max=8192, step=1)
      self._path_height = gui.add_number("Height", intr.height, min=1, max=8192, step=1)
      self._path_loop = gui.add_checkbox("Loop", False)
      self._path_file = gui.add_text("File", "camera_path.json")
      save = gui.add_button("Save path")
      self._path_text = gui.add_markdown("No keyframes.")
    add.on_click(lambda event: self.add_keyframe(event.client.camera))
    clear.on_click(lambda _: self.clear_keyframes())
    save.on_click(lambda _: self._save_clicked())
    self._frustums = []
    scale = 0.03 * self._scene_extent()
    colours = {"train": (40, 90, 220)}
    corrections = pose_correction.of_params(self.params)
    train_positions = train_regions = None
    for name, split in self.comps.scene.splits.items():
      fov = cameras.fov_y(split.intrinsics)
      aspect = split.intrinsics.width / split.intrinsics.height
      poses = split.poses
      if name == "train" and corrections is not None:  # pose refinement: the poses the field was fitted to
        poses = pose_correction.corrected_poses(poses, corrections)
      colour = [colours.get(name, (230, 120, 30))] * len(poses)
      if name == "train" and self.partition is not None:  # each in its region's colour
        train_positions = np.asarray(poses, np.float64)[:, :3, 3]
        train_regions = np.asarray(_region_of(np.asarray(train_positions, np.float32), self.partition))
        colour = [region_colour(k) for k in train_regions]
      for i, (pose, image) in enumerate(zip(poses, split.images)):
        wxyz, position = cameras.pose_to_opencv(pose)
        self._frustums.append(scene.add_camera_frustum(
            f"/cameras/{name}/{i}", fov=float(fov), aspect=aspect, scale=scale, wxyz=wxyz, position=position,
            color=colour[i], image=_thumbnail(image), format="jpeg"))
    self._regions = [] if self.partition is None else self._draw_regions(train_positions, train_regions)

  def _draw_regions(self, camera_positions_Nx3, regions_N) -> list:
    """A region model's regions on the page, each in its colour: /regions/K/cell, the wireframe of the region
    within the field's box [-b, b]^3 (its ground polygon, nerf_regions.cells, at z = -b and z = b, joined at
    the corners); /regions/K/centre, a marker at the mean of its training cameras (the mean of its cell's
    corners at z = 0 where it has none); /regions/K/label, its name and camera count there (`regions_N`: the
    region of each camera). Returns their handles."""
    scene, bound = self.server.scene, float(self.config.model.hashgrid.bound)
    radius = 0.01 * self._scene_extent()
    handles = []
    for k, polygon in enumerate(nerf_regions.cells(self.partition, bound)):
      colour = region_colour(k)
      if len(polygon):
        ring = np.concatenate([polygon, np.roll(polygon, -1, axis=0)], axis=1).reshape(-1, 2, 2)  # its edges
        edges = [np.concatenate([ring, np.full(ring.shape[:2] + (1,), z)], axis=-1) for z in (-bound, bound)]
        upright = np.stack([np.pad(polygon, ((0, 0), (0, 1)), constant_values=-bound),
                            np.pad(polygon, ((0, 0), (0, 1)), constant_values=bound)], axis=1)
        handles.append(scene.add_line_segments(f"/regions/{k}/cell", np.concatenate(edges + [upright]), colour,
                                               thickness=2.0, thickness_units="screen"))
      mine = camera_positions_Nx3[regions_N == k] if camera_positions_Nx3 is not None else np.zeros((0, 3))
      if len(mine):
        centre = mine.mean(0)
      elif len(polygon):
        centre = np.append(polygon.mean(0), 0.0)
      else:  # a region that misses the box and holds no camera: nothing of the field's to show
        continue
      handles.append(scene.add_icosphere(f"/regions/{k}/centre", radius=radius, color=colour, position=centre))
      handles.append(scene.add_label(f"/regions/{k}/label", f"region {k} ({len(mine)} cameras)", position=centre))
    return handles

  def _set_regions_visible(self, visible: bool):
    for handle in self._regions:
      handle.visible = visible

  def _scene_extent(self) -> float:
    positions = np.concatenate([s.poses[:, :3, 3] for s in self.comps.scene.splits.values()])
    return float(np.linalg.norm(positions - positions.mean(0), axis=1).mean()) or 1.0

  def _set_cameras_visible(self, visible: bool):
    for frustum in self._frustums:
      frustum.visible = visible

  def _initial_view(self, camera):
    """A new page looks where the first held-out camera looks, with its field of view and the scene's up
    direction, from INITIAL_PULL_BACK times as far (so that the cameras around it are in sight too)."""
    split = self.comps.scene.split(self.config.eval.split)
    pose = np.asarray(split.poses[0], np.float64)
    up = np.concatenate([s.poses[:, :3, 1] for s in self.comps.scene.splits.values()]).mean(0)
    forward = -pose[:3, 2]
    distance = max(float(np.linalg.norm(pose[:3, 3])), 1e-3)  # to the point in front nearest the origin
    target = pose[:3, 3] + forward * distance
    camera.up_direction = up / (np.linalg.norm(up) or 1.0)
    camera.fov = cameras.fov_y(split.intrinsics)
    camera.position = target - forward * distance * INITIAL_PULL_BACK
    camera.look_at = target

  def _connected(self, client):
    browser = _Browser(client)
    with self._lock:
      self._browsers[client.client_id] = browser
    client.camera.on_update(lambda _: browser.changed())
    self._initial_view(client.camera)
    browser.changed()
    threading.Thread(target=self._render_loop, args=(browser,), name=f"nerfpod-view-{client.client_id}",
                     daemon=True).start()

  def _disconnected(self, client):
    with self._lock:
      browser = self._browsers.pop(client.client_id, None)
    if browser is not None:
      browser.closed = True
      browser.wake.set()

  def _all_changed(self):
    with self._lock:
      browsers = list(self._browsers.values())
    for browser in browsers:
      browser.changed()

  def browsers(self) -> dict[int, _Browser]:
    with self._lock:
      return dict(self._browsers)

  # ---- camera paths -------------------------------------------------------------------------------------

  def add_keyframe(self, camera):
    """Records a browser camera as the next keyframe and draws it."""
    pose = cameras.pose_from_opencv(camera.wxyz, camera.position)
    fov_deg = float(np.degrees(camera.fov))
    self.keyframes.append((pose, fov_deg))
    wxyz, position = cameras.pose_to_opencv(pose)
    self.server.scene.add_camera_frustum(
        f"/keyframes/{len(self.keyframes) - 1}", fov=float(camera.fov), aspect=camera.aspect or 1.0,
        scale=0.08 * self._scene_extent(), wxyz=wxyz, position=position, color=(230, 40, 40))
    self._path_text.content = f"{len(self.keyframes)} keyframe(s)."

  def clear_keyframes(self):
    for i in range(len(self.keyframes)):
      self.server.scene.remove_by_name(f"/keyframes/{i}")
    self.keyframes.clear()
    self._path_text.content = "No keyframes."

  def camera_path(self) -> camera_paths.CameraPath:
    """The path through the keyframes with the page's frame count, rate and size."""
    if not self.keyframes:
      raise UserError("add at least one keyframe before saving a camera path.")
    poses, fov = keyframes.interpolate(np.stack([p for p, _ in self.keyframes]),
                                       [f for _, f in self.keyframes], int(self._path_frames.value),
                                       loop=bool(self._path_loop.value))
    return camera_paths.CameraPath(poses, fov, int(self._path_width.value), int(self._path_height.value),
                                   float(self._path_fps.value))

  def save_path(self, name: str) -> str:
    """Writes the keyframes' path as paths_dir/name (nerfstudio's camera_path.json); returns the path."""
    name = name.strip()
    if not name or os.path.basename(name) != name:
      raise UserError(f"camera path file name {name!r} is not a plain file name; give e.g. camera_path.json.")
    path = self.camera_path()
    os.makedirs(self.paths_dir, exist_ok=True)
    out = os.path.join(self.paths_dir, name if name.endswith(".json") else name + ".json")
    partial = out + ".partial"  # whole or not at all: a renderer may be watching the folder
    # The keyframes under a key of our own: nerfstudio's viewer reads "keyframes" in its own (three.js)
    # layout when it loads a path, and would misread ours.
    camera_paths.write(partial, path, nerfpod_keyframes=[
        {"camera_to_world": pose.reshape(16).tolist(), "fov": fov} for pose, fov in self.keyframes],
        is_cycle=bool(self._path_loop.value))
    os.replace(partial, out)
    return out

  def _save_clicked(self):
    try:
      out = self.save_path(self._path_file.value)
    except (UserError, OSError) as e:
      self._path_text.content = f"Not saved: {e}"
      return
    self._path_text.content = f"Saved {int(self._path_frames.value)} frames to `{os.path.abspath(out)}`."
    print(f"nerfpod: view: saved camera path {out}", flush=True)

  def close(self):
    self._stop.set()
    for browser in self.browsers().values():
      browser.closed = True
      browser.wake.set()
    self.server.stop()


def _thumbnail(image_HxWx3) -> np.ndarray:
  """A small uint8 copy of a training image for its frustum (every other pixel until it fits)."""
  image = np.asarray(image_HxWx3)
  step = max(1, -(-max(image.shape[:2]) // THUMBNAIL_PIXELS))
  return video.to_uint8(image[::step, ::step])


ABOUT = "a live web viewer of a workdir (training may still be running)"
FLAGS = flags.FlagValues()  # its own: other subcommands define --workdir too
flags.DEFINE_string("workdir", None, "The training run's workdir (local or gs://).", flag_values=FLAGS)
flags.DEFINE_integer("port", 7007, "Port to serve the page on (0: any free one).", lower_bound=0,
                     upper_bound=65535, flag_values=FLAGS)
flags.DEFINE_string("host", "127.0.0.1", "Address to listen on (0.0.0.0: every interface).", flag_values=FLAGS)
flags.DEFINE_integer("max_resolution", 512, "Longest side of a still frame, pixels (the page's slider starts "
                     "here).", lower_bound=8, flag_values=FLAGS)
flags.DEFINE_integer("coarse_resolution", 64, "Longest side of the preview frames drawn while the camera moves, "
                     "pixels.", lower_bound=8, flag_values=FLAGS)
flags.DEFINE_string("paths_dir", "camera_paths", "Local folder where saved camera paths go.", flag_values=FLAGS)
flags.DEFINE_float("poll_seconds", 2.0, "How often to look for a newer checkpoint, seconds.", flag_values=FLAGS)
flags.register_validator("poll_seconds", lambda seconds: seconds > 0, "must be a positive number of seconds",
                         flag_values=FLAGS)


COMMAND = Command("nerfpod view", ABOUT, FLAGS, required=("workdir",), examples={"workdir": "runs/mine"})


def run(argv=None):
  """`nerfpod view ...` and `python -m nerfpod.view ...` (argv: the words after it; None: sys.argv[1:]): serves
  until Ctrl-C, then exits 0; a user's mistake is one sentence and exit code 2 (errors.Command.run)."""
  started = time.perf_counter()

  def serve():
    args = types.SimpleNamespace(**FLAGS.flag_values_dict())
    logging.set_verbosity(logging.WARNING)  # orbax and grain log at INFO; warnings (e.g. a scene's) stay shown
    quiet.quiet_library_reports()  # orbax's reports of what nerfpod asked for, or said already
    distributed.keep_off_absent_tpu()  # libtpu installed (the `tpu` extra) on a machine without a TPU: the CPU
    viewer = Viewer(args.workdir, args.host, args.port, args.max_resolution, args.coarse_resolution,
                    args.paths_dir, args.poll_seconds)
    try:
      print(f"nerfpod: view: step {viewer.step} of {args.workdir} at {viewer.url} (ready in "
            f"{time.perf_counter() - started:.1f} s; Ctrl-C stops)", flush=True)
      _serve_until_ctrl_c(viewer)
    finally:
      viewer.close()
  COMMAND.run(argv, serve)


def _serve_until_ctrl_c(viewer: Viewer) -> None:
  """Serving ends with Ctrl-C (SIGINT, caught here: the viewer's way to stop, not an interruption; where it is
  ignored, as in the background of a non-interactive shell, it stays ignored). Then it stops serving (for at
  most 10 s) and leaves at once, exit 0: the viewer writes nothing, so skipping the interpreter's clean-up of
  JAX's and the server's threads loses nothing; that clean-up can take long under load (docs/results.md), and
  Ctrl-C must stop the viewer."""
  stop = threading.Event()
  if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
    signal.signal(signal.SIGINT, lambda signum, frame: stop.set())
  while not stop.wait(1.0):  # (a timeout: the handler runs even where another thread took the signal)
    pass
  closing = threading.Thread(target=viewer.close, name="nerfpod-view-close", daemon=True)
  closing.start()
  closing.join(10)
  sys.stdout.flush()
  sys.stderr.flush()
  os._exit(0)


if __name__ == "__main__":
  run()
