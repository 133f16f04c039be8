"""The entry point as a user runs it: one command, a workdir with config, events and metrics.

The whole job (the smoke config, in a process of its own on one device) is marked slow; the refusals below
stop before any work and stay in the quick loop, in this process, through nerfpod.main.run: those refused before
JAX starts (a bad flag, config file or field), and those refused by the run's start-up (the scene, the devices),
after JAX has started on this process's 8 CPU devices (conftest.run_start_held: what the start-up sets for its
whole process goes back after each)."""
import json
import os
import subprocess
import sys

import pytest

import test_golden
from conftest import REPO
from procs import run_main


@pytest.fixture
def main_here(capsys, monkeypatch):
  """`python -m nerfpod.main ARGS` in this process (nerfpod.main.run; procs.in_process), for refusals that come
  before any work."""
  from nerfpod import main
  import procs
  return procs.in_process(main.run, "nerfpod.main", capsys, monkeypatch, REPO)


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
  """`python -m nerfpod.main --config=configs/default.py:smoke`: 20 steps, logs every 5, previews at 10."""
  workdir = tmp_path_factory.mktemp("smoke")
  result = run_main("--config=configs/default.py:smoke", f"--workdir={workdir}")
  assert result.returncode == 0, result.stderr[-3000:]
  return workdir, result


@pytest.mark.slow
def test_main_writes_resolved_config_metrics_and_progress(smoke_run):
  workdir, result = smoke_run
  config = json.loads((workdir / "config.json").read_text())
  assert config["train"]["num_steps"] == 20 and config["data"]["kind"] == "procedural"
  scene = json.loads((workdir / "scene.json").read_text())
  assert scene["kind"] == "procedural" and scene["space"] == "object" and scene["near"] == 2.0
  assert scene["capture_to_scene"] == [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
  metrics = json.loads((workdir / "eval" / "metrics.json").read_text())
  assert metrics["step"] == 20 and metrics["scene"] == "procedural" and metrics["split"] == "test"
  assert [v["index"] for v in metrics["views"]] == [0, 1]
  assert metrics["mean"]["psnr"] == pytest.approx(sum(v["psnr"] for v in metrics["views"]) / 2)
  assert metrics["mean"]["ssim"] == pytest.approx(sum(v["ssim"] for v in metrics["views"]) / 2)
  # The same job as test_golden's on 8 devices in the test process: one device sums the gradient mean in
  # another order, which moved these by at most 2.3e-7 relative (test_golden's docstring).
  got = {k: metrics["mean"][k] for k in test_golden.EVAL}
  assert got == pytest.approx(test_golden.EVAL, rel=test_golden.RTOL, abs=0)
  assert "step     20/20" in result.stdout and "rays/s" in result.stdout and "ETA" in result.stdout
  assert (workdir / "checkpoints" / "20").is_dir()
  # Saving arrays whole on one CPU process (checkpoints.py) replaces orbax's handler without its warning.
  assert "Type handler registry" not in result.stderr, result.stderr


@pytest.mark.slow
def test_tensorboard_can_read_the_events_with_the_recorded_losses(smoke_run):
  event_accumulator = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")
  workdir, _ = smoke_run
  acc = event_accumulator.EventAccumulator(str(workdir), size_guidance={"images": 0, "scalars": 0})
  acc.Reload()
  tags = acc.Tags()
  for tag in ("train/loss", "train/psnr", "train/learning_rate", "train/rays_per_sec", "eval/test/psnr"):
    assert tag in tags["scalars"], tags
  assert "preview/rgb" in tags["images"] and "preview/depth" in tags["images"]
  losses = {e.step: e.value for e in acc.Scalars("train/loss")}  # float32, as the step computed them
  assert sorted(losses) == [1, 5, 10, 15, 20]
  want = {step: test_golden.LOSSES[step] for step in (1, 5, 10, 20)}
  assert {step: losses[step] for step in want} == pytest.approx(want, rel=test_golden.RTOL, abs=0)
  eval_psnr = acc.Scalars("eval/test/psnr")
  assert [e.step for e in eval_psnr] == [20]
  assert eval_psnr[0].value == pytest.approx(test_golden.EVAL["psnr"], rel=test_golden.RTOL)


def test_unknown_config_key_is_refused_clearly(main_here, tmp_path):
  result = main_here("--config=configs/default.py", f"--workdir={tmp_path}", "--config.train.num_stepz=5")
  assert result.returncode != 0
  assert "num_stepz" in result.stderr and "Traceback" not in result.stderr
  assert result.stderr.count("nerfpod: error:") == 1
  assert not (tmp_path / "config.json").exists()


# Refused by the run's start-up, after JAX has started on the process's devices (this process's 8).
@pytest.mark.parametrize("args,message", [
    (["--config.data.kind=blender", "--config.data.path=/nonexistent/lego"], "not found"),
    (["--config.data.kind=tiny", "--config.data.path=/nonexistent/tiny.npz"], "not found"),
    (["--config.train.batch_size=100", "--config.data.image_size=8"], None),
])
def test_bad_input_exits_non_zero_with_one_sentence(main_here, run_start_held, tmp_path, args, message):
  import jax
  assert jax.device_count() == 8  # the devices the batch must split over
  result = main_here("--config=configs/default.py:smoke", f"--workdir={tmp_path}", *args)
  if message is None:  # 100 rays over 8 devices
    message = "does not split over 8 devices"
  _assert_one_sentence(result, message)


# Refused by the config's check, before JAX starts: in this process.
@pytest.mark.parametrize("args,message", [
    (["--config.render.proposal_padding=-0.01"], "render.proposal_padding=-0.01 is not valid: it must be a finite "
                                                 "number >= 0"),
    (["--config.train.proposal_anneal_steps=1000"], "train.proposal_anneal_steps=1000 is longer than the run"),
])
def test_bad_config_values_exit_2_with_one_sentence(main_here, tmp_path, args, message):
  _assert_one_sentence(main_here("--config=configs/default.py:smoke", f"--workdir={tmp_path}", *args), message)


def _assert_one_sentence(result, message):
  assert result.returncode == 2, result.stderr[-2000:]
  assert message in result.stderr and "Traceback" not in result.stderr
  assert len([l for l in result.stderr.splitlines() if l.startswith("nerfpod: error:")]) == 1


def test_missing_config_file_is_refused_clearly(main_here, tmp_path):
  result = main_here("--config=configs/no_such_config.py", f"--workdir={tmp_path}")
  assert result.returncode == 2 and "Traceback" not in result.stderr
  assert result.stderr == ("nerfpod: error: the --config file configs/no_such_config.py does not exist (a relative "
                           f"path is from the current folder, {os.getcwd()}).\n")
