"""The viewer (nerfpod/view.py) in a real browser: Debian's chromium, headless, driven by selenium.

One smoke-trained workdir and one viewer serve every browser test. The picture the page shows is read back
from the browser's own canvas (viser's get_render: what WebGL drew, without the HTML panels on top) and
compared with nerfpod's renderer for the camera the page reports. Cameras are converted here with viser's
own rotation code (not the viewer's), so a wrong convention in the viewer cannot cancel out.
"""
import json
import os
import pathlib
import shutil
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import (ABANDONED_READ_REPORTS, LEGO, REPO, SMOKE_RUN_OVERRIDES, TINY_NPZ, damage_checkpoint, require,
                      smoke_config)
from nerfpod.workdir import files as workdir_files

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


def _wait(predicate, timeout: float, what: str):
  deadline = time.monotonic() + timeout
  while time.monotonic() < deadline:
    value = predicate()
    if value:
      return value
    time.sleep(0.05)
  raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _reference(viewer, client, frame, params=None):
  """nerfpod's own rendering (renderer.render_image, the evaluator's path) of the frame's camera, as uint8,
  after checking that camera is the page's (converted here independently of the viewer)."""
  import viser.transforms as tf
  from nerfpod.render import renderer, video
  camera = client.camera
  pose = np.eye(4)
  pose[:3, :3] = tf.SO3(np.asarray(camera.wxyz)).as_matrix() @ np.diag([1.0, -1.0, -1.0])  # OpenCV -> OpenGL
  pose[:3, 3] = camera.position
  np.testing.assert_allclose(frame.pose, pose, atol=1e-5)
  intr = frame.intrinsics
  np.testing.assert_allclose(intr.fy, 0.5 * intr.height / np.tan(0.5 * camera.fov), rtol=1e-6)
  assert (intr.cx, intr.cy) == (intr.width / 2, intr.height / 2)
  out = renderer.render_image(viewer.comps.renderer, viewer.params if params is None else params,
                            viewer.comps.mesh, frame.pose, intr, viewer.config.data.pixel_center, 512)
  return video.to_uint8(out["rgb"])


def _full_frame(viewer, client, after: int = 0, timeout: float = 60.0):
  """The first full-resolution frame sent to the page after its `after`-th frame, once the camera is still."""
  browser = viewer.browsers()[client.client_id]
  def done():
    frame = browser.last
    return frame if browser.frames > after and frame.full and frame.version == browser.version else None
  while True:  # and the camera still unchanged a moment later (the page settles after a move)
    frame = _wait(done, timeout, "a full-resolution frame")
    time.sleep(0.5)
    if done() is frame:
      return frame


def _canvas(client, frame):
  """What the browser's canvas shows, at the frame's size (viser's get_render of the page)."""
  return client.get_render(frame.intrinsics.height, frame.intrinsics.width, transport_format="png",
                           timeout=30)[..., :3]


def _assert_shows(picture, frame, reference):
  """The frame sent is nerfpod's rendering (to rounding), and the page shows it: to within 40 dB PSNR, as
  the browser may draw its canvas at a lower resolution than its size (viser lowers it when frames are
  slow, as with software WebGL), which resamples the picture."""
  assert picture.shape == reference.shape == frame.image.shape
  difference = np.abs(frame.image.astype(int) - reference)
  assert difference.max() <= 2, f"the frame differs from nerfpod's rendering by up to {difference.max()} / 255"
  mse = np.mean((picture / 255.0 - reference / 255.0) ** 2)
  psnr = 10 * np.log10(1.0 / max(mse, 1e-12))
  assert psnr > 40, f"the page shows another picture than nerfpod's rendering (PSNR {psnr:.1f} dB)"


def test_frame_sizes_and_cameras_of_the_page():
  from nerfpod import view
  assert view.fit_resolution(1000, 500, 256) == (256, 128)
  assert view.fit_resolution(200, 100, 256) == (200, 100)  # never enlarged
  assert view.fit_resolution(300, 1, 64) == (64, 1)


def test_a_busy_port_and_a_workdir_without_config_are_user_errors(tmp_path):
  from nerfpod import view
  from nerfpod.errors import UserError
  with socket.socket() as busy:
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    with pytest.raises(UserError, match="another program uses it"):
      view.check_port_free("127.0.0.1", busy.getsockname()[1])
  view.check_port_free("127.0.0.1", 0)
  with pytest.raises(UserError, match="holds no config.json"):
    workdir_files.read_config(str(tmp_path))
  (tmp_path / "config.json").write_text("{not json")
  with pytest.raises(UserError, match="is not valid JSON"):
    workdir_files.read_config(str(tmp_path))
  config = json.loads(smoke_config().to_json_best_effort())
  config["train"]["log_every"] = 0
  (tmp_path / "config.json").write_text(json.dumps(config))
  with pytest.raises(UserError, match="refuses .*train.log_every=0"):
    workdir_files.read_config(str(tmp_path))
  config["train"]["log_every"] = 5
  (tmp_path / "config.json").write_text(json.dumps(config))
  assert workdir_files.read_config(str(tmp_path)).train.log_every == 5


def test_a_missing_workdir_is_named_with_the_way_out(tmp_path):
  from nerfpod import view
  from nerfpod.errors import UserError
  missing = tmp_path / "no-such-run"
  with pytest.raises(UserError, match=f"workdir {missing} does not exist; check the --workdir path, or train "
                                      f"first .nerfpod train "):
    view.Viewer(str(missing), port=0)
  assert not missing.exists()


def _files(directory: pathlib.Path) -> dict[str, bytes]:
  return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def _warnings(capsys) -> list[str]:
  return [line for line in capsys.readouterr().err.splitlines() if line.startswith("nerfpod: warning:")]


def test_a_damaged_checkpoint_is_skipped_at_start_and_when_polled_and_left_in_place(trained_workdir, tmp_path,
                                                                                     capsys, monkeypatch):
  from nerfpod import view
  from nerfpod.workdir import checkpoints, quiet
  # What `nerfpod view` does (view.run): orbax's reads abandoned by a failed restore report nothing.
  monkeypatch.setattr(sys, "unraisablehook", quiet.quiet_abandoned_reads(sys.unraisablehook))
  workdir = tmp_path / "run"
  shutil.copytree(trained_workdir, workdir)
  ckpts = workdir / "checkpoints"
  for newer in set(checkpoints.finished_steps(str(workdir))) - {10, 20}:  # one written by the page test
    shutil.rmtree(ckpts / str(newer))
  damage_checkpoint(ckpts / "20")
  damaged = _files(ckpts / "20")
  capsys.readouterr()
  viewer = view.Viewer(str(workdir), port=0, poll_seconds=3600)  # polled by hand below
  try:
    # Start-up: the step before the damaged one, said in one stderr line and on the page.
    assert viewer.step == 10
    state, _, _ = checkpoints.read_numpy(str(workdir), 10)
    np.testing.assert_array_equal(np.asarray(viewer.params["params"]["coarse"]["rgb"]["bias"]),
                                  state["params"]["params"]["coarse"]["rgb"]["bias"])
    (line,) = _warnings(capsys)
    assert f"the checkpoint of step 20 in {ckpts} does not read back whole (" in line
    assert "left in place" in line and "falling back to the step before it" in line
    assert viewer._step_text.content.startswith("**Checkpoint** step 10 (step 20 does not read back whole: `")

    # A new step that is damaged: the page keeps step 10 and says why; it is read once, not at every poll.
    shutil.copytree(ckpts / "10", ckpts / "30")
    damage_checkpoint(ckpts / "30")
    assert not viewer.poll() and viewer.step == 10
    (line,) = _warnings(capsys)
    assert "the checkpoint of step 30" in line
    assert viewer._step_text.content.startswith(
        "**Checkpoint** step 10 (step 30 does not read back whole: `")
    assert "step 20 does not read back whole" in viewer._step_text.content
    assert not viewer.poll() and _warnings(capsys) == []

    # A newer step that reads back whole replaces step 10; the damaged ones are no longer mentioned.
    shutil.copytree(ckpts / "10", ckpts / "40")
    assert viewer.poll() and viewer.step == 40
    assert viewer._step_text.content.startswith("**Checkpoint** step 40  \n")
  finally:
    viewer.close()
  # Read-only: the damaged steps are where they were, byte for byte; nothing was set aside or added.
  assert _files(ckpts / "20") == damaged
  assert sorted(p.name for p in ckpts.iterdir()) == ["10", "20", "30", "40"]
  assert sorted(p.name for p in workdir.iterdir()) == sorted(p.name for p in trained_workdir.iterdir())


@pytest.fixture(scope="module")
def trained_workdir(smoke_run, tmp_path_factory):
  """A copy of the session's smoke run (conftest.smoke_run: 20 steps, checkpoints at 10 and 20), which a test
  below writes a checkpoint into."""
  workdir = tmp_path_factory.mktemp("view") / "run"
  shutil.copytree(smoke_run.workdir, workdir)
  return workdir


@pytest.fixture(scope="module")
def page(trained_workdir, tmp_path_factory):
  """(viewer, selenium driver, viser client) of one headless chromium page open on the viewer."""
  if CHROMIUM is None or CHROMEDRIVER is None:
    pytest.skip("chromium and chromedriver are not installed (apt-get install chromium chromium-driver)")
  webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
  from selenium.webdriver.chrome.service import Service
  from nerfpod import view
  viewer = view.Viewer(str(trained_workdir), port=0, max_resolution=1024, poll_seconds=0.5,
                       paths_dir=str(tmp_path_factory.mktemp("paths")))
  options = webdriver.ChromeOptions()
  options.binary_location = CHROMIUM
  for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=420,400",
                   "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--force-device-scale-factor=1"):
    options.add_argument(argument)
  driver = webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))
  try:
    driver.get(viewer.url)
    browsers = _wait(viewer.browsers, 60, "the page to connect")
    client = next(iter(browsers.values())).client
    yield viewer, driver, client
  finally:
    driver.quit()
    viewer.close()


def _click(driver, text: str):
  """Clicks the page's control labelled `text` (a button, or a checkbox's label) like a user would."""
  from selenium.webdriver.common.by import By
  element = driver.find_element(By.XPATH, f"//*[self::button or self::label][normalize-space()='{text}']")
  element.click()


@pytest.mark.slow
def test_page_shows_nerfpods_rendering_of_its_camera_and_follows_a_drag(page):
  viewer, driver, client = page
  _click(driver, "Show cameras")  # hide the frustums: the canvas then shows the rendered frame alone
  frame = _full_frame(viewer, client)
  assert frame.step == 20 and frame.channel == "rgb"
  assert (frame.intrinsics.width, frame.intrinsics.height) == (client.camera.image_width,
                                                                client.camera.image_height)
  picture = _canvas(client, frame)
  assert picture.std() > 5, "the page shows a blank picture"
  _assert_shows(picture, frame, _reference(viewer, client, frame))

  # Drag on the canvas: the camera orbits, a coarse preview comes first, then the full frame of the new view.
  from selenium.webdriver.common.action_chains import ActionChains
  from selenium.webdriver.common.by import By
  browser = viewer.browsers()[client.client_id]
  before, frames, coarse = np.array(client.camera.position), browser.frames, browser.coarse_frames
  canvas = driver.find_elements(By.TAG_NAME, "canvas")[0]
  # Left of the control panel and below the notification that software WebGL is in use.
  ActionChains(driver).move_to_element_with_offset(canvas, 30 - canvas.size["width"] // 2, canvas.size["height"] // 4) \
      .click_and_hold().move_by_offset(40, 0).move_by_offset(40, 5).release().perform()
  _wait(lambda: np.linalg.norm(client.camera.position - before) > 0.1, 20, "the drag to move the camera")
  moved = _full_frame(viewer, client, after=frames + 1)
  assert browser.coarse_frames > coarse, "no coarse preview came while the camera moved"
  _assert_shows(_canvas(client, moved), moved, _reference(viewer, client, moved))
  assert not np.allclose(moved.pose, frame.pose), "the frame was not rendered for the moved camera"
  after = _canvas(client, moved)  # the browser may also have resized its canvas meanwhile
  assert after.shape != picture.shape or np.abs(after.astype(int) - picture).mean() > 1, "the view did not change"


@pytest.mark.slow
def test_camera_set_through_viser_gives_that_view_and_the_other_channels(page):
  viewer, driver, client = page
  viewer._set_cameras_visible(False)  # the canvas shows the rendered frame alone (also when run by itself)
  frames = viewer.browsers()[client.client_id].frames
  client.camera.position = (0.5, -3.5, 2.0)
  client.camera.look_at = (0.0, 0.0, 0.0)
  frame = _full_frame(viewer, client, after=frames)
  np.testing.assert_allclose(frame.pose[:3, 3], [0.5, -3.5, 2.0], atol=1e-6)
  _assert_shows(_canvas(client, frame), frame, _reference(viewer, client, frame))
  # Depth through the page's dropdown is what the orbit videos would show for that camera.
  from nerfpod.render import renderer, video
  viewer._channel.value = "depth"
  depth = _wait(lambda: (f := viewer.browsers()[client.client_id].last).full and f.channel == "depth" and f,
                60, "a depth frame")
  out = renderer.render_image(viewer.comps.renderer, viewer.params, viewer.comps.mesh, depth.pose,
                            depth.intrinsics, viewer.config.data.pixel_center, 512)
  want = video.ChannelStyle.fit([out], viewer.comps.near, viewer.comps.far).image("depth", out)
  assert np.abs(depth.image.astype(int) - want).max() <= 2
  viewer._channel.value = "rgb"


@pytest.mark.slow
def test_a_checkpoint_written_while_the_page_is_open_appears(page, trained_workdir):
  import jax
  from selenium.webdriver.common.by import By
  from nerfpod.workdir import checkpoints
  viewer, driver, client = page
  viewer._set_cameras_visible(False)  # the canvas shows the rendered frame alone (also when run by itself)
  old = _full_frame(viewer, client)
  # The training run's next save, as it would write it: here, the same state with brighter colours.
  with checkpoints.Checkpoints(str(trained_workdir), 10, 5) as ckpt:
    state, position = ckpt.restore(viewer.comps.state_shapes)
    params = jax.tree_util.tree_map_with_path(
        lambda path, x: x + 1.0 if jax.tree_util.keystr(path).endswith("['rgb']['bias']") else x, state.params)
    ckpt.save(30, state.replace(params=params, step=state.step + 10), {"next_step": 30}, force=True)
  _wait(lambda: driver.find_elements(By.XPATH, "//*[contains(text(), 'step 30')]"), 30,
        "the page to show step 30")
  frame = _wait(lambda: (f := viewer.browsers()[client.client_id].last).step == 30 and f.full and f, 60,
                "a frame of step 30")
  picture = _canvas(client, frame)
  _assert_shows(picture, frame, _reference(viewer, client, frame, params))
  assert np.abs(picture.astype(int) - old.image).mean() > 1, "the new checkpoint shows the same picture"


@pytest.mark.slow
def test_a_path_saved_from_the_page_holds_the_keyframes_path(page):
  import viser.transforms as tf
  from nerfpod.render import camera_path
  from nerfpod.nerf import keyframes
  viewer, driver, client = page
  placed = []
  # The server's copy of the camera changes as soon as it is set; the browser's reports of its camera (which
  # replace that copy) follow, and one sent before the browser had moved could land after the click. So wait
  # for the browser's own report of the new camera before clicking.
  reports = []
  client.camera.on_update(lambda camera: reports.append((np.array(camera.position), np.array(camera.look_at))))
  for position in [(3.0, 0.0, 2.0), (0.0, 3.0, 2.5), (-3.0, 0.5, 1.5)]:
    client.camera.position = position
    client.camera.look_at = (0.0, 0.0, 0.0)
    _wait(lambda: reports and np.allclose(reports[-1][0], position, atol=1e-4)
          and np.allclose(reports[-1][1], 0.0, atol=1e-4), 10, "the browser to report the moved camera")
    _click(driver, "Add keyframe")
    _wait(lambda: len(viewer.keyframes) == len(placed) + 1, 10, "the keyframe to be added")
    pose = np.eye(4)
    pose[:3, :3] = tf.SO3(np.asarray(client.camera.wxyz)).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = position
    placed.append((pose, np.degrees(client.camera.fov)))
  viewer._path_frames.value = 8  # a short path: it is rendered below
  _click(driver, "Save path")
  saved = pathlib.Path(viewer.paths_dir) / "camera_path.json"
  _wait(saved.exists, 10, "the saved camera_path.json")
  path = camera_path.read(saved)
  want_poses, want_fov = keyframes.interpolate(np.stack([p for p, _ in placed]), [f for _, f in placed], 8)
  assert len(path) == 8 and (path.width, path.height) == (32, 32) and path.fps == 30
  np.testing.assert_allclose(path.poses, want_poses, atol=1e-6)
  np.testing.assert_allclose(path.fov_y_deg, want_fov, atol=1e-6)
  np.testing.assert_allclose(path.poses[0], placed[0][0], atol=1e-6)   # it starts and ends on the keyframes
  np.testing.assert_allclose(path.poses[-1], placed[-1][0], atol=1e-6)
  saved_keyframes = json.loads(saved.read_text())["nerfpod_keyframes"]
  np.testing.assert_allclose([np.reshape(k["camera_to_world"], (4, 4)) for k in saved_keyframes],
                             [p for p, _ in placed], atol=1e-6)

  # --mode=render renders the saved path into the archive: its cameras are the file's.
  from nerfpod.render import archive
  from nerfpod.run import modes
  config = smoke_config(**dict(SMOKE_RUN_OVERRIDES, **{"orbit.path": "file", "orbit.path_file": str(saved)}))
  modes.render_workdir(config, str(viewer.workdir))
  rendered = archive.Archive.open(f"{viewer.workdir}/renders/orbit.zarr")
  np.testing.assert_allclose(rendered.attributes["poses"], path.poses, atol=1e-6)
  assert rendered.read_frame(0)["rgb"].shape == (32, 32, 3)


def _view(*args, timeout=120):
  from procs import environment
  return subprocess.run([sys.executable, "-m", "nerfpod.view", *args], cwd=REPO, env=environment(1),
                        capture_output=True, text=True, timeout=timeout)


def _assert_one_sentence(result, *words):
  assert result.returncode == 2, result.stderr
  lines = [line for line in result.stderr.splitlines() if line.startswith("nerfpod: error:")]
  assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
  for word in words:
    assert word in lines[0], lines[0]


@pytest.mark.slow
def test_bad_workdirs_and_a_busy_port_are_one_sentence(trained_workdir, tmp_path):
  empty = tmp_path / "fresh"
  empty.mkdir()
  shutil.copy(trained_workdir / "config.json", empty / "config.json")  # a run that has not saved yet
  _assert_one_sentence(_view(f"--workdir={empty}", "--port=0"), "no checkpoint")
  _assert_one_sentence(_view(f"--workdir={tmp_path / 'missing'}", "--port=0"),
                       f"workdir {tmp_path / 'missing'} does not exist", "--workdir", "nerfpod train")
  no_config = tmp_path / "no-config"
  no_config.mkdir()
  _assert_one_sentence(_view(f"--workdir={no_config}", "--port=0"), "no config.json")
  # Every step damaged: one sentence naming each, and nothing of orbax's abandoned reads after it.
  damaged = tmp_path / "damaged"
  shutil.copytree(trained_workdir, damaged)
  steps = sorted(int(p.name) for p in (damaged / "checkpoints").iterdir())
  for step in steps:
    damage_checkpoint(damaged / "checkpoints" / str(step))
  result = _view(f"--workdir={damaged}", "--port=0")
  _assert_one_sentence(result, f"no checkpoint in {damaged / 'checkpoints'} reads back whole",
                       *(f"step {step}: " for step in steps), "train again")
  warnings = [line for line in result.stderr.splitlines() if line.startswith("nerfpod: warning:")]
  assert len(warnings) == len(steps), result.stderr
  for noise in ABANDONED_READ_REPORTS:
    assert noise not in result.stderr, result.stderr
  # No network here: one sentence at once (before a bucket client's minute of retries), naming the workdir.
  _assert_one_sentence(_view("--workdir=gs://nerfpod-no-such-bucket-for-tests/run", "--port=0"),
                       "cannot reach Cloud Storage", "gs://nerfpod-no-such-bucket-for-tests/run")
  with socket.socket() as busy:
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    _assert_one_sentence(_view(f"--workdir={trained_workdir}", f"--port={port}"), f"127.0.0.1:{port}", "--port")


@pytest.mark.slow
def test_nerfpod_view_serves_the_page_and_stops_on_ctrl_c(trained_workdir):
  import signal
  import urllib.request
  from procs import environment
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
  before = sorted(p.name for p in (trained_workdir / "checkpoints").iterdir())
  # The viewer starts as from a terminal, with SIGINT's default action, also where the suite itself was started
  # in the background of a non-interactive shell, which ignores SIGINT (the viewer then rightly ignores it
  # too, as any program would: an ignored signal stays ignored in a child, a caught one does not).
  signal.signal(signal.SIGINT, signal.default_int_handler)
  proc = subprocess.Popen([sys.executable, "-m", "nerfpod.view", f"--workdir={trained_workdir}", f"--port={port}"],
                          cwd=REPO, env=environment(1), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
  try:
    lines = []
    while not lines or (lines[-1] and not lines[-1].startswith("nerfpod: view:")):
      lines.append(proc.stdout.readline())  # '' at the end of the output
    from nerfpod.workdir import checkpoints
    step = checkpoints.latest_step(str(trained_workdir))  # 20, or 30 after the test that writes one
    assert f"step {step} of {trained_workdir} at http://127.0.0.1:{port}" in lines[-1], "".join(lines)
    page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10).read().decode()
    assert "<html" in page.lower()
    assert sorted(p.name for p in (trained_workdir / "checkpoints").iterdir()) == before, "the viewer wrote"
    proc.send_signal(signal.SIGINT)
    # communicate, not wait: the viewer's stderr (never read until now) may fill its pipe, and a process
    # blocked writing to a full pipe never exits.
    try:
      _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
      raise AssertionError(f"the viewer did not exit within 60 s of SIGINT; {_signal_state(proc.pid)}") from None
    assert proc.returncode == 0, err[-2000:]
  finally:
    proc.kill()
    proc.wait()


def _signal_state(pid: int) -> str:
  """A process's signal masks and its threads' states, from /proc (what a test says when a signal went
  unanswered)."""
  try:
    status = pathlib.Path(f"/proc/{pid}/status").read_text().splitlines()
    threads = [pathlib.Path(f"/proc/{pid}/task/{t}/status").read_text().splitlines()
               for t in os.listdir(f"/proc/{pid}/task")]
  except OSError as e:
    return f"no /proc state ({e})"
  masks = [line for line in status if line.split(":")[0] in ("SigPnd", "ShdPnd", "SigBlk", "SigIgn", "SigCgt")]
  states = [" ".join(line.split(":", 1)[1].strip() for line in t if line.split(":")[0] in ("Name", "State", "SigBlk"))
            for t in threads]
  return "; ".join(masks) + "; threads: " + ", ".join(states)


def _workdir_of(config, workdir):
  """A workdir as training writes it, of `config`'s initial state (step 0): config.json and a checkpoint."""
  from nerfpod.run import components
  from nerfpod.workdir import checkpoints
  comps = components.build(config)
  state = comps.init_state()
  workdir_files.write_config(str(workdir), json.loads(config.to_json_best_effort()))
  with checkpoints.Checkpoints(str(workdir), 10, 2) as ckpt:
    ckpt.save(0, state, {"next_step": 0}, force=True)
  return comps, state.params


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["procedural", "tiny", "blender"])
def test_the_viewer_builds_every_scene_kind_from_config_json_alone(kind, tmp_path):
  from nerfpod import view
  from nerfpod.render import renderer, video
  from nerfpod.nerf import cameras
  from conftest import load_config
  if kind == "procedural":
    config = smoke_config()
  elif kind == "tiny":
    config = load_config("tiny_fast", f"path={require(TINY_NPZ)},smoke")
  else:
    config = load_config("blender", "smoke")
    config.data.path = str(require(LEGO))
    config.eval.split = "val"  # the shared lego_400 has no test split
  comps, params = _workdir_of(config, tmp_path / "run")
  viewer = view.Viewer(str(tmp_path / "run"), port=0)
  try:
    assert viewer.step == 0 and viewer.comps.scene.name == comps.scene.name
    split = comps.scene.split(config.eval.split)
    intr = cameras.intrinsics_from_fov(cameras.fov_y(split.intrinsics), 24, 20)
    got = viewer.render(split.poses[0], intr, "rgb")
    want = renderer.render_image(comps.renderer, params, comps.mesh, split.poses[0], intr, config.data.pixel_center,
                               256)
    assert got.shape == (20, 24, 3)
    assert np.abs(got.astype(int) - video.to_uint8(want["rgb"])).max() <= 1
    assert len(viewer._frustums) == sum(len(s) for s in comps.scene.splits.values())
  finally:
    viewer.close()


def _time_wait_port() -> int:
  """A port whose only user is a connection in TIME_WAIT, as a viewer that served pages leaves it for a minute
  after it stops: the server side closes first (so TIME_WAIT lands on the server's port), then the client,
  then the listener."""
  with socket.socket() as listener:
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as viser's server (asyncio) binds
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    client = socket.create_connection(("127.0.0.1", port))
    served, _ = listener.accept()
    served.close()
    client.recv(1)  # the server's FIN arrived
    client.close()
    time.sleep(0.1)  # the client's FIN reaches the server's side: TIME_WAIT
  return port


def test_a_port_left_in_time_wait_by_a_stopped_viewer_is_free(tmp_path):
  from nerfpod import view
  port = _time_wait_port()
  with socket.socket() as plain:  # the connection really is in TIME_WAIT: a bind without SO_REUSEADDR fails
    with pytest.raises(OSError):
      plain.bind(("127.0.0.1", port))
  view.check_port_free("127.0.0.1", port)  # viser's own bind would succeed: so does the check


@pytest.mark.parametrize("reuse", [False, True])
def test_a_port_a_live_listener_holds_is_refused_even_by_a_probe_with_so_reuseaddr(reuse):
  from nerfpod import view
  from nerfpod.errors import UserError
  with socket.socket() as busy:
    if reuse:  # a server that binds as viser's does (SO_REUSEADDR): still a listener, still refused
      busy.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    with pytest.raises(UserError, match=rf"cannot listen on 127.0.0.1:{port} \(.*\); another program uses it: pick "
                                        r"another with --port \(or stop that program\)."):
      view.check_port_free("127.0.0.1", port)


# In a fresh interpreter (the tests' own has picked the CPU already): what `nerfpod view` leaves JAX's platform
# at, stopping at a missing workdir; no GPU plugin is pretended (as tests/test_platform.py does).
VIEW_PLATFORM_PROBE = r"""
import json, sys, jax
from nerfpod import distributed, view
distributed.pjrt_plugins = lambda: set()
try:
  view.run([f"--workdir={sys.argv[1]}"])
except SystemExit as e:
  code = e.code
print(json.dumps({"code": code, "platforms": jax.config.jax_platforms}))
"""


def test_the_viewer_keeps_jax_off_an_absent_tpu_as_train_and_export_do(tmp_path):
  pytest.importorskip("libtpu")  # the `tpu` extra: its runtime installed, no TPU chip here
  env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
  env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
  done = subprocess.run([sys.executable, "-c", VIEW_PLATFORM_PROBE, str(tmp_path / "missing")], env=env,
                        capture_output=True, text=True, timeout=120)
  assert done.returncode == 0, done.stderr
  out = json.loads(done.stdout.strip().splitlines()[-1])
  assert out == {"code": 2, "platforms": "cpu"}, (out, done.stderr[-2000:])
  assert "TPU" not in done.stderr, done.stderr[-2000:]
