"""One writer per workdir: the lock refuses a live holder in one sentence, takes over a dead one (a pid gone
on this host, a heartbeat stopped on another), and a second training run arriving at any moment of a first
one is refused while the first ends with the uninterrupted run's parameters."""
import json
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import procs
from lock_clock import until, watch_clock
from nerfpod.workdir import checkpoints, lock as workdir_lock
from nerfpod.errors import UserError


@pytest.fixture
def short_lease(monkeypatch):
  monkeypatch.setattr(workdir_lock, "HEARTBEAT_SECONDS", 0.1)
  monkeypatch.setattr(workdir_lock, "LEASE_SECONDS", 1.5)


def _write_lock(workdir, **holder):
  (workdir / workdir_lock.NAME).write_text(json.dumps(holder))


def test_a_held_workdir_is_refused_naming_the_holder_and_released_at_the_end(tmp_path):
  with workdir_lock.WorkdirLock(str(tmp_path)) as lock:
    holder = json.loads((tmp_path / workdir_lock.NAME).read_text())
    assert holder["host"] == socket.gethostname() and holder["pid"] == os.getpid()
    with pytest.raises(UserError) as refused:
      workdir_lock.WorkdirLock(str(tmp_path)).acquire()
    message = str(refused.value)
    assert message.count(". ") == 0 and message.endswith(".")
    assert f"workdir {tmp_path} is in use by another training run (process {os.getpid()} on host " \
           f"{socket.gethostname()} since {holder['since']} holds {lock.path})" in message
  assert not (tmp_path / workdir_lock.NAME).exists()
  with workdir_lock.WorkdirLock(str(tmp_path)):  # free again
    pass


def test_a_lock_whose_process_is_gone_is_taken_over_at_once(tmp_path):
  gone = subprocess.Popen([sys.executable, "-c", "pass"])
  gone.wait()
  _write_lock(tmp_path, host=socket.gethostname(), pid=gone.pid, process_start="1", since="2026-01-01T00:00:00")
  started = time.monotonic()
  with workdir_lock.WorkdirLock(str(tmp_path)):
    assert json.loads((tmp_path / workdir_lock.NAME).read_text())["pid"] == os.getpid()
  assert time.monotonic() - started < 1.0
  # A pid that now belongs to another process (this one) started at another time: the holder is gone too.
  _write_lock(tmp_path, host=socket.gethostname(), pid=os.getpid(), process_start="-1", since="x")
  with workdir_lock.WorkdirLock(str(tmp_path)):
    assert json.loads((tmp_path / workdir_lock.NAME).read_text())["process_start"] != "-1"
  # A lock file cut off while it was written (empty): its holder cannot be alive on this host... nor named;
  # it is judged by its heartbeat, like another host's.
  (tmp_path / workdir_lock.NAME).write_text("")
  os.utime(tmp_path / workdir_lock.NAME, (0, 0))
  with workdir_lock.WorkdirLock(str(tmp_path)):
    pass


def test_another_hosts_lock_is_refused_while_it_beats_and_taken_over_once_it_stops(tmp_path, short_lease, monkeypatch):
  _write_lock(tmp_path, host="elsewhere-host", pid=12345, since="2026-01-01T00:00:00")
  stop = threading.Event()

  def beat():
    while not stop.wait(0.1):
      os.utime(tmp_path / workdir_lock.NAME)

  beating = threading.Thread(target=beat)
  beating.start()
  try:
    started = time.monotonic()
    with pytest.raises(UserError, match="process 12345 on host elsewhere-host since 2026-01-01T00:00:00"):
      workdir_lock.WorkdirLock(str(tmp_path)).acquire()
    assert time.monotonic() - started < 1.0  # refused at its first beat, not at the end of a lease
  finally:
    stop.set()
    beating.join()
  stopped = time.monotonic()
  clock = watch_clock(monkeypatch)  # nothing beats from here on: a lease passes on the watch's clock
  with workdir_lock.WorkdirLock(str(tmp_path)):  # the holder stopped beating: it is taken over after a lease
    assert json.loads((tmp_path / workdir_lock.NAME).read_text())["pid"] == os.getpid()
  # Watched until a lease (1.5 s) had passed since its last beat (at most 0.1 s before it stopped), by the watch's
  # clock and the real time since, and no look's sleep (0.5 s) longer.
  assert clock.offset + (time.monotonic() - stopped) + 0.1 >= 1.5 and clock.offset <= 1.5 + 0.5
  # A heartbeat older than a lease is stale at once: taken without watching it at all.
  _write_lock(tmp_path, host="elsewhere-host", pid=1, since="x")
  os.utime(tmp_path / workdir_lock.NAME, (time.time() - 60, time.time() - 60))
  slept = clock.offset
  with workdir_lock.WorkdirLock(str(tmp_path)):
    pass
  assert clock.offset == slept


def test_the_holder_beats_and_release_leaves_another_holders_lock(tmp_path, short_lease):
  lock = workdir_lock.WorkdirLock(str(tmp_path))
  lock.acquire()
  os.utime(lock.path, (0, 0))
  until(lambda: os.stat(lock.path).st_mtime > 0)  # a beat every 0.1 s (a busy machine's 10 s)
  assert time.time() - os.stat(lock.path).st_mtime < 10.0  # touched by the heartbeat, with this host's time
  _write_lock(tmp_path, host="elsewhere-host", pid=1, since="x")  # (someone replaced it by hand)
  lock.release()
  assert json.loads((tmp_path / workdir_lock.NAME).read_text())["host"] == "elsewhere-host"


# The fault test: a second run of the same command started at random moments of a first one.
SEED = int(os.environ.get("NERFPOD_TEST_SEED", "20251125"))
NUM_STEPS = 16
OVERRIDES = {"train.num_steps": NUM_STEPS, "train.batch_size": 128, "checkpoint.every_steps": 2,
             "checkpoint.max_to_keep": 2, "train.log_every": 1, "train.image_every": 0, "eval.max_views": 1,
             "orbit.num_frames": 2}
RUN_TIMEOUT = 300  # seconds one run may take on a loaded 2-core machine: a bound for a hung run


@pytest.mark.slow
def test_a_second_run_at_random_moments_is_refused_and_the_first_ends_as_if_alone(tmp_path):
  reference = tmp_path / "reference"
  with procs.Run(reference, OVERRIDES, devices_per_process=2) as run:
    run.wait_ok(RUN_TIMEOUT)
  want, _, _ = checkpoints.read_numpy(str(reference))

  rng = random.Random(SEED)
  workdir = tmp_path / "run"
  moments = []
  with procs.Run(workdir, OVERRIDES, devices_per_process=2) as first:
    for phase in ("training", "evaluation and orbit"):
      if phase == "training":
        first.wait_for(lambda: "step " in first.output(0), RUN_TIMEOUT, "a training step")
      else:
        first.wait_for(lambda: f"step {NUM_STEPS:>6d}/{NUM_STEPS}" in first.output(0), RUN_TIMEOUT, "the end of training")
      time.sleep(rng.uniform(0.0, 0.3))
      # The first run is paused (SIGSTOP) where it is while the second starts, so that the second meets it
      # in this phase however slowly the second starts on a loaded machine; a paused holder is alive.
      first.kill(sig=signal.SIGSTOP)
      try:
        started = time.monotonic()
        second = procs.run_main("--config=configs/default.py:smoke", f"--workdir={workdir}",
                                *procs.overrides_to_flags(OVERRIDES), devices_per_process=2, timeout=RUN_TIMEOUT)
        took = time.monotonic() - started
      finally:
        first.kill(sig=signal.SIGCONT)
      moments.append(f"{phase}: refused in {took:.1f} s")
      errors = [line for line in second.stderr.splitlines() if line.startswith("nerfpod: error:")]
      assert second.returncode == 2 and len(errors) == 1 and "Traceback" not in second.stderr, (
          f"seed {SEED}, {moments}: {second.stderr[-3000:]}")
      assert f"is in use by another training run (process {first.procs[0].pid} on host" in errors[0], errors
    first.wait_ok(RUN_TIMEOUT)
  print(f"\nsecond writers (seed {SEED}): {moments}")
  got, position, step = checkpoints.read_numpy(str(workdir))
  assert step == NUM_STEPS and position == {"next_step": NUM_STEPS}
  assert len(_leaves(got["params"])) == len(_leaves(want["params"]))
  for a, b in zip(_leaves(got["params"]), _leaves(want["params"])):
    np.testing.assert_array_equal(a, b)
  assert not (workdir / workdir_lock.NAME).exists()

  # Two runs started together on a new workdir: one trains, the other is refused.
  raced = tmp_path / "raced"
  with procs.Run(raced, OVERRIDES, devices_per_process=2) as one, \
       procs.Run(raced, OVERRIDES, devices_per_process=2, log_dir=tmp_path / "raced-other") as other:
    codes = sorted(one.wait(RUN_TIMEOUT) + other.wait(RUN_TIMEOUT))
    logs = one.output(0) + other.output(0)
  assert codes == [0, 2] and logs.count("is in use by another training run") == 1, logs[-3000:]
  got, _, _ = checkpoints.read_numpy(str(raced))
  for a, b in zip(_leaves(got["params"]), _leaves(want["params"])):
    np.testing.assert_array_equal(a, b)

  # (A holder SIGKILLed leaves its lock behind, which the next run takes over at once: every restart of
  # tests/test_chaos.py does that, and test_a_lock_whose_process_is_gone_is_taken_over_at_once above.)


def _leaves(tree):
  import jax
  return jax.tree.leaves(tree)
