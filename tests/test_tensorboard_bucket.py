"""TensorBoard events of a gs:// workdir, against a Cloud Storage JSON API served on 127.0.0.1 (tests/gcs.py):
TensorBoard reads every scalar back from the bucket, in order, and what a run uploads grows with what it
writes, not with the square of its flushes (Cloud Storage objects cannot be appended to: a writer that
uploaded the whole event file again at each flush sent N/2 times the file over N flushes)."""
import os
import socket
import time

from nerfpod import monitor
from nerfpod.monitor import bucket_events

FLUSHES = 40  # a run's flushes: the whole-file writer sends about FLUSHES / 2 times its events
TAGS = ("train/loss", "train/psnr", "train/learning_rate")


def _value(tag: str, step: int) -> float:
  return TAGS.index(tag) + step / 1000.0


def _log(writer, steps) -> None:
  """Scalars every 100 steps, as training logs them, and a flush after each log step."""
  for step in steps:
    for tag in TAGS:
      writer.add_scalar(tag, _value(tag, step), step)
    writer.flush()


def _read_back(url: str) -> dict:
  """{tag: [(step, value), ...]} as TensorBoard reads the run folder `url`, with its own file reader (gs://:
  through fsspec's gcsfs, whose listings are made anew here: a gcsfs instance keeps those it made)."""
  import gcsfs
  from tensorboard.backend.event_processing import event_accumulator
  gcsfs.GCSFileSystem.clear_instance_cache()
  board = event_accumulator.EventAccumulator(url, size_guidance={"scalars": 0})
  try:
    board.Reload()
  except Exception as e:  # noqa: BLE001 (the run folder not in the bucket yet: its first upload is under way)
    if "NotFound" not in type(e).__name__ and "DirectoryDeleted" not in type(e).__name__:
      raise
    return {}
  return {tag: [(e.step, round(e.value, 6)) for e in board.Scalars(tag)] for tag in board.Tags()["scalars"]}


def _event_bytes(emulator, prefix: str) -> int:
  fs = emulator.filesystem()
  return sum(fs.size(f"{emulator.bucket}/{prefix}/{name}") for name in emulator.files(prefix)
             if name.startswith("events.out.tfevents."))


def test_a_bucket_workdir_s_scalars_read_back_in_order_and_each_byte_is_uploaded_about_once(emulator):
  workdir = f"gs://{emulator.bucket}/runs/scalars"
  before = emulator.received_bytes()
  writer = monitor.summary_writer(workdir)
  steps = [100 * (i + 1) for i in range(FLUSHES)]
  _log(writer, steps)
  writer.close()
  uploaded = emulator.received_bytes() - before

  names = emulator.files("runs/scalars")
  assert names and all(name.startswith("events.out.tfevents.") for name in names), names  # in WORKDIR itself
  want = {tag: [(step, round(_value(tag, step), 6)) for step in steps] for tag in TAGS}
  assert _read_back(workdir) == want
  written = _event_bytes(emulator, "runs/scalars")
  # What was sent: the events once, and each upload's request around them (its metadata, a few hundred bytes).
  assert uploaded <= 2 * written + 1024 * len(names), (uploaded, written, len(names))


def test_a_second_writer_on_the_same_bucket_workdir_adds_to_what_tensorboard_reads(emulator, monkeypatch):
  """A resumed run (or evaluation after training) writes the same workdir again: TensorBoard reads both, also
  where the second started in the same second as the first (tensorboardX's event file names, which hold the
  second, are then the same)."""
  import types

  from tensorboardX import event_file_writer
  monkeypatch.setattr(event_file_writer, "time", types.SimpleNamespace(time=lambda: 1795800000.25))
  workdir = f"gs://{emulator.bucket}/runs/resumed"
  first = monitor.summary_writer(workdir)
  _log(first, [100, 200, 300])
  first.close()
  second = monitor.summary_writer(workdir)
  _log(second, [400, 500])
  second.close()
  assert _read_back(workdir)["train/loss"] == [(step, round(_value("train/loss", step), 6))
                                               for step in (100, 200, 300, 400, 500)]
  same = f"events.out.tfevents.1795800000.{socket.gethostname()}"
  assert {name.rsplit(".", 1)[0] for name in emulator.files("runs/resumed")} == {same}


# A writer in a process of its own: it logs two log steps, then flushes every 0.1 s until it is killed.
_FLUSHING_WRITER = """
import sys, time
sys.path.insert(0, sys.argv[2])
from nerfpod import monitor
import test_tensorboard_bucket as t
writer = monitor.summary_writer(sys.argv[1])
t._log(writer, [100, 200])
print("logged", flush=True)
while True:
  writer.flush()
  time.sleep(0.1)
"""


def test_a_killed_writer_s_flushed_scalars_are_in_the_bucket(emulator):
  """A run's process killed (SIGKILL: nothing closes its writer) after its flushes has left the scalars of those
  flushes where TensorBoard reads them, the last log step's included."""
  import signal
  import subprocess
  import sys
  workdir = f"gs://{emulator.bucket}/runs/killed"
  want = {tag: [(step, round(_value(tag, step), 6)) for step in (100, 200)] for tag in TAGS}
  writer = subprocess.Popen([sys.executable, "-c", _FLUSHING_WRITER, workdir, os.path.dirname(__file__)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
  try:
    logged = writer.stdout.readline() == "logged\n"
    deadline = time.monotonic() + 60  # a flush uploads what the writer's thread has taken from its queue
    while logged and _read_back(workdir) != want and time.monotonic() < deadline and writer.poll() is None:
      time.sleep(0.1)
  finally:
    writer.send_signal(signal.SIGKILL)
    writer.wait(timeout=30)
  assert logged and writer.returncode == -signal.SIGKILL, writer.stderr.read()[-2000:]  # alive until killed
  assert _read_back(workdir) == want  # as the killed process left them


def test_an_event_object_s_name_is_never_taken_from_another_upload(emulator):
  """Objects are created only where there is none of the name: a writer that finds its next name taken goes
  on to the one after it, unless the object there is its own upload (a retry of one that was stored)."""
  url = f"gs://{emulator.bucket}/runs/names/events.out.tfevents.1795800000.host"
  first = bucket_events.BucketEventFile(url)
  first.write(b"first")
  first.flush()
  second = bucket_events.BucketEventFile(url)
  second.number = 0  # as if it had listed the bucket before the first's upload
  second.write(b"second")
  second.flush()
  again = bucket_events.BucketEventFile(url)
  again.number = 1  # the second's upload again, as a client's retry sends it
  again.write(b"second")
  again.close()
  assert emulator.files("runs/names") == ["events.out.tfevents.1795800000.host.00000000",
                                          "events.out.tfevents.1795800000.host.00000001"]
  assert [emulator.read(f"runs/names/{name}") for name in emulator.files("runs/names")] == [b"first", b"second"]
  assert (second.number, again.number) == (2, 2)


def test_a_local_workdir_keeps_one_event_file(tmp_path):
  writer = monitor.summary_writer(str(tmp_path))
  _log(writer, [100, 200, 300])
  writer.close()
  names = os.listdir(tmp_path)
  assert len(names) == 1 and names[0].startswith("events.out.tfevents."), names
  assert _read_back(str(tmp_path))["train/loss"] == [(s, round(_value("train/loss", s), 6)) for s in (100, 200, 300)]
