"""A model of K regions (model.regions) trained by real processes on 127.0.0.1: 2 processes x 4 devices end
at the parameters of 1 process x 8, whether each process holds whole region groups (K = 4: the partial sums
gathered within a process, the gradient mean across the two) or a region group spans both (K = 8: the
gather crosses processes, and both load the same rays)."""
import json

import jax
import numpy as np
import pytest

import procs
from nerfpod.workdir import checkpoints

pytestmark = pytest.mark.slow

STEPS = 6
OVERRIDES = {"train.num_steps": STEPS, "train.batch_size": 64, "checkpoint.every_steps": STEPS,
             "train.log_every": 3, "train.image_every": 0, "eval.max_views": 1,
             "orbit.render_after_training": False, "train.distortion_weight": 0.01}
RUN_TIMEOUT = 300


@pytest.mark.parametrize("regions", [4, 8])
def test_two_processes_end_at_one_processs_parameters(tmp_path, regions):
  overrides = dict(OVERRIDES, **{"model.regions": regions})
  with procs.Run(tmp_path / "one", overrides, devices_per_process=8) as one:
    one.wait_ok(RUN_TIMEOUT)
  with procs.Run(tmp_path / "pod", overrides, num_processes=2, devices_per_process=4) as pod:
    pod.wait_ok(RUN_TIMEOUT)
  assert "2 process(es), 8 device(s)" in pod.output(0)
  # regions.json: where each region's fields live, as the model cut them (model.region_cut=grid over the box).
  from conftest import smoke_config
  from nerfpod.run import components
  want_cut = components.region_partition(smoke_config(**overrides))
  for workdir in ("one", "pod"):
    saved = json.loads((tmp_path / workdir / "regions.json").read_text())
    assert saved["cut"] == "grid" and saved["count"] == len(saved["regions"]) == regions
    normals = [[p["normal"] for p in r["planes"]] for r in saved["regions"]]
    offsets = [[p["offset"] for p in r["planes"]] for r in saved["regions"]]
    np.testing.assert_allclose(normals, want_cut.normals_KxPx3, atol=1e-7)
    np.testing.assert_allclose(offsets, want_cut.offsets_KxP, atol=1e-6)
  want, _, step = checkpoints.read_numpy(str(tmp_path / "one"))
  got, _, pod_step = checkpoints.read_numpy(str(tmp_path / "pod"))
  assert step == pod_step == STEPS
  stacked = want["params"]["params"]["regions"]["coarse"]["rgb"]["kernel"]
  assert stacked.shape[0] == regions  # saved whole, every region's fields
  for (path, a), (_, b) in zip(jax.tree.leaves_with_path(got["params"]), jax.tree.leaves_with_path(want["params"])):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7, err_msg=jax.tree_util.keystr(path))
  # Evaluation over the two processes (each rendering its share of the held-out rays through every region)
  # gives one process's numbers, to the parameters' own tolerance.
  one, pod = (json.loads((tmp_path / w / "eval" / "metrics.json").read_text()) for w in ("one", "pod"))
  assert one["step"] == pod["step"] == STEPS and len(one["views"]) == len(pod["views"]) == 1
  for a, b in [(pod["mean"], one["mean"]), *zip(pod["views"], one["views"])]:
    assert sorted(a) == sorted(b) and {"psnr", "ssim"} <= set(a), (a, b)
    for key in a:
      if isinstance(a[key], float):
        np.testing.assert_allclose(a[key], b[key], rtol=1e-4, err_msg=key)
      else:
        assert a[key] == b[key], key
