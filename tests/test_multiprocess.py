"""Real multi-process runs on 127.0.0.1: the same trajectory on any number of hosts and devices, exact
resume after SIGKILL, elastic restore, preemption by SIGTERM, a dead peer, and a refused workdir.

Every run is the same 24-step job; its uninterrupted result on 1 process x 8 devices (this pytest process)
is the reference every other run must end at.
"""
import json
import os
import random
import re
from signal import SIGINT, SIGTERM
import time

import jax
import numpy as np
import pytest

import procs
from conftest import smoke_config
from nerfpod import data, distributed, scenes
from nerfpod.run import modes
from nerfpod.workdir import checkpoints
from nerfpod.errors import UserError

pytestmark = pytest.mark.slow

NUM_STEPS = 24
OVERRIDES = {"train.num_steps": NUM_STEPS, "train.batch_size": 128, "checkpoint.every_steps": 6,
             "checkpoint.max_to_keep": 3, "train.log_every": 10, "train.image_every": 0,
             "eval.max_views": 2, "orbit.render_after_training": False,
             # Real captures' per-frame appearance codes, replicated and averaged like the rest: the equality and
             # resume checks below cover them too. (Pose refinement, which makes every step about 80% dearer,
             # is checked 8 devices against 1 and through a resume in tests/test_per_frame.py.)
             "model.appearance_dim": 4,
             # NeRF-W's half-image code fit at evaluation, checked 2 x 4 against 1 x 8 below: a few steps on a
             # few rays each do that (its default 100 steps of 1,024 rays took 7 of a warm run's 20 s).
             "eval.appearance_steps": 5, "eval.appearance_rays": 64,
             # BARF's test-time pose fit (the smoke config's 5 steps of 64 rays), on a run without refinement
             # ('always'): the same fitter, checked 2 x 4 against 1 x 8 below.
             "eval.pose_fit": "always"}
# How close two runs' parameters must be, per tensor: the norm of the difference relative to the tensor's
# norm, and the fraction of entries off by more than 1e-3 of the tensor's largest magnitude. 2x4 and 1x8
# devices sum the gradient mean in the same order (distributed.ordered_mean): on this config they give the
# same bits (on bigger ones XLA:CPU's per-process compilation differs; README, Never losing work). 1 or 2
# devices sum it in another
# order, and Adam (eps 1e-15) divides each gradient component by its own running RMS, so where a hash-grid
# entry's gradient is nearly zero the round-off can flip the sign of its update: a handful of entries
# then differ by a few lr-sized steps while the rest agree to round-off.
SAME_SUMS = {"rel_tol": 0.0, "outliers": 0.0}
OTHER_SUMS = {"rel_tol": 1e-2, "outliers": 0.01}
# Seconds any one run may take on a loaded 2-core machine: a bound for a hung run, not a speed check. The
# slowest, 2 x 4 devices under XLA's default flags (whose evaluation programs compile slower than the tests'),
# took 46 s alone with a cold compilation cache and over 120 s in one CI run beside the other worker.
RUN_TIMEOUT = 300
# Moments of interruption are drawn from this fixed seed, as in test_chaos (NERFPOD_TEST_SEED=N draws them from
# seed N instead); every assertion message that depends on one names the seed.
SEED = int(os.environ.get("NERFPOD_TEST_SEED", "20251125"))
# The same job, checkpointed every 2 steps: as each save waits for the previous one to finish, the run
# moves at the pace of its saves, which leaves time to interrupt it after a checkpoint and before its end.
# (Checkpoint settings may change between a run and its resumption; they do not touch the trajectory.)
THROTTLED = dict(OVERRIDES, **{"checkpoint.every_steps": 2})


def assert_params_close(workdir, reference, rel_tol, outliers):
  state, position, step = checkpoints.read_numpy(str(workdir))
  assert step == NUM_STEPS and position == {"next_step": NUM_STEPS} and int(state["step"]) == NUM_STEPS
  got, want = jax.tree.leaves_with_path(state["params"]), jax.tree.leaves_with_path(reference)
  assert [path for path, _ in got] == [path for path, _ in want]
  for (path, a), (_, b) in zip(got, want):
    name = jax.tree_util.keystr(path)
    rel = np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-12)
    off = np.mean(np.abs(a - b) > 1e-3 * np.abs(b).max())
    assert rel <= rel_tol, f"{name}: relative difference {rel:.2e} > {rel_tol:.0e}"
    assert off <= outliers, f"{name}: {off:.2%} of the entries differ, more than {outliers:.0%}"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
  """Final parameters of the uninterrupted job on 1 process x 8 devices."""
  workdir = tmp_path_factory.mktemp("reference")
  modes.train_and_evaluate(smoke_config(**OVERRIDES), str(workdir))
  state, _, step = checkpoints.read_numpy(str(workdir))
  assert step == NUM_STEPS
  return {"workdir": workdir, "params": state["params"]}


def test_two_processes_as_two_slices_and_one_device_follow_the_same_trajectory(reference, tmp_path):
  """2 processes x 4 devices, each process one simulated slice as on TPU multi-slice (mesh.slices=2: a
  (slice, data) mesh, the gradient mean within each slice, then across the two), end at exactly the
  parameters of 1 process x 8 devices in one slice, each process loading its own half of every batch; one
  process of one device follows the same trajectory. (The other 2 x 4 runs below are single-slice.)"""
  record = tmp_path / "record"
  record.mkdir()
  with procs.Run(tmp_path / "pod", dict(OVERRIDES, **{"mesh.slices": 2}), num_processes=2, devices_per_process=4,
                 record_dir=record) as pod:
    pod.wait_ok(RUN_TIMEOUT)
  assert "2 process(es), 8 device(s) in 2 slices" in pod.output(0)
  assert_params_close(tmp_path / "pod", reference["params"], **SAME_SUMS)
  # The same parameters, bit for bit, evaluated by the 2 processes (each rendering its share of every view's
  # rays) give exactly 1 process's eval/metrics.json: every view's PSNR and SSIM, and their means.
  pod_metrics = json.loads((tmp_path / "pod" / "eval" / "metrics.json").read_text())
  assert len(pod_metrics["views"]) == 2
  one_metrics = json.loads((reference["workdir"] / "eval" / "metrics.json").read_text())
  # NeRF-W's half-image code fit (the run has appearance codes): each process fits on its share of the rays,
  # the gradient averaged in the step's order; the fitted views agree to round-off (1e-8 relative seen).
  pod_half, one_half = pod_metrics.pop("appearance_half"), one_metrics.pop("appearance_half")
  pod_fit, one_fit = pod_metrics.pop("poses_optimised"), one_metrics.pop("poses_optimised")  # likewise
  assert pod_metrics == one_metrics
  for got, want in zip(pod_half["views"] + [pod_half["mean"]] + pod_fit["views"] + [pod_fit["mean"]],
                       one_half["views"] + [one_half["mean"]] + one_fit["views"] + [one_fit["mean"]]):
    for name in ("psnr", "ssim"):
      assert got[name] == pytest.approx(want[name], rel=1e-6), (name, got, want)
  for got, want in zip(pod_fit["views"], one_fit["views"]):
    assert got["correction"] == pytest.approx(want["correction"], rel=1e-4, abs=1e-7)

  # Each process loaded its own half of every global batch, and the halves make up the whole batch.
  config = smoke_config(**OVERRIDES)
  split = scenes.load(config.data).split("train")
  batch = config.train.batch_size
  whole = data.ray_batches(split, config.train.seed, batch, slice(0, batch), config.data.pixel_center,
                           NUM_STEPS)
  loaded = [np.load(record / f"process_{i}.npz") for i in range(2)]
  for step in range(NUM_STEPS):
    rows = [np.flatnonzero(part["steps"] == step) for part in loaded]
    assert all(len(r) == 1 for r in rows), f"step {step} not loaded once by each process"
    ids = [part["ray_ids"][r[0]] for part, r in zip(loaded, rows)]
    np.testing.assert_array_equal(ids[0], np.arange(0, batch // 2))
    np.testing.assert_array_equal(ids[1], np.arange(batch // 2, batch))
    expected = whole[step]
    for key in ("origins", "directions", "rgb"):
      np.testing.assert_array_equal(
          np.concatenate([part[key][r[0]] for part, r in zip(loaded, rows)]), expected[key])

  with procs.Run(tmp_path / "single", OVERRIDES, devices_per_process=1) as single:
    single.wait_ok(RUN_TIMEOUT)
  assert "1 process(es), 1 device(s)" in single.output(0)
  assert_params_close(tmp_path / "single", reference["params"], **OTHER_SUMS)


def test_sigkill_at_any_moment_then_restart_ends_with_the_same_parameters(reference, tmp_path):
  workdir = tmp_path / "run"
  with procs.Run(workdir, THROTTLED) as run:
    run.wait_for(lambda: checkpoints.latest_step(str(workdir)) is not None, RUN_TIMEOUT, "a checkpoint")
    time.sleep(random.Random(SEED).uniform(0.0, 0.3))  # mid-step, mid-save, whichever it is now
    run.kill()
  stopped_at = checkpoints.latest_step(str(workdir))
  assert stopped_at is not None and stopped_at < NUM_STEPS, f"the run was not cut short (seed {SEED})"
  with procs.Run(workdir, OVERRIDES) as again:
    again.wait_ok(RUN_TIMEOUT)
  assert f"steps {stopped_at}..{NUM_STEPS}" in again.output(0), f"seed {SEED}: " + again.tails()
  # Same devices as the reference: the same computations, so (all but) the same bits.
  assert_params_close(workdir, reference["params"], rel_tol=1e-6, outliers=0.0)


def test_under_xlas_default_flags_two_hosts_and_a_killed_then_resumed_run_end_at_one_processs_bits(tmp_path):
  """The two exactness claims above (2 x 4 devices = 1 x 8; a run killed at any moment and restarted = one never
  interrupted), also as users' runs compile: XLA's default flags (XLA_FLAGS empty), not the test processes'
  procs.TEST_XLA_FLAGS, whose loop emitters add some fused reductions in another order. The reference is then
  a process of its own too: this pytest process compiles with the test flags."""
  users = {"XLA_FLAGS": ""}
  with procs.Run(tmp_path / "one", OVERRIDES, env=users) as one:
    one.wait_ok(RUN_TIMEOUT)
  want, _, _ = checkpoints.read_numpy(str(tmp_path / "one"))
  with procs.Run(tmp_path / "pod", OVERRIDES, num_processes=2, devices_per_process=4, env=users) as pod:
    pod.wait_ok(RUN_TIMEOUT)
  assert "2 process(es), 8 device(s)" in pod.output(0)
  assert_params_close(tmp_path / "pod", want["params"], **SAME_SUMS)

  workdir = tmp_path / "run"
  with procs.Run(workdir, THROTTLED, env=users) as run:
    run.wait_for(lambda: checkpoints.latest_step(str(workdir)) is not None, RUN_TIMEOUT, "a checkpoint")
    time.sleep(random.Random(SEED + 1).uniform(0.0, 0.3))
    run.kill()
  stopped_at = checkpoints.latest_step(str(workdir))
  assert stopped_at is not None and stopped_at < NUM_STEPS, f"the run was not cut short (seed {SEED})"
  with procs.Run(workdir, OVERRIDES, env=users) as again:
    again.wait_ok(RUN_TIMEOUT)
  assert f"steps {stopped_at}..{NUM_STEPS}" in again.output(0), f"seed {SEED}: " + again.tails()
  assert_params_close(workdir, want["params"], **SAME_SUMS)


def test_sigterm_to_one_host_saves_an_agreed_step_then_resumes_on_another_topology(reference, tmp_path):
  workdir = tmp_path / "pod"
  with procs.Run(workdir, THROTTLED, num_processes=2, devices_per_process=4) as pod:
    pod.wait_for(lambda: "step      1/" in pod.output(0), RUN_TIMEOUT, "first training step")
    pod.signal(1, SIGTERM)  # what a TPU VM gets before maintenance, here on one host only
    # Exit 75 (checkpoint.preempted_exit_code): stopped early, run me again. (The step: asserted below.)
    assert pod.wait(RUN_TIMEOUT) == [75, 75], pod.tails()
  lines = [l for l in pod.output(0).splitlines() if l.startswith("nerfpod: preempted")]
  assert len(lines) == 1, pod.tails()
  agreed = checkpoints.latest_step(str(workdir))
  assert 0 < agreed < NUM_STEPS and f"saved step {agreed} " in lines[0]
  assert not (workdir / "eval" / "metrics.json").exists()  # no evaluation after a preemption

  # Written by 2 processes x 4 devices, continued by 1 process x 2 devices.
  with procs.Run(workdir, OVERRIDES, devices_per_process=2) as elastic:
    elastic.wait_ok(RUN_TIMEOUT)
  assert f"1 process(es), 2 device(s), steps {agreed}..{NUM_STEPS}" in elastic.output(0)
  assert_params_close(workdir, reference["params"], **OTHER_SUMS)


def test_preemptions_in_one_process_and_in_a_just_resumed_pod_lose_nothing(reference, tmp_path):
  workdir = tmp_path / "run"
  with procs.Run(workdir, THROTTLED, devices_per_process=2) as run:
    run.wait_for(lambda: "step      1/" in run.output(0), RUN_TIMEOUT, "first training step")
    run.signal(0, SIGINT)  # Ctrl-C: a preemption too, in one line, without a traceback
    assert run.wait(60) == [75], run.tails()
  assert "nerfpod: preempted: saved step" in run.output(0)
  assert "nerfpod: interrupted: saving the current step" in run.output(0)
  assert "Traceback" not in run.output(0) and "KeyboardInterrupt" not in run.output(0)
  first = checkpoints.latest_step(str(workdir))
  assert 0 < first < NUM_STEPS

  # Written by 1 process x 2 devices, continued by 2 processes x 4 devices started by launch/local.py,
  # which passes a SIGTERM on to both as soon as they have restored: before their first step.
  with procs.Run(workdir, THROTTLED, num_processes=2, devices_per_process=4, via_launcher=True) as pod:
    pod.wait_for(lambda: f"steps {first}..{NUM_STEPS}" in pod.output(0), RUN_TIMEOUT, "the restore")
    pod.signal(0, SIGTERM)
    assert pod.wait(60) == [75], pod.tails()  # the launcher passes the processes' 75 on
  assert f"2 process(es), 8 device(s), steps {first}..{NUM_STEPS}" in pod.output(0)
  assert "nerfpod: preempted: saved step" in pod.output(0), pod.tails()
  second = checkpoints.latest_step(str(workdir))
  assert first < second < NUM_STEPS

  # (Topologies the tests above compiled already: a program read back from the compilation cache, not built.)
  with procs.Run(workdir, OVERRIDES, devices_per_process=8) as last:
    last.wait_ok(RUN_TIMEOUT)
  assert f"1 process(es), 8 device(s), steps {second}..{NUM_STEPS}" in last.output(0)
  assert_params_close(workdir, reference["params"], **OTHER_SUMS)


def test_a_dead_process_stops_the_others_within_the_heartbeat_timeout(tmp_path):
  workdir = tmp_path / "pod"
  heartbeat = 6
  overrides = dict(OVERRIDES, **{"train.num_steps": 100000, "checkpoint.every_steps": 3})
  with procs.Run(workdir, overrides, num_processes=2, devices_per_process=4,
                 extra_flags=[f"--heartbeat_timeout_seconds={heartbeat}"]) as pod:
    pod.wait_for(lambda: checkpoints.latest_step(str(workdir)) is not None, RUN_TIMEOUT,
                 "first checkpoint")
    saved_before = checkpoints.latest_step(str(workdir))
    pod.kill(1)
    killed = time.monotonic()
    codes = pod.wait(timeout=heartbeat + 30)
    took = time.monotonic() - killed
  assert codes[0] != 0, pod.tails()
  assert took < heartbeat + 15, f"the survivor took {took:.1f} s to stop"
  out = pod.output(0)
  # The coordination service's words (jax 0.10.2), either one; a JAX that words both otherwise fails here.
  assert "another task died" in out or "stopped sending heartbeats" in out, pod.tails()
  # What was saved before is still there, complete, and restorable.
  latest = checkpoints.latest_step(str(workdir))
  assert latest >= saved_before
  state, position, step = checkpoints.read_numpy(str(workdir))
  assert position == {"next_step": latest} and int(state["step"]) == latest


def test_resuming_with_another_model_shape_is_refused_in_one_sentence(reference, tmp_path):
  changed = dict(OVERRIDES, **{"model.hashgrid.num_levels": 2, "model.hashgrid.hidden_width": 8,
                               "train.num_steps": NUM_STEPS + 10})
  with procs.Run(reference["workdir"], changed, log_dir=tmp_path) as run:
    codes = run.wait(RUN_TIMEOUT)
  out = run.output(0)
  assert codes == [2], run.tails()
  errors = [l for l in out.splitlines() if l.startswith("nerfpod: error:")]
  assert len(errors) == 1 and "Traceback" not in out
  assert "model.hashgrid.hidden_width (16 -> 8)" in errors[0]
  assert "model.hashgrid.num_levels (4 -> 2)" in errors[0]
  assert "train.num_steps" not in errors[0].split(";")[0]  # allowed to change
  assert checkpoints.latest_step(str(reference["workdir"])) == NUM_STEPS  # untouched


@pytest.mark.parametrize("args,env,message", [
    ({"coordinator_address": "127.0.0.1:1234", "num_processes": 2}, {}, "needs all of --coordinator_address"),
    ({"num_processes": 2, "process_id": 0}, {}, "needs all of --coordinator_address"),
    ({}, {"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"}, "needs all of --coordinator_address"),
    ({"coordinator_address": "127.0.0.1:1234", "num_processes": 2, "process_id": 2}, {}, "outside [0, 2)"),
    ({}, {"JAX_NUM_PROCESSES": "two"}, "must be integers"),
    ({"heartbeat_timeout_seconds": 0}, {}, "--heartbeat_timeout_seconds=0 must be a positive"),
])
def test_initialize_refuses_an_incomplete_or_impossible_multi_process_setting(monkeypatch, args, env, message):
  for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
    monkeypatch.delenv(name, raising=False)
  for name, value in env.items():
    monkeypatch.setenv(name, value)
  with pytest.raises(UserError, match=re.escape(message)):
    distributed.initialize(**args)


def test_initialize_without_settings_off_tpu_is_a_single_process(monkeypatch):
  for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID", "TPU_WORKER_HOSTNAMES"):
    monkeypatch.delenv(name, raising=False)
  distributed.initialize()
  assert not jax.distributed.is_initialized() and jax.process_count() == 1
