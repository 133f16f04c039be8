"""configs/llff.py and configs/capture.py end to end (smoke variants) on the shared real captures: the LLFF
horns in NDC with the spiral, the COLMAP cup contracted with the ellipse. Each trains, evaluates the held-out
views and renders its path into the orbit archive and videos."""
import json

import numpy as np
import pytest

from conftest import DATA, require
from nerfpod import archive as archives
from procs import run_main

pytestmark = pytest.mark.slow  # whole jobs on real images


@pytest.mark.parametrize("config,capture,space,path", [
    ("configs/llff.py:smoke", "llff_horns", "forward_facing", "spiral"),
    ("configs/capture.py:smoke", "colmap_cup", "unbounded", "ellipse"),
])
def test_real_capture_config_trains_evaluates_and_renders_its_path(tmp_path, config, capture, space, path):
  folder = require(DATA / capture)
  result = run_main(f"--config={config}", f"--config.data.path={folder}", f"--workdir={tmp_path}",
                    "--config.train.num_steps=10", "--config.eval.max_views=1", "--config.orbit.num_frames=3",
                    timeout=600)
  assert result.returncode == 0, result.stderr[-3000:]
  metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
  assert len(metrics["views"]) == 1 and 5 < metrics["mean"]["psnr"] < 40
  scene = json.loads((tmp_path / "scene.json").read_text())
  assert scene["space"] == space
  archive = archives.Archive.open(str(tmp_path / "renders" / "orbit.zarr"))
  assert archive.attributes["path"] == path and archive.missing_frames() == []
  frame = archive.read_frame(1)
  assert np.isfinite(frame["depth"]).all() and frame["rgb"].std() > 0
  assert (tmp_path / "renders" / "orbit_rgb.mp4").stat().st_size > 0
