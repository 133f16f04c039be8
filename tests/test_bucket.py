"""Scenes and workdirs in a bucket, against a Cloud Storage JSON API served on 127.0.0.1 (tests/gcs.py): every
loader reads a scene from gs:// to exactly what it reads from the same local folder (images_N/ and
data.kind=auto too); a missing object, or no way to reach the storage, is one sentence; and the smoke job
trained from a bucket scene into a bucket workdir, killed and run again, ends with the parameters, metrics
and orbit frames of the same job run uninterrupted on local files."""
import json
import time

import jax
import numpy as np
import pytest
from PIL import Image

import gcs
import procs
from conftest import smoke_config
from nerfpod.render import archive as archives
from nerfpod import scenes, storage
from nerfpod.workdir import checkpoints
from nerfpod.errors import UserError
from nerfpod.scenes import procedural
from test_captures import CAPTURE_KINDS as CAPTURES, data_config as _config, write_capture_kinds, write_images

SIZE = 16  # the loaders' scenes: the procedural scene's first frames at 16x16, images_2/ at 8x8


def write_blender(root, scene, splits=("train", "val", "test")):
  """`scene` (procedural: binary alpha on white) as a NeRF synthetic folder: RGBA PNGs and transforms files,
  which the Blender loader reads back to the same pixels, alphas and cameras."""
  for split in splits:
    part = scene.split(split)
    (root / split).mkdir(parents=True)
    frames = []
    for i in range(len(part)):
      rgba = np.concatenate([part.image_uint8(i), np.round(part.alpha(i) * 255).astype(np.uint8)[..., None]], -1)
      Image.fromarray(rgba).save(root / split / f"r_{i}.png")
      frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": part.poses[i].tolist()})
    (root / f"transforms_{split}.json").write_text(json.dumps(
        {"camera_angle_x": procedural.CAMERA_ANGLE_X, "frames": frames}))


def _half(image):
  return np.asarray(Image.fromarray(image).reduce(2))


@pytest.fixture(scope="module")
def local_scenes(tmp_path_factory):
  """One small scene in each format in a local folder: blender/, tiny.npz, and the captures (with images_2/)."""
  root = tmp_path_factory.mktemp("scenes")
  scene = procedural.make(SIZE, num_train=8, num_val=2, num_test=2)
  write_blender(root / "blender", scene)
  many = procedural.make(8, num_train=101, num_val=1, num_test=1).split("train")  # the npz holds > 100 frames
  np.savez(root / "tiny.npz", images=np.stack([many.image(i) for i in range(len(many))]), poses=many.poses,
           focal=np.float64(many.cameras.fx[0]))
  train = scene.split("train")
  images = [train.image_uint8(i) for i in range(len(train))]
  names = [f"r_{i}.png" for i in range(len(train))]
  poses, focal = train.poses.astype(np.float64), float(train.cameras.fx[0])
  write_capture_kinds(root, poses, focal, images, names, SIZE)
  for kind in CAPTURES:
    write_images(root / kind / "images_2", names, [_half(im) for im in images])
  return root


@pytest.fixture(scope="module")
def bucket_scenes(emulator, local_scenes):
  """The same scenes uploaded: gs://BUCKET/scenes/<name>."""
  return {p.name: emulator.upload(p, f"scenes/{p.name}") for p in sorted(local_scenes.iterdir())}


def assert_same_scene(got, want):
  assert (got.name, got.kind, got.space, got.near, got.far, got.background) == (
      want.name, want.kind, want.space, want.near, want.far, want.background)
  np.testing.assert_array_equal(got.transform, want.transform)
  assert sorted(got.splits) == sorted(want.splits)
  for name, split in want.splits.items():
    mine = got.split(name)
    assert mine.names == split.names and len(mine) > 0
    for field in ("pixels", "poses", "alphas", "bounds", "held"):
      a, b = getattr(mine, field), getattr(split, field)
      assert (a is None) == (b is None), field
      if b is not None:
        np.testing.assert_array_equal(a, b, err_msg=f"{name}.{field}")
    jax.tree.map(np.testing.assert_array_equal, mine.cameras, split.cameras)


LOADS = [("tiny", "tiny.npz", 1), ("blender", "blender", 1), ("blender", "blender", 2), ("llff", "llff", 1),
         ("llff", "llff", 2), ("colmap", "colmap_bin", 2), ("colmap", "colmap_txt", 1),
         ("nerfstudio", "nerfstudio", 1), ("nerfstudio", "nerfstudio", 2)]


@pytest.mark.parametrize("kind,name,downscale", LOADS, ids=[f"{n}-x{d}" for _, n, d in LOADS])
def test_each_loader_reads_a_bucket_scene_as_it_reads_the_local_folder(local_scenes, bucket_scenes, kind, name,
                                                                        downscale):
  if name.startswith("colmap"):
    pytest.importorskip("pycolmap")
  want = scenes.load(_config(kind, local_scenes / name, downscale=downscale))
  got = scenes.load(_config(kind, bucket_scenes[name], downscale=downscale))
  assert_same_scene(got, want)
  if downscale == 2 and kind != "blender":  # read from images_2/, not shrunk on loading
    assert int(got.split("train").cameras.width[0]) == SIZE // 2
  auto = scenes.load(_config("auto", bucket_scenes[name], downscale=downscale))
  assert auto.kind == kind
  assert_same_scene(auto, want)


def test_a_loader_reads_only_its_shard_of_a_bucket_scene(local_scenes, bucket_scenes):
  shards = scenes.Shards(count=2, held=(1,), host=1, hosts=2)
  want = scenes.load(_config("nerfstudio", local_scenes / "nerfstudio"), shards)
  got = scenes.load(_config("nerfstudio", bucket_scenes["nerfstudio"]), shards)
  assert_same_scene(got, want)
  assert got.split("train").held.tolist() == [1, 3, 5]


def test_a_missing_object_in_a_bucket_is_one_sentence_naming_it(emulator, local_scenes):
  url = f"gs://{emulator.bucket}/scenes"
  for kind in ("auto", "blender", "llff", "colmap", "nerfstudio", "tiny"):
    with pytest.raises(UserError, match=f"'{url}/nope' not found; set --config.data.path to "):
      scenes.load(_config(kind, f"{url}/nope"))
  with pytest.raises(UserError, match="data.path 'gs://no-such-bucket/scene' not found"):
    scenes.load(_config("auto", "gs://no-such-bucket/scene"))
  broken = emulator.upload(local_scenes / "blender", "broken/blender")
  emulator.delete("broken/blender/train/r_1.png")
  with pytest.raises(UserError, match=f"^frame './train/r_1': image file {broken}/train/r_1.png not found; "
                                      "restore it or remove the frame from the transforms file.$"):
    scenes.load(_config("blender", broken))
  capture = emulator.upload(local_scenes / "nerfstudio", "broken/nerfstudio")
  emulator.delete("broken/nerfstudio/images/r_2.png")
  with pytest.raises(UserError, match=rf"^{capture}/transforms.json lists 1 image\(s\) of its 8 frames that do not "
                                      rf"exist in {capture}/images/ \(images/r_2.png\); restore them"):
    scenes.load(_config("nerfstudio", capture))


def test_no_way_to_the_storage_is_one_sentence_at_once(emulator, monkeypatch):
  import portpicker
  closed = f"http://127.0.0.1:{portpicker.pick_unused_port()}"
  monkeypatch.setenv("STORAGE_EMULATOR_HOST", closed)
  started = time.monotonic()
  with pytest.raises(UserError, match=rf"^cannot reach Cloud Storage at 127.0.0.1:\d+ to read gs://nerfpod-test/"
                                      rf"scene \(Connection refused\); start the storage emulator that "
                                      rf"STORAGE_EMULATOR_HOST={closed} names, or unset it.$"):
    scenes.load(_config("auto", "gs://nerfpod-test/scene"))
  with pytest.raises(UserError, match=r"^cannot reach Cloud Storage at 127.0.0.1:\d+ to read gs://nerfpod-test/runs/a"):
    checkpoints.finished_steps("gs://nerfpod-test/runs/a")  # what --mode=eval, render and the viewer list first
  assert time.monotonic() - started < 5  # not a client's minute of retries


def test_an_unreachable_endpoint_is_refused_before_a_client_looks_for_credentials(monkeypatch):
  """Making a gcsfs client looks for credentials (on a machine without a network, a metadata server's
  retries: seconds); the endpoint is tried first, with the client's class only."""
  import fsspec
  import portpicker
  from nerfpod import storage
  monkeypatch.setenv("STORAGE_EMULATOR_HOST", f"http://127.0.0.1:{portpicker.pick_unused_port()}")
  monkeypatch.setattr(fsspec, "filesystem", lambda *args, **kwargs: pytest.fail("a client was made first"))
  with pytest.raises(UserError, match=r"^cannot reach Cloud Storage at 127.0.0.1:\d+ to read gs://nerfpod-test/run"):
    storage.check_reachable("gs://nerfpod-test/run")


def test_without_gcsfs_a_bucket_path_is_one_sentence_naming_the_extra(monkeypatch):
  import fsspec

  def missing(protocol, **kwargs):
    raise ImportError("Install gcsfs to access Google Storage")

  monkeypatch.setattr(fsspec, "filesystem", missing)
  monkeypatch.setattr(fsspec, "get_filesystem_class", missing)  # (what is looked up before a client is made)
  want = (r"^cannot read gs://nerfpod-test/{}: gs:// needs the gcsfs package, which is not installed; install the "
          r"gcs extra \(pip install 'nerfpod\[gcs\]'\).$")
  with pytest.raises(UserError, match=want.format("scene")):
    scenes.load(_config("auto", "gs://nerfpod-test/scene"))
  with pytest.raises(UserError, match=want.format("runs/a")):
    checkpoints.finished_steps("gs://nerfpod-test/runs/a")


def test_a_bucket_that_refuses_access_is_one_sentence(emulator, monkeypatch):
  """A server that answers every request 403, as Cloud Storage does without credentials for the bucket."""
  import http.server
  import threading

  class Refusing(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
      body = json.dumps({"error": {"code": 403, "message": "Anonymous caller does not have storage.objects.get "
                                                           "access to the Google Cloud Storage object."}}).encode()
      self.send_response(403)
      self.send_header("Content-Type", "application/json")
      self.send_header("Content-Length", str(len(body)))
      self.end_headers()
      self.wfile.write(body)

    def log_message(self, *args):
      pass

  server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Refusing)
  threading.Thread(target=server.serve_forever, daemon=True).start()
  import gcsfs
  monkeypatch.setenv("STORAGE_EMULATOR_HOST", f"http://127.0.0.1:{server.server_port}")
  gcsfs.GCSFileSystem.clear_instance_cache()  # a client for this server, not the emulator
  try:
    started = time.monotonic()
    with pytest.raises(UserError, match=r"^could not read gs://nerfpod-test/scene \(.*Anonymous caller does not "
                                        r"have storage.objects.get access.*\); check the path, and for gs:// the "
                                        r"network, your credentials \(gcloud auth application-default login"):
      scenes.load(_config("auto", "gs://nerfpod-test/scene"))
    assert time.monotonic() - started < 10  # refused, not retried
  finally:
    server.shutdown()
    gcsfs.GCSFileSystem.clear_instance_cache()


def test_a_camera_path_file_is_read_from_a_bucket(emulator, tmp_path):
  from nerfpod.render import camera_path
  from nerfpod.nerf import cameras
  poses = np.stack([cameras.spherical_pose(a, -30, 4) for a in (0, 120, 240)])
  camera_path.write(tmp_path / "path.json", camera_path.CameraPath(poses, np.array([40.0, 50.0, 60.0]), 80, 60,
                                                                   24.0), keyframes=[])
  url = emulator.upload(tmp_path / "path.json", "paths/path.json")
  got, want = camera_path.read(url), camera_path.read(tmp_path / "path.json")
  np.testing.assert_array_equal(got.poses, want.poses)
  np.testing.assert_array_equal(got.fov_y_deg, want.fov_y_deg)
  assert (got.width, got.height, got.fps) == (want.width, want.height, want.fps) == (80, 60, 24.0)
  with pytest.raises(UserError, match=f"^camera path {url}-nope does not exist"):
    camera_path.read(f"{url}-nope")


def test_paths_of_either_kind():
  assert storage.join("gs://b/scene", "images", "a.png") == "gs://b/scene/images/a.png"
  assert storage.normpath("gs://b/scene/./images/../x/") == "gs://b/scene/x"
  assert storage.join("/data/scene", "a.png") == "/data/scene/a.png"
  assert storage.normpath("/data/scene/../x/") == "/data/x"
  assert storage.is_url("gs://b") and not storage.is_url("/data/gs:/b")


# --- The smoke job from and into the bucket, killed and resumed, against the same job on local files. ---

RUN = {"data.kind": "blender", "train.log_every": 1, "train.image_every": 0, "checkpoint.every_steps": 10,
       "orbit.num_frames": 2}
RUN_TIMEOUT = 240


def _final(workdir):
  """(parameters, data position, step, metrics, orbit frames) of a finished workdir, local or gs://."""
  state, position, step = checkpoints.read_numpy(str(workdir))
  metrics = json.loads(storage.read_bytes(storage.join(str(workdir), "eval", "metrics.json")))
  orbit = archives.Archive.open(storage.join(str(workdir), archives.ORBIT))
  orbit.check_complete()
  return state["params"], position, step, metrics, [orbit.read_frame(i) for i in range(orbit.num_frames)]


@pytest.mark.slow
def test_the_smoke_job_from_and_into_a_bucket_is_killed_resumes_and_ends_as_a_local_run(emulator, tmp_path):
  scene = tmp_path / "smoke"  # the scene is named after its folder, here and in the bucket
  write_blender(scene, procedural.make(smoke_config().data.image_size))
  url = emulator.upload(scene, "scenes/smoke")
  workdir = f"gs://{emulator.bucket}/runs/smoke"
  logs = tmp_path / "logs"

  with procs.Run(tmp_path / "local", dict(RUN, **{"data.path": scene})) as run:
    run.wait_ok(RUN_TIMEOUT)
  want = _final(tmp_path / "local")

  # Killed in training, after the checkpoint of step 10 is in the bucket: its pipeline stalls at step 12.
  with procs.Run(workdir, dict(RUN, **{"data.path": url}), env=dict(emulator.env, NERFPOD_TEST_STALL_AT_STEP="12"),
                 log_dir=logs) as run:
    run.wait_for(lambda: "checkpoints/10/commit_success.txt" in emulator.files("runs/smoke"), RUN_TIMEOUT,
                 "checkpoint of step 10 in the bucket")
    run.kill()
  assert checkpoints.latest_step(workdir) == 10
  assert not any(name.startswith("eval/") for name in emulator.files("runs/smoke"))

  with procs.Run(workdir, dict(RUN, **{"data.path": url}), env=emulator.env, log_dir=logs) as run:
    run.wait_ok(RUN_TIMEOUT)
  out = run.output()
  assert "Traceback" not in out and "steps 10..20" in out, run.tails()  # resumed

  params, position, step, metrics, frames = _final(workdir)
  want_params, want_position, want_step, want_metrics, want_frames = want
  assert (step, position) == (want_step, want_position) == (20, {"next_step": 20})
  jax.tree.map(np.testing.assert_array_equal, params, want_params)
  assert metrics == want_metrics
  for got, wanted in zip(frames, want_frames):
    jax.tree.map(np.testing.assert_array_equal, got, wanted)
  files = emulator.files("runs/smoke")
  assert {"config.json", "scene.json", "renders/orbit_rgb.mp4"} <= set(files)
  # TensorBoard: the resumed run's scalars. (The killed run's own may still have been in its writer's buffer:
  # what it writes goes up at each flush, every 10 s, and that run may have been killed sooner.)
  events = tmp_path / "events"
  events.mkdir()
  for name in files:
    if name.startswith("events.out.tfevents."):
      (events / name).write_bytes(emulator.read(f"runs/smoke/{name}"))
  from tensorboard.backend.event_processing import event_accumulator
  board = event_accumulator.EventAccumulator(str(events), size_guidance={"scalars": 0})
  board.Reload()
  assert set(range(11, 21)) <= {e.step for e in board.Scalars("train/loss")}
  assert "lock.json" not in files  # released at the end

  # Evaluation alone (read-only, from the bucket's newest checkpoint): the same metrics, written again.
  emulator.delete("runs/smoke/eval/metrics.json")
  evaluated = procs.run_main("--mode=eval", "--config=configs/default.py:smoke", f"--workdir={workdir}",
                             *procs.overrides_to_flags(dict(RUN, **{"data.path": url})), env=emulator.env,
                             devices_per_process=8, timeout=RUN_TIMEOUT)
  assert evaluated.returncode == 0, evaluated.stderr[-3000:]
  assert json.loads(emulator.read("runs/smoke/eval/metrics.json")) == want_metrics

  missing = procs.run_main("--config=configs/default.py:smoke", f"--workdir={tmp_path / 'refused'}",
                           "--config.data.kind=blender", f"--config.data.path={url}-nope", env=emulator.env)
  assert missing.returncode == 2
  assert missing.stderr.strip().splitlines()[-1] == (
      f"nerfpod: error: Blender scene folder '{url}-nope' not found; set --config.data.path to a folder holding "
      f"transforms_train.json.")


def test_a_workdir_in_a_bucket_that_does_not_exist_is_named_as_such(emulator):
  """What the exports and the viewer read first, config.json: under a bucket that does not exist the sentence
  names the bucket, not a missing config.json (which it says where the bucket is there)."""
  from nerfpod.workdir import files as workdir_files
  with pytest.raises(UserError, match=r"^workdir gs://no-such-bucket/run: there is no bucket no-such-bucket \(or "
                                      r"these credentials cannot see it\); check the --workdir path\.$"):
    workdir_files.read_config("gs://no-such-bucket/run")
  with pytest.raises(UserError, match=rf"^workdir gs://{gcs.BUCKET}/no-run holds no config.json; "):
    workdir_files.read_config(f"gs://{gcs.BUCKET}/no-run")
