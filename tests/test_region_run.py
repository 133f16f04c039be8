"""A model of K regions (model.regions) through the training loop in this process, on the 8 simulated devices:
steps, checkpoints, regions.json and evaluation, then a run killed after a checkpoint that resumes to the same
bits. (tests/test_region_multiprocess.py runs it over 2 processes, in the extended set.)"""
import json
import shutil

import jax
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod import monitor
from nerfpod.nerf import model as nerf_model
from nerfpod.run import modes
from nerfpod.workdir import checkpoints

OVERRIDES = {"model.regions": 4, "train.num_steps": 6, "train.batch_size": 64, "checkpoint.every_steps": 3,
             "train.log_every": 1, "train.image_every": 0, "eval.max_views": 1, "orbit.render_after_training": False,
             "train.distortion_weight": 0.01}


@pytest.mark.slow  # (two short runs to the end, ~20 s)
def test_a_region_run_trains_saves_evaluates_and_resumes_to_the_same_bits(tmp_path, monkeypatch):
  class Recording(monitor.Monitor):
    def scalars(self, step, metrics, lr):
      recorded.append((step, float(metrics["loss"])))
      super().scalars(step, metrics, lr)

  recorded = []
  monkeypatch.setattr(monitor, "Monitor", Recording)
  config = smoke_config(**OVERRIDES)
  whole = tmp_path / "whole"
  metrics = modes.train_and_evaluate(config, str(whole))
  whole_losses = dict(recorded)
  assert sorted(whole_losses) == [1, 2, 3, 4, 5, 6]
  assert sorted(int(p.name) for p in (whole / "checkpoints").iterdir() if p.name.isdigit()) == [3, 6]
  assert metrics["step"] == 6 and len(metrics["views"]) == 1 and np.isfinite(metrics["mean"]["psnr"])
  assert json.loads((whole / "eval" / "metrics.json").read_text())["mean"] == metrics["mean"]
  # regions.json against the cut built here: a grid of 4 over the hash grid's box.
  saved = json.loads((whole / "regions.json").read_text())
  want = nerf_model.partition(config)
  assert saved["cut"] == "grid" and saved["count"] == len(saved["regions"]) == 4 == want.size
  np.testing.assert_allclose([[p["normal"] for p in r["planes"]] for r in saved["regions"]], want.normals_KxPx3,
                             atol=1e-7)
  np.testing.assert_allclose([[p["offset"] for p in r["planes"]] for r in saved["regions"]], want.offsets_KxP,
                             atol=1e-6)
  # Killed after step 3's checkpoint: what came after it is lost; the same command resumes from step 3.
  killed = tmp_path / "killed"
  shutil.copytree(whole, killed)
  shutil.rmtree(killed / "checkpoints" / "6")
  shutil.rmtree(killed / "eval")
  recorded.clear()
  resumed = modes.train_and_evaluate(config, str(killed))
  assert dict(recorded) == {step: whole_losses[step] for step in (4, 5, 6)}  # from step 3 on, the same losses
  want_state, _, step = checkpoints.read_numpy(str(whole))
  got_state, _, resumed_step = checkpoints.read_numpy(str(killed))
  assert step == resumed_step == 6
  stacked = got_state["params"]["params"]["regions"]["coarse"]["rgb"]["kernel"]
  assert stacked.shape[0] == 4  # every region's fields, saved whole
  jax.tree.map(np.testing.assert_array_equal, got_state["params"], want_state["params"])
  assert resumed["views"] == metrics["views"] and resumed["mean"] == metrics["mean"]
