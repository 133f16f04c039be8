"""A model of K regions (model.regions) through the training loop in this process, on the 8 simulated devices:
steps, checkpoints, regions.json and evaluation, then a run killed after a checkpoint that resumes to the same
bits, locally and in a bucket. (tests/test_region_multiprocess.py runs it over 2 processes, in the extended set.)"""
import json
import shutil

import jax
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod import monitor
from nerfpod.run import components, modes
from nerfpod.workdir import checkpoints

OVERRIDES = {"model.regions": 4, "train.num_steps": 6, "train.batch_size": 64, "checkpoint.every_steps": 3,
             "train.log_every": 1, "train.image_every": 0, "eval.max_views": 1, "orbit.render_after_training": False,
             "train.distortion_weight": 0.01}


class _Recording(monitor.Monitor):
  """The run's monitor, recording (step, training loss) of each log step into `recorded`."""
  recorded = []

  def scalars(self, step, metrics, lr):
    self.recorded.append((step, float(metrics["loss"])))
    super().scalars(step, metrics, lr)


def _train(config, workdir) -> tuple[dict, dict]:
  """(eval/metrics.json's dict, {step: training loss} of the steps this run took)."""
  _Recording.recorded = []
  with pytest.MonkeyPatch.context() as patch:
    patch.setattr(monitor, "Monitor", _Recording)
    metrics = modes.train_and_evaluate(config, str(workdir))
  return metrics, dict(_Recording.recorded)


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
  """The region run to its end (steps 1-6, checkpoints 3 and 6, evaluation) in a local workdir: (workdir,
  metrics, losses)."""
  workdir = tmp_path_factory.mktemp("region-run") / "whole"
  metrics, losses = _train(smoke_config(**OVERRIDES), workdir)
  return workdir, metrics, losses


def _killed_after_step_3(whole_workdir, to):
  """A copy of the whole run as a kill after step 3's checkpoint leaves it: no step 6, no evaluation."""
  shutil.copytree(whole_workdir, to)
  shutil.rmtree(to / "checkpoints" / "6")
  shutil.rmtree(to / "eval")
  return to


@pytest.mark.slow  # (two short runs to the end, ~20 s)
def test_a_region_run_trains_saves_evaluates_and_resumes_to_the_same_bits(whole, tmp_path):
  config = smoke_config(**OVERRIDES)
  whole, metrics, whole_losses = whole
  assert sorted(whole_losses) == [1, 2, 3, 4, 5, 6]
  assert sorted(int(p.name) for p in (whole / "checkpoints").iterdir() if p.name.isdigit()) == [3, 6]
  assert metrics["step"] == 6 and len(metrics["views"]) == 1 and np.isfinite(metrics["mean"]["psnr"])
  assert json.loads((whole / "eval" / "metrics.json").read_text())["mean"] == metrics["mean"]
  # regions.json against the cut built here: a grid of 4 over the hash grid's box.
  saved = json.loads((whole / "regions.json").read_text())
  want = components.region_partition(config)
  assert saved["cut"] == "grid" and saved["count"] == len(saved["regions"]) == 4 == want.size
  np.testing.assert_allclose([[p["normal"] for p in r["planes"]] for r in saved["regions"]], want.normals_KxPx3,
                             atol=1e-7)
  np.testing.assert_allclose([[p["offset"] for p in r["planes"]] for r in saved["regions"]], want.offsets_KxP,
                             atol=1e-6)
  # Killed after step 3's checkpoint: what came after it is lost; the same command resumes from step 3.
  killed = _killed_after_step_3(whole, tmp_path / "killed")
  resumed, losses = _train(config, killed)
  assert losses == {step: whole_losses[step] for step in (4, 5, 6)}  # from step 3 on, the same losses
  want_state, _, step = checkpoints.read_numpy(str(whole))
  got_state, _, resumed_step = checkpoints.read_numpy(str(killed))
  assert step == resumed_step == 6
  stacked = got_state["params"]["params"]["regions"]["coarse"]["rgb"]["kernel"]
  assert stacked.shape[0] == 4  # every region's fields, saved whole
  jax.tree.map(np.testing.assert_array_equal, got_state["params"], want_state["params"])
  assert resumed["views"] == metrics["views"] and resumed["mean"] == metrics["mean"]


@pytest.mark.slow  # (one short run from step 3, ~10 s)
def test_a_region_run_resumes_in_a_bucket_to_the_same_bits(whole, tmp_path, emulator):
  """The killed run's workdir in a bucket (the test's Cloud Storage emulator; regions.json left out, which
  each start writes): the resume restores step 3 from gs://, saves step 6 and evaluates there, and ends with
  the local whole run's parameters, metrics and regions.json."""
  whole, metrics, whole_losses = whole
  killed = _killed_after_step_3(whole, tmp_path / "killed")
  (killed / "regions.json").unlink()
  workdir = emulator.upload(killed, "runs/region-resumed")
  resumed, losses = _train(smoke_config(**OVERRIDES), workdir)
  assert losses == {step: whole_losses[step] for step in (4, 5, 6)}
  names = emulator.files("runs/region-resumed")
  assert "checkpoints/6/commit_success.txt" in names and "eval/metrics.json" in names, names
  assert json.loads(emulator.read("runs/region-resumed/regions.json")) == \
      json.loads((whole / "regions.json").read_text())
  want_state, _, step = checkpoints.read_numpy(str(whole))
  got_state, _, resumed_step = checkpoints.read_numpy(workdir)
  assert step == resumed_step == 6
  jax.tree.map(np.testing.assert_array_equal, got_state["params"], want_state["params"])
  assert resumed["views"] == metrics["views"] and resumed["mean"] == metrics["mean"]
  assert json.loads(emulator.read("runs/region-resumed/eval/metrics.json"))["mean"] == metrics["mean"]
