"""The orbit rendered by 2 real processes on 127.0.0.1 (`--mode=render`) equals the single-process render."""
import os
import pathlib
import re
import shutil
import subprocess
import sys
import time

import numpy as np
import portpicker

from conftest import REPO, smoke_config
from nerfpod import orbit, train

OVERRIDES = {"train.num_steps": 2, "train.log_every": 1, "train.image_every": 0, "eval.max_views": 1,
             "orbit.num_frames": 5, "orbit.width": 16, "orbit.height": 16}
RUN_TIMEOUT = 150  # seconds for both processes to start, restore, render and export on a loaded machine


def run_processes(workdir: pathlib.Path, num_processes: int, devices_per_process: int,
                  flags: list[str]) -> list[str]:
  """Runs `python -m nerfpod.main` as `num_processes` processes on 127.0.0.1; returns their outputs.
  Fails, after killing them all, if any exits non-zero or they run past RUN_TIMEOUT."""
  port = portpicker.pick_unused_port()
  env = dict(os.environ, JAX_NUM_CPU_DEVICES=str(devices_per_process), JAX_PLATFORMS="cpu",
             PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
  for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID", "XLA_FLAGS"):
    env.pop(name, None)
  logs = [workdir.parent / f"{workdir.name}_process_{i}.log" for i in range(num_processes)]
  processes = []
  try:
    for index, log in enumerate(logs):
      with open(log, "wb") as out:
        processes.append(subprocess.Popen(
            [sys.executable, "-m", "nerfpod.main", f"--workdir={workdir}", *flags,
             f"--coordinator_address=127.0.0.1:{port}", f"--num_processes={num_processes}",
             f"--process_id={index}"], cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT))
    deadline = time.monotonic() + RUN_TIMEOUT
    codes = [p.wait(timeout=max(1.0, deadline - time.monotonic())) for p in processes]
  finally:
    for p in processes:
      if p.poll() is None:
        p.kill()
        p.wait()
  outputs = [log.read_text(errors="replace") for log in logs]
  assert codes == [0] * num_processes, "\n".join(f"--- process {i}:\n{out[-3000:]}"
                                                for i, out in enumerate(outputs))
  return outputs


def test_two_processes_write_each_frame_once_and_match_one_process(tmp_path):
  one = tmp_path / "one"
  train.train_and_evaluate(smoke_config(**OVERRIDES), str(one))  # 1 process x 8 devices, with its orbit
  pod = tmp_path / "pod"
  shutil.copytree(one, pod, ignore=shutil.ignore_patterns("renders"))
  flags = ["--config=configs/default.py:smoke", "--mode=render", "--verbosity=0",
           *(f"--config.{k}={v}" for k, v in OVERRIDES.items())]
  outputs = run_processes(pod, num_processes=2, devices_per_process=2, flags=flags)

  # Each process rendered exactly its own frames (i % 2), and wrote each of them once.
  for index, frames in ((0, [0, 2, 4]), (1, [1, 3])):
    rendered = re.findall(r"orbit: process (\d) of 2 renders frames \[([\d, ]*)\]", outputs[index])
    assert rendered == [(str(index), ", ".join(map(str, frames)))], outputs[index][-3000:]
  archive = orbit.Archive.open(str(pod / "renders" / "orbit.zarr"))
  np.testing.assert_array_equal(archive.written_by(), [0, 1, 0, 1, 0])
  reference = orbit.Archive.open(str(one / "renders" / "orbit.zarr"))
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
