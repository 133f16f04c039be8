"""data.shards: each host reads only the training frames of its shards, and the global batches depend on
(seed, step, shards), never on the number of hosts.

Quick tests check the draw, the loaders' frame selection, the memory check and the refusals on small
in-memory scenes; the slow ones run real 1 x 8 and 2 x 4 device jobs on the shared lego (Blender).
"""
import json
import types
from signal import SIGTERM

import numpy as np
import pytest
from PIL import Image

import procs
from conftest import LEGO, require, smoke_config
from nerfpod import data, distributed, schema, scenes
from nerfpod.run import components, modes
from nerfpod.workdir import checkpoints, files as workdir_files
from nerfpod.errors import UserError
from nerfpod.nerf import cameras
from nerfpod.scenes import Shards, blender, procedural


@pytest.fixture(scope="module")
def scene():
  return procedural.make(image_size=12, num_train=10, num_val=2, num_test=2)


def _host_split(full, count, host, hosts):
  per = count // hosts
  return full.keep(Shards(count, tuple(range(host * per, (host + 1) * per))).frames(len(full)))


def _global_batch(full, count, hosts, step, batch_size=32, seed=5):
  """What `hosts` hosts, each holding only its shards' frames, load at `step`, concatenated in host order."""
  per = batch_size // hosts
  pieces = [data.LocalRayBatch(_host_split(full, count, p, hosts), seed, batch_size, slice(p * per, (p + 1) * per),
                               0.5, count).map(step) for p in range(hosts)]
  return {k: np.concatenate([p[k] for p in pieces]) for k in ("origins", "directions", "rgb", "alpha", "ray_ids")}


def test_global_batches_depend_on_the_shard_count_not_on_the_host_count(scene):
  full = scene.split("train")
  for step in (0, 7):
    one = _global_batch(full, 4, 1, step)
    for hosts in (2, 4):
      many = _global_batch(full, 4, hosts, step)
      for key in one:
        np.testing.assert_array_equal(many[key], one[key])
    np.testing.assert_array_equal(one["ray_ids"], np.arange(32))


def test_sub_batch_s_is_drawn_from_shard_s_frames_by_seed_step_and_s(scene):
  full, count, step = scene.split("train"), 4, 3
  got = _global_batch(full, count, 2, step)["rgb"]
  for s in range(count):  # brute force: shard s's pixels side by side, indexed by the (seed, step, s) draw
    pixels = np.concatenate([full.image_uint8(i).reshape(-1, 3) for i in range(s, len(full), count)])
    want = pixels[np.random.default_rng([5, step, s]).integers(0, len(pixels), size=8, dtype=np.int64)]
    np.testing.assert_array_equal(np.round(got[8 * s:8 * (s + 1)] * 255).astype(np.uint8), want)


def test_one_shard_is_todays_draw_bit_for_bit(scene):
  config = smoke_config(**{"data.image_size": 12})
  assert config.data.shards == 1
  plain = scenes.load(config.data).split("train")
  sharded = scenes.load(config.data, Shards()).split("train")
  assert sharded.held is None and np.array_equal(sharded.pixels, plain.pixels)
  batch = data.LocalRayBatch(sharded, 5, 32, slice(8, 24), 0.5, 1).map(4)
  flat = np.random.default_rng([5, 4]).integers(0, plain.num_pixels, size=32, dtype=np.int64)[8:24]
  np.testing.assert_array_equal(batch["rgb"], plain.pixels[flat].astype(np.float32) / np.float32(255))


def test_a_host_holds_its_shards_pixels_and_every_frames_camera(scene):
  full = scene.split("train")
  half = _host_split(full, 4, 1, 2)  # shards 2, 3: frames 2, 3, 6, 7
  assert half.held.tolist() == [2, 3, 6, 7] and len(half) == len(full)
  assert half.pixels.shape == (4 * 12 * 12, 3) and half.alphas.shape == (4 * 12 * 12,)
  np.testing.assert_array_equal(half.poses, full.poses)
  np.testing.assert_array_equal(half.image_uint8(6), full.image_uint8(6))
  with pytest.raises(UserError, match="another host's shard"):
    half.image(0)


def _write_blender(root, frames=6, size=4):
  """A Blender scene of `frames` solid-colour training images (frame i has red = 10 i) and 2 val ones."""
  for split, n in (("train", frames), ("val", 2)):
    (root / split).mkdir(parents=True)
    meta = {"camera_angle_x": 0.69, "frames": []}
    for i in range(n):
      colour = np.array([10 * i, 0, 0, 255], np.uint8)
      Image.fromarray(np.tile(colour, (size, size, 1))).save(root / split / f"r_{i}.png")
      meta["frames"].append({"file_path": f"./{split}/r_{i}",
                             "transform_matrix": cameras.spherical_pose(30.0 * i, -30.0, 4.0).tolist()})
    (root / f"transforms_{split}.json").write_text(json.dumps(meta))


def test_the_blender_loader_reads_only_the_frames_of_the_hosts_shards(tmp_path, monkeypatch):
  _write_blender(tmp_path)
  read = []
  original = blender._read_image
  monkeypatch.setattr(blender, "_read_image", lambda path, *a: read.append(path) or original(path, *a))
  scene = blender.read(str(tmp_path), shards=Shards(3, (1,)))
  train = scene.split("train")
  assert sorted(p.rsplit("/", 2)[-2] + "/" + p.rsplit("/", 1)[-1] for p in read) == [
      "train/r_1.png", "train/r_4.png", "val/r_0.png", "val/r_1.png"]
  assert train.held.tolist() == [1, 4] and len(train) == 6 and train.pixels.shape == (2 * 16, 3)
  assert train.image_uint8(4)[0, 0, 0] == 40 and len(scene.split("val").pixels) == 2 * 16


def test_a_shard_that_would_not_fit_is_refused_before_reading_naming_the_hosts_that_would(tmp_path, monkeypatch):
  _write_blender(tmp_path, frames=8)
  monkeypatch.setattr(blender, "_read_image", lambda *a: pytest.fail("an image was read"))
  frame = 4 * 4 * 4  # RGBA bytes of one 4x4 frame
  budget = 2 * frame + 2 * frame  # two val frames and two training frames
  with pytest.raises(UserError) as e:
    blender.read(str(tmp_path), shards=Shards(2, (0,), 0, 2, budget))
  message = str(e.value)
  assert message.count(". ") == 0 and message.endswith(".")
  assert "host 0 would hold 4 of 8 training images" in message and "memory budget" in message
  assert "run on 4 hosts (data.shards=4, a multiple of 4;" in message
  with pytest.raises(UserError, match=r"run on these 2 hosts \(data.shards=2, a multiple of 2;"):
    blender.read(str(tmp_path), shards=Shards(1, (0,), 0, 2, budget + 2 * frame))  # one shard, held by both
  with pytest.raises(UserError, match="not even one image per host would fit"):
    blender.read(str(tmp_path), shards=Shards(2, (0,), 0, 2, 2 * frame))


def test_the_budget_comes_from_the_config_and_in_memory_scenes_are_checked_too():
  config = smoke_config(**{"data.image_size": 12, "data.host_memory_gib": 1e-5})
  shards = components.host_shards(config)
  assert shards == Shards(1, (0,), 0, 1, int(1e-5 * 2**30))
  with pytest.raises(UserError, match=r"host 0 would hold 100 of 100 training images .*run on \d+ hosts"):
    scenes.load(config.data, shards)
  assert components.host_memory_budget_bytes(smoke_config()) > 0  # half the machine's memory


def test_a_shard_count_the_hosts_do_not_divide_is_refused_in_one_sentence():
  device = lambda p: types.SimpleNamespace(process_index=p)
  mesh = types.SimpleNamespace(devices=np.array([device(p) for p in (0, 0, 1, 1, 2, 2)]))
  with pytest.raises(UserError) as e:
    distributed.local_shards(4, mesh)
  assert str(e.value) == ("data.shards=4 does not split over the 3 hosts of this run; make it a multiple of the "
                          "host count (e.g. --config.data.shards=6), and of every host count the run may be "
                          "resumed on.")
  assert distributed.local_shards(6, mesh) == ((0, 1), 0, 3)
  assert distributed.local_shards(1, mesh) == ((0,), 0, 3)  # one shard: every host holds every frame
  with pytest.raises(UserError, match="data.shards=12 is more than the 10 training images"):
    Shards(12, (0,)).check(np.ones(10), 0, "scene")


def test_the_schema_takes_the_shard_count_and_refuses_what_cannot_work():
  assert schema.problems(smoke_config(**{"data.shards": 4})) == []
  assert "data.shards=0 is not valid" in schema.problems(smoke_config(**{"data.shards": 0}))[0]
  [message] = schema.problems(smoke_config(**{"data.shards": 3, "train.batch_size": 3 * 7 + 1}))
  assert "does not split into data.shards=3 equal sub-batches" in message
  [message] = schema.problems(smoke_config(**{"data.shards": 2, "eval.split": "train"}))
  assert "eval.split=train cannot be evaluated with data.shards=2" in message


def test_resuming_with_another_shard_count_is_refused_but_another_budget_is_not():
  saved = smoke_config().to_dict()
  assert workdir_files.incompatible_fields(saved, smoke_config(**{"data.shards": 4})) == ["data.shards"]
  assert workdir_files.incompatible_fields(saved, smoke_config(**{"data.host_memory_gib": 8.0})) == []


# Whole runs on the shared lego: 24 steps of the smoke job on its Blender frames at 50x50 (downscale 8).
NUM_STEPS = 24
LEGO_OVERRIDES = {"data.kind": "blender", "data.downscale": 8, "data.shards": 4, "eval.split": "val",
                  "train.num_steps": NUM_STEPS, "train.batch_size": 128, "checkpoint.every_steps": 6,
                  "checkpoint.max_to_keep": 3, "train.log_every": 10, "train.image_every": 0,
                  "eval.max_views": 1, "orbit.render_after_training": False}
THROTTLED = dict(LEGO_OVERRIDES, **{"checkpoint.every_steps": 2})
RUN_TIMEOUT = 240  # seconds one run may take on a loaded 2-core machine


def _params_equal(workdir, reference):
  state, position, step = checkpoints.read_numpy(str(workdir))
  assert step == NUM_STEPS and position == {"next_step": NUM_STEPS}
  import jax
  for (path, a), (_, b) in zip(jax.tree.leaves_with_path(state["params"]), jax.tree.leaves_with_path(reference)):
    np.testing.assert_array_equal(a, b, err_msg=jax.tree_util.keystr(path))


@pytest.fixture(scope="module")
def lego_reference(tmp_path_factory):
  """The lego job's final parameters on 1 process x 8 devices (this pytest process), 4 shards."""
  overrides = dict(LEGO_OVERRIDES, **{"data.path": str(require(LEGO))})
  workdir = tmp_path_factory.mktemp("lego_reference")
  modes.train_and_evaluate(smoke_config(**overrides), str(workdir))
  return {"overrides": overrides, "params": checkpoints.read_numpy(str(workdir))[0]["params"]}


@pytest.mark.slow
def test_two_hosts_holding_half_the_frames_each_train_the_one_host_model(lego_reference, tmp_path):
  with procs.Run(tmp_path / "pod", lego_reference["overrides"], num_processes=2, devices_per_process=4) as pod:
    pod.wait_ok(RUN_TIMEOUT)
  for p in range(2):
    assert f"host {p} holds 50 of 100 training images (0.5 MiB)" in pod.output(p), pod.tails()
  # 2 x 4 and 1 x 8 devices sum the gradient mean in one order (distributed.ordered_mean): the same bits.
  _params_equal(tmp_path / "pod", lego_reference["params"])


@pytest.mark.slow
def test_a_run_stopped_on_two_hosts_continues_exactly_on_one(lego_reference, tmp_path):
  workdir = tmp_path / "pod"
  throttled = dict(THROTTLED, **{"data.path": lego_reference["overrides"]["data.path"]})
  with procs.Run(workdir, throttled, num_processes=2, devices_per_process=4) as pod:
    pod.wait_for(lambda: "step      1/" in pod.output(0), RUN_TIMEOUT, "first training step")
    pod.signal(1, SIGTERM)
    assert pod.wait(RUN_TIMEOUT) == [75, 75], pod.tails()
  agreed = checkpoints.latest_step(str(workdir))
  assert 0 < agreed < NUM_STEPS
  with procs.Run(workdir, lego_reference["overrides"], devices_per_process=8) as one:
    one.wait_ok(RUN_TIMEOUT)
  assert f"1 process(es), 8 device(s), steps {agreed}..{NUM_STEPS}" in one.output(0), one.tails()
  assert "host 0 holds 100 of 100 training images" in one.output(0)
  _params_equal(workdir, lego_reference["params"])


@pytest.mark.slow
def test_a_run_whose_shard_would_not_fit_exits_2_with_one_sentence(tmp_path):
  done = procs.run_main("--config=configs/default.py:smoke", f"--workdir={tmp_path / 'run'}",
                        "--config.data.host_memory_gib=0.0001", devices_per_process=1)
  errors = [l for l in done.stderr.splitlines() if l.startswith("nerfpod: error:")]
  assert done.returncode == 2 and len(errors) == 1 and "Traceback" not in done.stderr, done.stderr
  assert "more than its memory budget" in errors[0] and "run on" in errors[0]


def test_a_capture_loader_reads_only_the_frames_of_the_hosts_shards(tmp_path, monkeypatch):
  from nerfpod.scenes import capture
  (tmp_path / "images").mkdir()
  frames = []
  for i in range(10):  # frames 0 and 8 are held out (data.llffhold=8): training frames 1-7 and 9
    Image.fromarray(np.full((6, 8, 3), 10 * i, np.uint8)).save(tmp_path / "images" / f"{i:02d}.png")
    frames.append({"file_path": f"images/{i:02d}.png",
                   "transform_matrix": cameras.spherical_pose(36.0 * i, -30.0, 4.0).tolist()})
  (tmp_path / "transforms.json").write_text(json.dumps(
      {"fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "frames": frames}))
  read = []
  original = capture.read_image
  monkeypatch.setattr(capture, "read_image", lambda path, *a: read.append(path[-6:-4]) or original(path, *a))
  config = smoke_config(**{"data.kind": "nerfstudio", "data.path": str(tmp_path), "data.shards": 2})
  scene = scenes.load(config.data, Shards(2, (1,), 1, 2, 2**20))
  train = scene.split("train")
  assert sorted(read) == ["00", "02", "04", "06", "08", "09"]  # held-out 0, 8; shard 1 of 1-7, 9: 2, 4, 6, 9
  assert train.held.tolist() == [1, 3, 5, 7] and len(train) == 8 and train.image_uint8(7)[0, 0, 0] == 90
  assert scene.split("val") is scene.split("test")
