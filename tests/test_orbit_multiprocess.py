"""The orbit rendered by 2 real processes on 127.0.0.1 (`--mode=render`) equals the single-process render."""
import re
import shutil

import numpy as np
import pytest

import procs
from conftest import smoke_config
from nerfpod import archive as archives
from nerfpod import modes

pytestmark = pytest.mark.slow
OVERRIDES = {"train.num_steps": 2, "train.log_every": 1, "train.image_every": 0, "eval.max_views": 1,
             "orbit.num_frames": 5, "orbit.width": 16, "orbit.height": 16}
RUN_TIMEOUT = 150  # seconds for both processes to start, restore, render and export on a loaded machine


def test_two_processes_write_each_frame_once_and_match_one_process(tmp_path):
  one = tmp_path / "one"
  modes.train_and_evaluate(smoke_config(**OVERRIDES), str(one))  # 1 process x 8 devices, with its orbit
  pod = tmp_path / "pod"
  shutil.copytree(one, pod, ignore=shutil.ignore_patterns("renders"))
  with procs.Run(pod, OVERRIDES, num_processes=2, devices_per_process=2,
                 extra_flags=["--mode=render", "--verbosity=0"]) as run:
    run.wait_ok(RUN_TIMEOUT)
  outputs = [run.output(0), run.output(1)]

  # Each process rendered exactly its own frames (i % 2), and wrote each of them once.
  for index, frames in ((0, [0, 2, 4]), (1, [1, 3])):
    rendered = re.findall(r"orbit: process (\d) of 2 renders frames \[([\d, ]*)\]", outputs[index])
    assert rendered == [(str(index), ", ".join(map(str, frames)))], outputs[index][-3000:]
  archive = archives.Archive.open(str(pod / "renders" / "orbit.zarr"))
  np.testing.assert_array_equal(archive.written_by(), [0, 1, 0, 1, 0])
  reference = archives.Archive.open(str(one / "renders" / "orbit.zarr"))
  assert {k: v for k, v in archive.attributes.items() if k != "config"} == {
      k: v for k, v in reference.attributes.items() if k != "config"}
  for index in range(5):
    got, want = archive.read_frame(index), reference.read_frame(index)
    assert np.abs(got["rgb"].astype(int) - want["rgb"]).max() <= 1, index
    for name in ("depth", "acc", "disparity"):
      np.testing.assert_allclose(got[name], want[name], rtol=1e-5, atol=1e-5, err_msg=f"{name} {index}")
  # Process 0 exported the videos once every frame was there.
  assert (pod / "renders" / "orbit_rgb.mp4").stat().st_size > 0
  assert (pod / "renders" / "orbit_sheet.png").stat().st_size > 0
