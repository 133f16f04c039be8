"""The chaos test: a 2 processes x 4 devices job SIGKILLed at random moments (start-up and restore, mid-step,
mid-save, during evaluation, during the orbit) and once SIGTERMed, each time restarted with the same command,
ends with exactly the parameters, eval/metrics.json and orbit archive of the same job run without a fault.

The moments are drawn from a fixed seed, SEED below, so that every run of the test aims at the same
moments; NERFPOD_TEST_SEED=N draws them from seed N instead (e.g. to replay a seed another run printed, or to
try new ones). Where a fault lands still depends on the machine's speed: each is classified by what the run
had done when it was killed (its log, and an orbax temporary folder for a save under way), and that fault
coverage (how many of each kind) is printed and put in every assertion message, not asserted, since a loaded
machine can shift a fault into the next phase. What is asserted: the SIGTERM ends both processes with
checkpoint.preempted_exit_code (75) or 0 (when training had already ended), at least one SIGKILL cut
training itself off, no run hit a traceback, the final run exits 0, and it ends with exactly the reference
run's parameters, step, metrics and orbit frames.
"""
import collections
import json
import os
import random
import signal
import time

import numpy as np
import pytest

import procs
from nerfpod.render import archive as archives
from nerfpod.workdir import checkpoints

pytestmark = pytest.mark.slow

SEED = int(os.environ.get("NERFPOD_TEST_SEED", "20251125"))
NUM_STEPS = 16
# Checkpoints every 2 steps (each save waits for the one before: the run moves at the pace of its saves,
# which leaves time to cut a save off), a short evaluation and an 8-frame orbit.
OVERRIDES = {"train.num_steps": NUM_STEPS, "train.batch_size": 128, "checkpoint.every_steps": 2,
             "checkpoint.max_to_keep": 2, "train.log_every": 1, "train.image_every": 0, "eval.max_views": 2,
             "orbit.num_frames": 8}
RUN_TIMEOUT = 300  # seconds for one run of 2 processes on a loaded 2-core machine: a bound for a hung run
KINDS = ("start-up/restore", "mid-step", "mid-save", "evaluation", "orbit")
# The schedule of SIGKILLs: what each one waits for before its random delay. Training faults first, then
# evaluation and orbit faults (which need training to be over), then a start-up fault of a finished run.
SCHEDULE = ("start-up/restore", "mid-step", "mid-save", "evaluation", "orbit", "start-up/restore")


def _saving(workdir) -> bool:
  directory = checkpoints.checkpoint_dir(str(workdir))
  return directory.exists() and any(".orbax-checkpoint-tmp" in p.name for p in directory.iterdir())


def _trained(out: str) -> bool:
  return f"step {NUM_STEPS:>6d}/{NUM_STEPS}" in out or f"steps {NUM_STEPS}..{NUM_STEPS}" in out


def _classify(out: str, saving: bool) -> str:
  """What a run was doing when it was killed, from its log."""
  if "nerfpod: scene" not in out:
    return "start-up/restore"
  if not _trained(out):
    return "mid-save" if saving else "mid-step"
  if "eval test:" not in out:
    return "evaluation"
  if "orbit: wrote" not in out:
    return "orbit"
  return "after the end"


def _wait_for_moment(run, workdir, kind: str, rng: random.Random) -> None:
  """Returns at a random moment of the phase `kind` of `run` (or when its processes have ended)."""
  deadline = time.monotonic() + RUN_TIMEOUT
  def out():
    return run.output(0)
  def ready():
    if kind == "start-up/restore":
      return True
    if kind in ("mid-step", "mid-save"):
      return "step " in out() and "nerfpod: scene" in out()
    if kind == "evaluation":
      return _trained(out())
    return "orbit: " in out() and "frames of" in out()
  while not ready() and time.monotonic() < deadline and all(p.poll() is None for p in run.procs):
    time.sleep(0.02)
  if kind == "start-up/restore":
    # Before its scene line: with the session's compilation cache a run printed it 4 s after its start on the
    # loaded 2-core machine (the kill aimed at 4.1 s landed mid-step).
    time.sleep(rng.uniform(0.2, 3.0))
  elif kind == "mid-save":  # the next save under way
    while not _saving(workdir) and time.monotonic() < deadline and all(p.poll() is None for p in run.procs):
      time.sleep(0.005)
    time.sleep(rng.uniform(0.0, 0.02))
  elif kind == "mid-step":
    time.sleep(rng.uniform(0.0, 1.0))
  else:
    time.sleep(rng.uniform(0.0, 0.5))


def _final(workdir):
  state, position, step = checkpoints.read_numpy(str(workdir))
  metrics = json.loads((workdir / "eval" / "metrics.json").read_text())
  orbit = archives.Archive.open(str(workdir / "renders" / "orbit.zarr"))
  orbit.check_complete()
  frames = [orbit.read_frame(i) for i in range(orbit.num_frames)]
  attributes = {k: v for k, v in orbit.attributes.items() if k != "config"}
  return state, position, step, metrics, frames, attributes


def test_sigkill_at_random_moments_and_a_sigterm_lose_nothing(tmp_path):
  started = time.monotonic()
  with procs.Run(tmp_path / "reference", OVERRIDES, num_processes=2, devices_per_process=4) as run:
    run.wait_ok(RUN_TIMEOUT)
  reference = _final(tmp_path / "reference")

  rng = random.Random(SEED)
  workdir = tmp_path / "chaos"
  tally = collections.Counter()
  history = []
  sigterm_at = rng.randrange(1, 3)  # a SIGTERM instead of the SIGKILL of this training-phase fault
  for attempt, kind in enumerate(SCHEDULE):
    with procs.Run(workdir, OVERRIDES, num_processes=2, devices_per_process=4) as run:
      _wait_for_moment(run, workdir, kind, rng)
      saving = _saving(workdir)
      if attempt == sigterm_at:
        run.signal(rng.randrange(2), signal.SIGTERM)  # one host gets it; they agree on a step
        codes = run.wait(RUN_TIMEOUT)
        assert codes in ([75, 75], [0, 0]), f"seed {SEED}: exit codes {codes} after a SIGTERM; " + "; ".join(
            history) + "\n" + run.tails()
        history.append(f"SIGTERM -> {codes}")
        tally["SIGTERM"] += 1
        continue
      finished = any(p.poll() is not None for p in run.procs)
      run.kill()
    what = "after the end" if finished else _classify(run.output(0), saving)
    tally[what] += 1
    history.append(f"SIGKILL aimed at {kind}: {what}")
    assert "Traceback" not in run.output(0), f"seed {SEED}: {dict(tally)}; " + "; ".join(history) + run.tails()

  with procs.Run(workdir, OVERRIDES, num_processes=2, devices_per_process=4) as run:
    run.wait_ok(RUN_TIMEOUT)
  out = run.output(0)
  took = time.monotonic() - started
  summary = f"seed {SEED}, {took:.0f} s: " + "; ".join(history)
  missed = [k for k in KINDS if not tally[k]]
  summary = (f"fault coverage {dict(tally)}" + (f" (no fault landed in: {', '.join(missed)})" if missed else "")
             + f"\n{summary}")
  print(f"\nchaos: {summary}")
  assert "Metadata file does not exist" not in out and "Traceback" not in out, summary + run.tails()
  assert tally["SIGTERM"] == 1, summary
  # One SIGKILL is aimed at training (the other of the two mid-step/mid-save moments gets the SIGTERM),
  # once the run has logged a step, after at most 1 s: a run saves every 2 of its 16 steps, each save waiting
  # for the one before, so training is not over that soon on any machine (load only makes it longer).
  assert tally["mid-step"] + tally["mid-save"] >= 1, summary

  state, position, step, metrics, frames, attributes = _final(workdir)
  want_state, want_position, want_step, want_metrics, want_frames, want_attributes = reference
  assert (step, position) == (want_step, want_position) == (NUM_STEPS, {"next_step": NUM_STEPS}), summary
  for (path, got), (_, want) in zip(_leaves(state), _leaves(want_state)):
    np.testing.assert_array_equal(got, want, err_msg=f"{path}; {summary}")
  assert metrics == want_metrics, summary
  assert attributes == want_attributes, summary
  for index, (got, want) in enumerate(zip(frames, want_frames)):
    for name in want:
      np.testing.assert_array_equal(got[name], want[name], err_msg=f"frame {index} {name}; {summary}")


def _leaves(tree):
  import jax
  return [(jax.tree_util.keystr(path), np.asarray(leaf)) for path, leaf in jax.tree.leaves_with_path(tree)]
