"""Weights & Biases as the second monitor (config.monitor.wandb), in offline mode (no network here): what a run
sends W&B is read back from the run's own .wandb file and compared with its TensorBoard events; a killed and
resumed run continues one W&B run, with steps that never go backwards; a two-process run writes one W&B run,
from process 0; a W&B failure is one warning and TensorBoard goes on; the config and the extra's absence.

The .wandb file (W&B's transaction log, what `wandb sync` uploads) is read with a reader of its record format
below (wandb 0.31 has no Python reader of its own): a 7-byte header, then LevelDB-log blocks of 32 KiB whose
records hold wandb_internal_pb2.Record protobufs.
"""
import json
import os
import pathlib
import signal
import struct
import subprocess
import sys
import time

import numpy as np
import pytest

import procs
from conftest import smoke_config
from nerfpod import monitor, schema
from nerfpod.monitor import wandb_run, writer as monitor_writer
from nerfpod.workdir import checkpoints, files as workdir_files

OFFLINE = {"monitor.wandb.mode": "offline"}


@pytest.fixture(autouse=True)
def wandb_environment(tmp_path, monkeypatch):
  """No W&B setting of whoever runs the tests (nor their credentials) reaches a test; W&B's own files of
  the test go to its tmp_path. Processes the tests start inherit this environment."""
  for name in list(os.environ):
    if name.startswith("WANDB_"):
      monkeypatch.delenv(name)
  for name in ("WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR"):
    monkeypatch.setenv(name, str(tmp_path / "wandb-home" / name.lower()))


# --- reading an offline run back ---------------------------------------------------------------------------

BLOCK, HEADER = 32768, 7  # W&B's LevelDB-style log: block size, record header (crc32, length, type)


def read_records(path) -> list:
  """The Record protobufs of a .wandb file, in order; a record cut short by a kill ends the list."""
  from wandb.proto import wandb_internal_pb2
  data = pathlib.Path(path).read_bytes()
  ident, magic, version = struct.unpack("<4sHB", data[:HEADER])
  assert (ident, magic, version) == (b":W&B", 0xBEE1, 0), (ident, magic, version)
  records, position, parts = [], HEADER, b""
  while True:
    if BLOCK - position % BLOCK < HEADER:  # a block's tail too short for a header is padding
      position += BLOCK - position % BLOCK
    if position + HEADER > len(data):
      break
    _, length, kind = struct.unpack("<IHB", data[position:position + HEADER])
    if kind == 0 or position + HEADER + length > len(data):
      break
    chunk = data[position + HEADER:position + HEADER + length]
    position += HEADER + length
    parts = chunk if kind in (1, 2) else parts + chunk  # FULL, FIRST / MIDDLE, LAST
    if kind in (1, 4):
      record = wandb_internal_pb2.Record()
      record.ParseFromString(parts)
      records.append(record)
  return records


def wandb_files(workdir) -> list[pathlib.Path]:
  """The workdir's .wandb files, oldest first (one per process start: a resumed run adds one)."""
  return sorted((pathlib.Path(workdir) / "wandb").glob("offline-run-*/run-*.wandb"))


def history(path) -> list[dict]:
  """The rows a .wandb file's run logged: {key: value}, media as {field: value} dicts."""
  rows = []
  for record in read_records(path):
    if record.WhichOneof("record_type") != "history":
      continue
    row = {}
    for item in record.history.item:
      keys = list(item.nested_key) or [item.key]
      value = json.loads(item.value_json)
      if len(keys) == 1:
        row[keys[0]] = value
      else:
        row.setdefault(keys[0], {})["/".join(keys[1:])] = value
    rows.append(row)
  return rows


def run_of(path):
  """The RunRecord of a .wandb file (id, project, name, tags, config)."""
  return next(r.run for r in read_records(path) if r.WhichOneof("record_type") == "run")


def scalars_of(rows: list[dict]) -> dict:
  """{(key, step): value} of the logged numbers (not W&B's own _step, _runtime, _timestamp)."""
  return {(key, row["step"]): value for row in rows for key, value in row.items()
          if not key.startswith("_") and key != "step" and isinstance(value, (int, float))}


def media_of(rows: list[dict], kind: str) -> dict:
  """{(key, step): media dict} of the logged images ('image-file'), videos ('video-file'), tables."""
  return {(key, row["step"]): value for row in rows for key, value in row.items()
          if isinstance(value, dict) and value.get("_type") == kind}


def tensorboard_of(workdir):
  from tensorboard.backend.event_processing import event_accumulator
  events = event_accumulator.EventAccumulator(str(workdir), size_guidance={"scalars": 0, "images": 0})
  events.Reload()
  scalars = {(tag, e.step): e.value for tag in events.Tags()["scalars"] for e in events.Scalars(tag)}
  images = {(tag, e.step): e for tag in events.Tags()["images"] for e in events.Images(tag)}
  return scalars, images


# --- the config ---------------------------------------------------------------------------------------------

def test_wandb_is_off_by_default_and_its_fields_are_in_the_schema():
  config = smoke_config()
  assert config.monitor.wandb.mode == "disabled"
  assert {k for k in schema.FIELDS if k.startswith("monitor.")} == {
      "monitor.wandb.mode", "monitor.wandb.project", "monitor.wandb.entity", "monitor.wandb.name",
      "monitor.wandb.tags"}
  assert schema.problems(smoke_config(**{"monitor.wandb.tags": ("lego", "hashgrid")}), device_count=8) == []
  found = schema.problems(smoke_config(**{"monitor.wandb.mode": "cloud"}))
  assert found == ["monitor.wandb.mode=cloud is not valid: it must be one of 'disabled', 'online', 'offline' "
                   "(e.g. --config.monitor.wandb.mode=disabled)."]


def test_a_workdir_written_before_the_monitor_fields_resumes_with_wandb_on():
  from nerfpod.config_util import override
  saved = json.loads(smoke_config().to_json_best_effort())
  del saved["monitor"]  # a config.json of a version without W&B
  now = json.loads(override(smoke_config(), **OFFLINE, **{"monitor.wandb.tags": ("a",)}).to_json_best_effort())
  assert workdir_files.incompatible_fields(saved, now) == []  # monitor.* may change on resume


def test_asking_for_wandb_without_the_package_is_one_sentence_naming_the_extra(tmp_path, monkeypatch):
  monkeypatch.setitem(sys.modules, "wandb", None)  # `import wandb` fails, as where it is not installed
  config = smoke_config(**OFFLINE)
  assert schema.problems(config) == []  # a tool that only reads a workdir's config does not need it
  (message,) = schema.problems(config, device_count=8)
  assert message.startswith("monitor.wandb.mode=offline logs to Weights & Biases, but its package cannot be "
                            "imported") and "pip install 'nerfpod[wandb]'" in message, message
  assert message.replace("e.g. ", "").count(". ") == 0 and message.endswith(")."), message


def test_the_command_without_the_wandb_package_exits_2_before_any_work(tmp_path):
  hide = tmp_path / "hide"
  (hide / "wandb").mkdir(parents=True)
  (hide / "wandb" / "__init__.py").write_text("raise ImportError(\"No module named 'wandb'\")\n")
  workdir = tmp_path / "run"
  result = procs.run_main("--config=configs/default.py:smoke", f"--workdir={workdir}",
                          "--config.monitor.wandb.mode=offline", timeout=120,
                          env={"PYTHONPATH": os.pathsep.join([str(hide), str(procs.REPO), str(procs.REPO / "tests")])})
  assert result.returncode == 2, result.stderr[-2000:]
  errors = [line for line in result.stderr.splitlines() if line.startswith("nerfpod: error:")]
  assert len(errors) == 1 and "pip install 'nerfpod[wandb]'" in errors[0], result.stderr[-2000:]
  assert "Traceback" not in result.stderr and "step " not in result.stdout
  assert not workdir.exists()  # nothing written


# --- the monitor interface ------------------------------------------------------------------------------------

class FakeRun:
  """What WandbRun uses of a wandb Run; `fail_at`: the log call (0-based) that raises, as a lost connection."""

  def __init__(self, fail_at=None):
    self.logged, self.finished, self.fail_at = [], [], fail_at

  def log(self, row):
    if self.fail_at is not None and len(self.logged) == self.fail_at:
      raise ConnectionError("connection reset by peer")
    self.logged.append(dict(row))

  def finish(self, exit_code=None):
    self.finished.append(exit_code)


class FakeTensorBoard:
  def __init__(self):
    self.scalars = []

  def add_scalar(self, tag, value, step):
    self.scalars.append((tag, step, value))

  def flush(self):
    pass

  def close(self):
    pass


def test_wandb_gets_one_row_per_step_and_nothing_at_or_below_what_it_already_has(tmp_path):
  (tmp_path / "wandb.json").write_text(json.dumps({"id": "abc", "step": 10, "keys": ["train/loss"]}))
  run = FakeRun()
  writer = monitor.Writer(FakeTensorBoard(), wandb_run.WandbRun(run, str(tmp_path), wandb_run.read_wandb_record(
      str(tmp_path))))
  for step in (5, 10, 15):  # a resumed run re-trains 6..15; W&B got up to step 10's train/loss before
    writer.add_scalar("train/loss", 1.0 / step, step)
    writer.add_scalar("train/psnr", float(step), step)
  writer.add_scalar("eval/test/psnr", 20.0, 15)
  writer.close()
  assert run.logged == [{"train/psnr": 10.0, "step": 10},
                        {"train/loss": 1 / 15, "train/psnr": 15.0, "eval/test/psnr": 20.0, "step": 15}]
  assert run.finished == [None]
  record = json.loads((tmp_path / "wandb.json").read_text())
  assert record == {"id": "abc", "step": 15, "keys": ["eval/test/psnr", "train/loss", "train/psnr"]}


def test_a_wandb_failure_mid_run_is_one_warning_and_tensorboard_goes_on(tmp_path, capsys):
  run = FakeRun(fail_at=1)
  tensorboard = FakeTensorBoard()
  writer = monitor.Writer(tensorboard, wandb_run.WandbRun(run, str(tmp_path), {"id": "abc"}))
  for step in range(1, 6):
    writer.add_scalar("train/loss", 1.0 / step, step)
  writer.close(exit_code=0)
  assert run.logged == [{"train/loss": 1.0, "step": 1}]
  assert run.finished == [1]  # closed as failed, once
  assert [s for _, s, _ in tensorboard.scalars] == [1, 2, 3, 4, 5]
  warnings = [l for l in capsys.readouterr().err.splitlines() if l.startswith("nerfpod: warning:")]
  assert warnings == ["nerfpod: warning: Weights & Biases failed (connection reset by peer); the run goes on "
                      "with TensorBoard only."]


def test_wandb_without_network_is_one_warning_and_tensorboard_goes_on(tmp_path, capsys, monkeypatch):
  pytest.importorskip("wandb")
  # A key of the right shape, and a server that refuses connections: one warning naming it, before wandb.init.
  monkeypatch.setenv("WANDB_API_KEY", "0" * 40)
  monkeypatch.setenv("WANDB_BASE_URL", "http://127.0.0.1:9")
  monkeypatch.setenv("WANDB_INIT_TIMEOUT", "2")
  writer = monitor.summary_writer(str(tmp_path), smoke_config(**{"monitor.wandb.mode": "online"}))
  assert writer.wandb is None
  writer.add_scalar("train/loss", 0.5, 1)
  writer.close()
  warnings = [l for l in capsys.readouterr().err.splitlines() if l.startswith("nerfpod: warning:")]
  assert len(warnings) == 1 and "Weights & Biases could not start" in warnings[0], warnings
  assert "TensorBoard only" in warnings[0]
  assert "cannot connect to its server 127.0.0.1:9" in warnings[0]  # at once, not after W&B's retries
  scalars, _ = tensorboard_of(tmp_path)
  assert scalars == {("train/loss", 1): 0.5}


def test_images_become_uint8_as_tensorboard_shows_them():
  hwc = np.linspace(0.0, 1.0, 2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
  out = monitor_writer.to_uint8_hwc(hwc)
  assert out.dtype == np.uint8 and out.shape == (2, 3, 3) and out.min() == 0 and out.max() == 255
  np.testing.assert_array_equal(monitor_writer.to_uint8_hwc(np.moveaxis(hwc, -1, 0), "CHW"), out)
  assert monitor_writer.to_uint8_hwc(hwc[..., :1]).shape == (2, 3)  # one channel: grey
  assert monitor_writer.to_uint8_hwc(np.full((2, 2, 1), np.nan)).max() == 0


# --- whole runs -----------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_an_offline_run_holds_what_tensorboard_holds_and_wandb_sync_would_upload_it(tmp_path):
  pytest.importorskip("wandb")
  pytest.importorskip("tensorboard")
  from nerfpod.run import modes
  config = smoke_config(**OFFLINE, **{"monitor.wandb.tags": ("smoke", "test")})
  result = modes.train_and_evaluate(config, str(tmp_path))

  (path,) = wandb_files(tmp_path)
  record = json.loads((tmp_path / "wandb.json").read_text())
  run = run_of(path)
  assert run.run_id == record["id"] and path.name == f"run-{record['id']}.wandb"
  assert (run.project, run.display_name, list(run.tags)) == ("nerfpod", tmp_path.name, ["smoke", "test"])
  synced_config = {u.key: json.loads(u.value_json) for u in run.config.update if u.key != "_wandb"}
  assert synced_config == json.loads(config.to_json_best_effort())  # the resolved config, whole

  rows = history(path)
  steps = [row["step"] for row in rows]
  assert steps == sorted(steps) and steps[-1] == 20 and record["step"] == 20
  tb_scalars, tb_images = tensorboard_of(tmp_path)
  wandb_scalars = scalars_of(rows)
  assert set(wandb_scalars) == set(tb_scalars)  # the same scalars at the same steps...
  for key, value in tb_scalars.items():        # ...with the same values (TensorBoard keeps float32)
    assert wandb_scalars[key] == pytest.approx(value, rel=1e-6), key
  assert {("train/loss", s) for s in (1, 5, 10, 15, 20)} <= set(wandb_scalars)
  assert ("eval/test/psnr", 20) in wandb_scalars
  assert wandb_scalars[("eval/test/psnr", 20)] == pytest.approx(result["mean"]["psnr"])

  files = path.parent / "files"
  images = media_of(rows, "image-file")
  assert set(images) == set(tb_images)  # previews, the evaluated views, the contact sheet
  assert {("preview/rgb", 10), ("eval/0/rgb", 20), ("orbit/contact_sheet", 20)} <= set(images)
  for (key, step), image in images.items():
    assert (files / image["path"]).is_file(), image
    assert (image["height"], image["width"]) == (tb_images[key, step].height, tb_images[key, step].width)
  videos = media_of(rows, "video-file")
  assert set(videos) == {(f"orbit/{c}", 20) for c in ("rgb", "depth", "acc", "disparity")}
  for video in videos.values():
    assert (files / video["path"]).stat().st_size > 0
  (table,) = media_of(rows, "table-file").items()
  assert table[0] == ("eval/test/views", 20)
  table_json = json.loads((files / table[1]["path"]).read_text())
  assert table_json["columns"][:4] == ["index", "name", "psnr", "ssim"]
  assert [row[2] for row in table_json["data"]] == pytest.approx([v["psnr"] for v in result["views"]])

  # What `wandb sync` uploads: this one run.
  done = subprocess.run([sys.executable, "-m", "wandb", "sync", "--dry-run", str(path.parent)],
                        capture_output=True, text=True, timeout=120, cwd=tmp_path)
  assert done.returncode == 0 and "Would sync 1 run(s)" in done.stdout + done.stderr, done.stdout + done.stderr


# The multi-process tests' job, logging every step.
JOB = {"train.num_steps": 24, "train.batch_size": 128, "checkpoint.every_steps": 2, "checkpoint.max_to_keep": 3,
       "train.log_every": 1, "train.image_every": 0, "eval.max_views": 1, "orbit.render_after_training": False,
       **OFFLINE}
RUN_TIMEOUT = 180


@pytest.mark.slow
def test_a_killed_and_resumed_run_continues_one_wandb_run_and_its_steps_never_go_back(tmp_path):
  pytest.importorskip("wandb")
  workdir = tmp_path / "run"
  record_file = workdir / "wandb.json"

  def logged_step():
    try:
      return json.loads(record_file.read_text()).get("step") or 0
    except (OSError, ValueError):
      return 0

  # Checkpoints every 5 steps, killed once W&B has rows of step 8: the resumed run re-trains steps W&B has.
  with procs.Run(workdir, dict(JOB, **{"checkpoint.every_steps": 5})) as run:
    run.wait_for(lambda: logged_step() >= 8, RUN_TIMEOUT, "W&B rows up to step 8")
    run.signal(0, signal.SIGSTOP)  # stopped at a step; W&B's own process writes its file every second...
    time.sleep(3)
    run.kill()                     # ...then SIGKILL: nothing is finished, flushed or closed
  at_kill = json.loads(record_file.read_text())
  checkpoint = checkpoints.latest_step(str(workdir)) or 0
  assert checkpoint < at_kill["step"] < 24, (checkpoint, at_kill, run.tails())

  with procs.Run(workdir, JOB) as again:
    again.wait_ok(RUN_TIMEOUT)
  assert f"steps {checkpoint}..24" in again.output(0), again.tails()
  assert json.loads(record_file.read_text())["id"] == at_kill["id"]

  first, second = wandb_files(workdir)  # one per process start, the same W&B run
  assert run_of(first).run_id == run_of(second).run_id == at_kill["id"]
  before, after = history(first), history(second)
  # W&B got what wandb.json says it got...
  assert max(row["step"] for row in before) == at_kill["step"]
  assert set(at_kill["keys"]) <= {key for row in before if row["step"] == at_kill["step"] for key in row}
  # ...and the resumed run, which trained again the steps after its checkpoint, sent none of them twice: every
  # step's loss is in the one W&B run exactly once, in order.
  assert all(row["step"] > at_kill["step"] or (row["step"] == at_kill["step"] and
                                               not set(row) & set(at_kill["keys"])) for row in after)
  steps = [row["step"] for row in before + after]
  assert steps == sorted(steps), steps
  assert [row["step"] for row in before + after if "train/loss" in row] == list(range(1, 25))
  assert ("eval/test/psnr", 24) in scalars_of(after)
  assert {u.key for u in run_of(second).config.update} >= {"train", "model", "monitor"}


@pytest.mark.slow
def test_a_two_process_run_writes_one_wandb_run_from_process_0(tmp_path):
  pytest.importorskip("wandb")
  pytest.importorskip("tensorboard")
  workdir = tmp_path / "pod"
  overrides = dict(JOB, **{"train.num_steps": 10, "train.log_every": 5})
  with procs.Run(workdir, overrides, num_processes=2, devices_per_process=4, via_launcher=True) as pod:
    pod.wait_ok(RUN_TIMEOUT)
  assert "2 process(es), 8 device(s)" in pod.output(0)
  (path,) = wandb_files(workdir)
  assert run_of(path).run_id == json.loads((workdir / "wandb.json").read_text())["id"]
  tb_scalars, _ = tensorboard_of(workdir)
  assert scalars_of(history(path)).keys() == tb_scalars.keys()
  assert {step for key, step in tb_scalars if key == "train/loss"} == {1, 5, 10}
  # W&B's console lines ("wandb: ...") come from process 0 only: process 1 never started W&B.
  assert any(line.startswith("wandb:") for line in pod.output(0).splitlines()), pod.tails()
  assert not any(line.startswith("wandb:") for line in pod.launched_log(1).splitlines()), pod.launched_log(1)


def test_only_process_0_writes_to_tensorboard_and_wandb(tmp_path, monkeypatch):
  import jax
  monkeypatch.setattr(jax, "process_index", lambda: 1)
  assert monitor.summary_writer(str(tmp_path), smoke_config(**OFFLINE)) is None
  assert list(tmp_path.iterdir()) == []
