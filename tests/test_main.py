"""The entry point as a user runs it: one command, a workdir with config, events and metrics."""
import json

import pytest

from procs import run_main


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
  workdir = tmp_path_factory.mktemp("smoke")
  result = run_main("--config=configs/default.py:smoke", f"--workdir={workdir}", "--config.train.num_steps=40",
                    "--config.train.log_every=10")
  assert result.returncode == 0, result.stderr[-3000:]
  return workdir, result


def test_main_writes_resolved_config_metrics_and_progress(smoke_run):
  workdir, result = smoke_run
  config = json.loads((workdir / "config.json").read_text())
  assert config["train"]["num_steps"] == 40 and config["data"]["kind"] == "procedural"
  scene = json.loads((workdir / "scene.json").read_text())
  assert scene["kind"] == "procedural" and scene["space"] == "object" and scene["near"] == 2.0
  assert scene["capture_to_scene"] == [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
  metrics = json.loads((workdir / "eval" / "metrics.json").read_text())
  assert metrics["step"] == 40 and metrics["scene"] == "procedural" and metrics["split"] == "test"
  assert [v["index"] for v in metrics["views"]] == [0, 1]
  assert metrics["mean"]["psnr"] == pytest.approx(sum(v["psnr"] for v in metrics["views"]) / 2)
  assert 0 < metrics["mean"]["ssim"] <= 1
  assert "step     40/40" in result.stdout and "rays/s" in result.stdout and "ETA" in result.stdout
  assert (workdir / "checkpoints" / "40").is_dir()


def test_tensorboard_can_read_the_events_and_loss_falls(smoke_run):
  event_accumulator = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")
  workdir, _ = smoke_run
  acc = event_accumulator.EventAccumulator(str(workdir), size_guidance={"images": 0, "scalars": 0})
  acc.Reload()
  tags = acc.Tags()
  for tag in ("train/loss", "train/psnr", "train/learning_rate", "train/rays_per_sec", "eval/test/psnr"):
    assert tag in tags["scalars"], tags
  assert "preview/rgb" in tags["images"] and "preview/depth" in tags["images"]
  losses = [e.value for e in acc.Scalars("train/loss")]
  assert [e.step for e in acc.Scalars("train/loss")] == [1, 10, 20, 30, 40]
  assert losses[-1] < 0.8 * losses[0]


def test_unknown_config_key_is_refused_clearly(tmp_path):
  result = run_main("--config=configs/default.py", f"--workdir={tmp_path}", "--config.train.num_stepz=5")
  assert result.returncode != 0
  assert "num_stepz" in result.stderr and "Traceback" not in result.stderr
  assert result.stderr.count("nerfpod: error:") == 1
  assert not (tmp_path / "config.json").exists()


@pytest.mark.parametrize("args,message", [
    (["--config.data.kind=blender", "--config.data.path=/nonexistent/lego"], "not found"),
    (["--config.data.kind=tiny", "--config.data.path=/nonexistent/tiny.npz"], "not found"),
    (["--config.train.batch_size=100", "--config.data.image_size=8"], None),
])
def test_bad_input_exits_non_zero_with_one_sentence(tmp_path, args, message):
  result = run_main("--config=configs/default.py:smoke", f"--workdir={tmp_path}", *args,
                    devices_per_process=8)
  if message is None:  # 100 rays over 8 devices
    message = "does not split over 8 devices"
  assert result.returncode == 2, result.stderr[-2000:]
  assert message in result.stderr and "Traceback" not in result.stderr
  assert len([l for l in result.stderr.splitlines() if l.startswith("nerfpod: error:")]) == 1


def test_missing_config_file_is_refused_clearly(tmp_path):
  result = run_main("--config=configs/no_such_config.py", f"--workdir={tmp_path}")
  assert result.returncode == 2 and "Traceback" not in result.stderr
  assert "could not load the --config file" in result.stderr and "no_such_config.py" in result.stderr
