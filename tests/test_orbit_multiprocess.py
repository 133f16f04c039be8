"""The orbit rendered by 2 real processes on 127.0.0.1 (`--mode=render`) equals the single-process render; a
render resumed with all the missing frames on one process (the other feeding padding) redoes exactly them,
bit for bit; and every program those processes compile spans all their devices (tests/compiles.py)."""
import re
import shutil

import numpy as np
import pytest

import compiles
import procs
from conftest import smoke_config
from nerfpod.render import archive as archives
from nerfpod.run import modes

pytestmark = pytest.mark.slow
OVERRIDES = {"train.num_steps": 2, "train.log_every": 1, "train.image_every": 0, "eval.max_views": 1,
             "orbit.num_frames": 5, "orbit.width": 16, "orbit.height": 16}
RUN_TIMEOUT = 300  # s for both processes to start, restore, render and export on a loaded machine: a hang's bound


def _rendered(output: str) -> list[tuple[str, str]]:
  return re.findall(r"orbit: process (\d) of 2 renders frames \[([\d, ]*)\]", output)


def _assert_close_frames(archive, reference, frames):
  """Frames of 1 x 8 and 2 x 2 devices: each device renders blocks of another size."""
  for index in frames:
    got, want = archive.read_frame(index), reference.read_frame(index)
    assert np.abs(got["rgb"].astype(int) - want["rgb"]).max() <= 1, index
    for name in ("depth", "acc", "disparity"):
      np.testing.assert_allclose(got[name], want[name], rtol=1e-5, atol=1e-5, err_msg=f"{name} {index}")


def _assert_whole_slice_programs(folder):
  records = compiles.read(*sorted(folder.glob("compiles_process_*.jsonl")))
  every = sorted({i for r in records for i in r["devices"]})
  assert len(every) == 4, every  # 2 processes x 2 devices
  assert compiles.subset_programs(records, every) == []
  assert any(len(r["devices"]) == 4 for r in records)


def test_two_processes_write_each_frame_once_and_match_one_process(tmp_path):
  one = tmp_path / "one"
  modes.train_and_evaluate(smoke_config(**OVERRIDES), str(one))  # 1 process x 8 devices, with its orbit
  pod = tmp_path / "pod"
  shutil.copytree(one, pod, ignore=shutil.ignore_patterns("renders"))
  with procs.Run(pod, OVERRIDES, num_processes=2, devices_per_process=2,
                 extra_flags=["--mode=render", "--verbosity=0"], compiles_dir=tmp_path) as run:
    run.wait_ok(RUN_TIMEOUT)
  outputs = [run.output(0), run.output(1)]

  # Each process rendered exactly its own frames (i % 2), and wrote each of them once.
  for index, frames in ((0, [0, 2, 4]), (1, [1, 3])):
    assert _rendered(outputs[index]) == [(str(index), ", ".join(map(str, frames)))], outputs[index][-3000:]
  archive = archives.Archive.open(str(pod / "renders" / "orbit.zarr"))
  np.testing.assert_array_equal(archive.written_by(), [0, 1, 0, 1, 0])
  reference = archives.Archive.open(str(one / "renders" / "orbit.zarr"))
  assert {k: v for k, v in archive.attributes.items() if k != "config"} == {
      k: v for k, v in reference.attributes.items() if k != "config"}
  _assert_close_frames(archive, reference, range(5))
  first = [archive.read_frame(i) for i in range(5)]
  # Process 0 exported the videos once every frame was there.
  assert (pod / "renders" / "orbit_rgb.mp4").stat().st_size > 0
  assert (pod / "renders" / "orbit_sheet.png").stat().st_size > 0
  _assert_whole_slice_programs(tmp_path)

  # Process 0's frames cut off (frame 2 half written): the resumed render redoes exactly those, process 1
  # taking part in every call with padding.
  for index in (0, 2, 4):
    archive.arrays["written_by"][index].write(np.int16(-1)).result()
  archive.arrays["rgb"][2].write(np.full_like(first[2]["rgb"], 5)).result()
  archive.arrays["rgb"][1].write(np.full_like(first[1]["rgb"], 9)).result()  # complete: not redone
  again_logs = tmp_path / "again"
  with procs.Run(pod, OVERRIDES, num_processes=2, devices_per_process=2, log_dir=again_logs,
                 extra_flags=["--mode=render", "--verbosity=0"], compiles_dir=again_logs) as again:
    again.wait_ok(RUN_TIMEOUT)
  assert _rendered(again.output(0)) == [("0", "0, 2, 4")] and _rendered(again.output(1)) == [("1", "")]
  assert "5 frames of 16x16 at step 2, 2 already written, over 2 process(es)" in again.output(0)
  np.testing.assert_array_equal(archive.written_by(), [0, 1, 0, 1, 0])
  for index in (0, 2, 3, 4):  # the same devices, the same blocks: the same bits
    for name, want in first[index].items():
      np.testing.assert_array_equal(archive.read_frame(index)[name], want, err_msg=f"{name} of frame {index}")
  assert (archive.read_frame(1)["rgb"] == 9).all()
  _assert_whole_slice_programs(again_logs)
