"""tools/device_check.sh --tiny: the accelerator check's every stage, run here on the CPU, so it never rots."""
import json
import math
import os
import subprocess

import pytest

from conftest import REPO

pytestmark = pytest.mark.slow


def test_the_tiny_device_check_runs_every_stage_and_reports_their_figures(tmp_path):
  out = tmp_path / "report"
  env = {k: v for k, v in os.environ.items() if k != "OUT"}
  done = subprocess.run(["bash", str(REPO / "tools" / "device_check.sh"), "--tiny", f"--out={out}"], cwd=tmp_path,
                        env=env, capture_output=True, text=True, timeout=600)
  log = (out / "device_check.log").read_text() if (out / "device_check.log").exists() else ""
  assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:] + log[-3000:]
  report = json.loads((out / "device_check.json").read_text())
  stages = report["stages"]
  assert list(stages) == ["env", "bench_64", "bench_128", "default", "capture_padded", "quality", "pod"]
  assert all(stage["status"] == "ok" for stage in stages.values()), stages
  env_stage = stages["env"]
  assert env_stage["backend"] == "cpu" and env_stage["device_count"] >= 1 and env_stage["jax"]
  from nerfpod.render import lpips, video  # what it found for the default job is what this machine has
  assert (env_stage["ffmpeg"], env_stage["lpips_weights"]) == (video.mp4_available(), lpips.available("alex"))
  for size in (64, 128):
    bench = stages[f"bench_{size}"]
    assert bench["batch_size"] == size and bench["rays_per_s"] > 0 and bench["step_ms"] > 0
    assert bench["flops_per_step"] > 0 and 0 < bench["fraction_of_peak"]
    assert bench["machine"]["backend"] == env_stage["backend"]  # the run is on the machine's own backend
  # The whole step's FLOPs, as nerfpod bench counts them: twice the rays, nearly twice the work (the update of
  # the parameters does not grow with the rays); a count of one device's share or one micro-batch would not.
  ratio = stages["bench_128"]["flops_per_step"] / stages["bench_64"]["flops_per_step"]
  assert 1.6 < ratio <= 2.0, ratio
  default = stages["default"]
  assert default["step"] == 20 and default["views"] == 2 and math.isfinite(default["psnr"])
  assert default["first_line"].startswith("nerfpod: JAX ") and " on cpu: " in default["first_line"]
  assert "orbit.zarr" in default["renders"] and "orbit_sheet.png" in default["renders"]
  # The capture stage on the tiny config: the default stage's job with its proposal histogram padded.
  padded = stages["capture_padded"]
  assert padded["overrides"] == ["--config.train.num_steps=20", "--config.render.proposal_padding=0.01"]
  assert padded["step"] == 20 and padded["views"] == 2
  assert sorted(map(int, padded["losses"])) == [1, 5, 10, 15, 20]  # log_every 5
  assert math.isfinite(padded["psnr"]) and padded["psnr"] != default["psnr"]  # the override reached the run
  assert math.isfinite(padded["train_psnr"]) and padded["loss_spikes"] == []
  assert sorted(map(int, padded["window"])) == [1, 5, 10, 15, 20] and sorted(padded["interlevel"]) == sorted(
      padded["window"])
  assert all(0.0 < w <= 1.0 for w in padded["window"].values()) and padded["collapse_warning"] is False
  kept = out / "capture_padded"  # what comes back from the machine: events (scalars, previews) and metrics
  assert "metrics.json" in padded["kept"] and any(k.startswith("events.out.tfevents") for k in padded["kept"])
  assert json.loads((kept / "metrics.json").read_text())["mean"]["psnr"] == pytest.approx(padded["psnr"])
  quality = stages["quality"]
  best = max(h["psnr"] for h in quality["history"])
  for target in (8.0, 9.0, 20.0):  # reached exactly where the held-out PSNR got there
    assert (quality[f"seconds_to_{target:g}db"] is not None) == (best >= target), quality
  assert quality["final_step"] == 40
  pod = stages["pod"]
  assert pod["how"].startswith("2 processes") and math.isfinite(pod["psnr"])
  table = (out / "device_check.md").read_text()
  for name in stages:
    assert f"| {name} | ok |" in table
  assert f"PSNR {default['psnr']:.2f} dB" in table


def test_loss_spikes_are_the_steps_whose_loss_jumps_over_the_recent_median():
  import importlib.util
  spec = importlib.util.spec_from_file_location("device_check", REPO / "tools" / "device_check.py")
  device_check = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(device_check)
  steps = list(range(100, 1300, 100))
  # the H200's cup at big: a steady ~0.01, one jump to 0.117, then the proposal losses gone (~0.001)
  losses = [0.011, 0.010, 0.011, 0.0098, 0.0105, 0.0113, 0.117, 0.003, 0.0021, 0.0017, 0.0014, 0.0013]
  assert device_check.loss_spikes(steps, losses) == [700]
  assert device_check.loss_spikes(steps, losses, factor=20.0) == []
  assert device_check.loss_spikes(steps[:5], losses[:5]) == []  # fewer than the window: nothing to compare
  match = device_check.STEP_LINE.match("step   2900/8000 | loss 0.11738 | psnr  18.95 dB | lr 2.85e-03 | 691,9")
  assert match and (int(match[1]), float(match[2]), float(match[3])) == (2900, 0.11738, 18.95)


def test_stages_the_budget_leaves_no_room_for_are_skipped_not_started(tmp_path):
  out = tmp_path / "report"
  env = {k: v for k, v in os.environ.items() if k != "OUT"}
  done = subprocess.run(["bash", str(REPO / "tools" / "device_check.sh"), "--tiny", f"--out={out}",
                         "--stages=capture,quality,pod", "--budget_s=20"], cwd=tmp_path, env=env,
                        capture_output=True, text=True, timeout=120)
  assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
  stages = json.loads((out / "device_check.json").read_text())["stages"]
  assert list(stages) == ["capture_padded", "quality", "pod"]
  for stage in stages.values():
    assert stage["status"] == "skipped" and "--budget_s=20" in stage["reason"], stage
