"""A gs:// workdir whose storage stops answering mid-run (a partition, an outage, revoked credentials): the run
stops within checkpoint.storage_timeout_s with one sentence naming the bucket, what failed and the newest
committed checkpoint (exit 69), a SIGTERM meanwhile changes nothing to that bound, and once storage is back the
same command resumes from that checkpoint to the bits of an uninterrupted run. Against the emulator behind
tests/gcs.py's Proxy, which stops answering (connections accepted, requests read, never answered) and comes back
with the emulator's objects kept."""
import os
import re
import signal
import time

import jax
import numpy as np
import pytest

import gcs
import procs
from nerfpod import storage
from nerfpod.workdir import checkpoints

TIMEOUT_S = 4.0  # checkpoint.storage_timeout_s of these runs
# Past the timeout, what a run may take to end: the step under way, the sentence, nothing waited for.
ENDING_S = 8.0
RUN = {"train.log_every": 1, "train.image_every": 0, "checkpoint.every_steps": 5,
       "orbit.render_after_training": False, "checkpoint.storage_timeout_s": TIMEOUT_S}
RUN_TIMEOUT = 240


def sentence(step) -> str:
  """The one line a run that lost its storage while saving `step` ends with (a regex; `step` may be one)."""
  return (rf"nerfpod: error: the bucket gs://{gcs.BUCKET} stopped answering while saving the checkpoint of step "
          rf"({step}) \(no answer in 4 s\); the newest committed checkpoint is step 5: rerun the same command once "
          rf"storage is back \(it resumes from there\)\.")


def assert_stopped_with_one_sentence(run, silent_since: float, step) -> int:
  """The run exits 69 within the bound after its storage went silent, its output ending with the one sentence
  (no traceback, no other error); returns the step the sentence names."""
  codes = run.wait(TIMEOUT_S + ENDING_S + 30)  # (fails, with the logs, past it)
  took = time.monotonic() - silent_since
  out = run.output()
  assert codes == [storage.STOPPED_EXIT_CODE], run.tails()
  assert took < TIMEOUT_S + ENDING_S, (took, run.tails())
  lines = out.strip().splitlines()
  said = re.fullmatch(sentence(step), lines[-1])
  assert said, run.tails()
  last_step = max((i for i, line in enumerate(lines) if line.startswith("step ")), default=0)
  assert "Traceback" not in out and sum(line.startswith("nerfpod: error") for line in lines) == 1, out
  assert len(lines) - last_step <= 4, out  # the sentence, and no flood before it
  return int(said.group(1))


def test_within_waits_for_a_bucket_at_most_its_deadline_and_then_gives_up_on_it_at_once(monkeypatch):
  monkeypatch.setattr(storage, "_stopped", set())
  assert storage.within("/a/local/dir", 0.01, lambda: time.sleep(0.05) or "local") == "local"  # not bounded
  assert storage.within("gs://b/run", 5, lambda: "answered") == "answered"
  with pytest.raises(KeyError):
    storage.within("gs://b/run", 5, lambda: {}["x"])  # its own error, as it is
  assert not storage.stopped("gs://b/other")
  started = time.monotonic()
  with pytest.raises(storage.NoAnswer, match=r"^gs://b gave no answer in 0.2 s$"):
    storage.within("gs://b/run", 0.2, lambda: time.sleep(30))
  assert time.monotonic() - started < 2
  assert storage.stopped("gs://b/anything") and not storage.stopped("gs://c/run") and not storage.stopped("/b")
  with pytest.raises(storage.NoAnswer):  # at once, without calling
    storage.within("gs://b/run", 5, lambda: pytest.fail("called"))


def test_orbax_and_gcsfs_error_logs_of_a_storage_failure_are_dropped_and_others_pass():
  import logging
  from nerfpod.workdir import quiet as quiet_lib
  quiet = quiet_lib._StorageFailureIsReported()

  def record(error, level=logging.ERROR):
    try:
      try:
        raise error
      except Exception as inner:
        raise RuntimeError("Failed to run 4 Handler Commit operations") from inner
    except RuntimeError as outer:
      return logging.LogRecord("absl", level, __file__, 1, "failed", (), (type(outer), outer, None))

  assert not quiet.filter(record(ConnectionRefusedError(111, "Connect call failed")))
  assert not quiet.filter(record(TimeoutError()))
  assert not quiet.filter(record(ValueError("UNAVAILABLE: CURL error: Couldn't connect to server")))
  assert quiet.filter(record(ValueError("a shape mismatch")))  # not storage's
  assert quiet.filter(record(ConnectionRefusedError(111, "refused"), level=logging.WARNING))  # (a warning)
  assert quiet.filter(logging.LogRecord("absl", logging.ERROR, __file__, 1, "no exception", (), None))


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
  """(parameters, data position, step) of the job run to its end uninterrupted, in a local workdir."""
  workdir = tmp_path_factory.mktemp("uninterrupted") / "run"
  with procs.Run(workdir, RUN) as run:
    run.wait_ok(RUN_TIMEOUT)
  state, position, step = checkpoints.read_numpy(str(workdir))
  return state["params"], position, step


@pytest.mark.slow
def test_a_bucket_that_stops_answering_stops_the_run_in_one_sentence_and_the_rerun_resumes_exactly(
    emulator, tmp_path, uninterrupted):
  workdir = f"gs://{emulator.bucket}/runs/away"
  with gcs.Proxy(emulator) as proxy:
    # Silent from the commit of step 10 on: its arrays and metadata are in the bucket, its commit marker never
    # is; the run finds out when it waits for that save, at step 15.
    proxy.silent_at(b"runs/away/checkpoints/10/commit_success.txt")
    with procs.Run(workdir, RUN, env=proxy.env, log_dir=tmp_path / "logs") as run:
      assert proxy.went_silent.wait(RUN_TIMEOUT), run.tails()
      assert_stopped_with_one_sentence(run, time.monotonic(), 10)
    # (the test reads the emulator itself) Step 10 written but for its commit, which orbax never takes as a
    # checkpoint: the newest is still step 5.
    cut_off = [name for name in emulator.files("runs/away/checkpoints") if name.startswith("10/")]
    assert cut_off and "10/commit_success.txt" not in cut_off, cut_off
    assert checkpoints.latest_step(workdir) == 5

    proxy.forward()  # storage is back, with what it held
    with procs.Run(workdir, RUN, env=proxy.env, log_dir=tmp_path / "logs") as run:
      run.wait_ok(RUN_TIMEOUT)
    out = run.output()
    assert "steps 5..20" in out and "Traceback" not in out, run.tails()
  state, position, step = checkpoints.read_numpy(workdir)
  params = state["params"]
  want_params, want_position, want_step = uninterrupted
  assert (step, position) == (want_step, want_position) == (20, {"next_step": 20})
  jax.tree.map(np.testing.assert_array_equal, params, want_params)
  assert "lock.json" not in emulator.files("runs/away")  # the rerun took the stopped run's lock and released it


@pytest.mark.slow
def test_an_endpoint_that_refuses_connections_mid_run_is_the_same_sentence(emulator, tmp_path):
  """The emulator's process stopped (its objects kept by the proxy's refusing in its place): connections
  refused and reset, which the clients retry for longer than the bound."""
  workdir = f"gs://{emulator.bucket}/runs/refused"
  with gcs.Proxy(emulator) as proxy:
    with procs.Run(workdir, RUN, env=dict(proxy.env, NERFPOD_TEST_STEP_SECONDS="6:0.3"),
                   log_dir=tmp_path / "logs") as run:
      run.wait_for(lambda: "checkpoints/5/commit_success.txt" in emulator.files("runs/refused"), RUN_TIMEOUT,
                   "the checkpoint of step 5 committed")
      time.sleep(1.0)  # (orbax's last requests for step 5, after its commit marker)
      proxy.refuse()
      assert_stopped_with_one_sentence(run, time.monotonic(), 10)
  assert checkpoints.latest_step(workdir) == 5


@pytest.mark.slow
def test_a_sigterm_while_the_bucket_does_not_answer_ends_the_run_within_the_bound(emulator, tmp_path):
  """A SIGTERM between two checkpoints, with the bucket silent: the preemption's save cannot be committed, so
  the run ends on the sentence within the bound (not 75, which says the step was saved); with the bucket back,
  a SIGTERM saves the step and exits 75 as ever."""
  workdir = f"gs://{emulator.bucket}/runs/term"
  slow = {"NERFPOD_TEST_STEP_SECONDS": "6:0.5"}  # steps 6.. take half a second: signalled before step 10
  with gcs.Proxy(emulator) as proxy:
    with procs.Run(workdir, RUN, env=dict(proxy.env, **slow), log_dir=tmp_path / "logs") as run:
      run.wait_for(lambda: "checkpoints/5/commit_success.txt" in emulator.files("runs/term"), RUN_TIMEOUT,
                   "the checkpoint of step 5 committed")
      time.sleep(1.0)  # (orbax's last requests for step 5, after its commit marker)
      proxy.silent()
      silent = time.monotonic()
      run.signal(0, signal.SIGTERM)
      step = assert_stopped_with_one_sentence(run, silent, r"\d+")
    assert 6 <= step <= 10, step  # the step the SIGTERM stopped at (or the regular save of step 10)
    assert checkpoints.latest_step(workdir) == 5

    proxy.forward()
    with procs.Run(workdir, RUN, env=dict(proxy.env, **slow), log_dir=tmp_path / "logs") as run:
      run.wait_for(lambda: re.search(r"^step +7/20", run.output(), re.M), RUN_TIMEOUT, "step 7")
      run.signal(0, signal.SIGTERM)
      codes = run.wait(TIMEOUT_S + ENDING_S + 30)
    out = run.output()
    assert codes == [75], run.tails()
    saved = re.search(r"nerfpod: preempted: saved step (\d+) in ", out)
    assert saved and "Traceback" not in out, run.tails()
    assert checkpoints.latest_step(workdir) == int(saved.group(1)) >= 7


def test_a_bucket_that_fails_while_a_run_restores_leaves_its_checkpoint_as_it_is(emulator, monkeypatch):
  """A training run's restore on a bucket that fails (a connection refused under orbax's error) stops on the
  storage sentence; the step is not taken as damaged and set aside, which only a step that does not read back
  whole is. (The clients' own retries of a refused connection take a minute: the failure is raised here.)"""
  from test_checkpoints import _abstract, _mesh, _state
  monkeypatch.setattr(storage, "_stopped", set())
  workdir = f"gs://{emulator.bucket}/runs/restore"
  mesh = _mesh(1)
  with checkpoints.Checkpoints(workdir, every_steps=1, max_to_keep=1, storage_timeout_s=TIMEOUT_S) as ckpt:
    ckpt.save(1, _state(mesh, 1), {"next_step": 1})

  def refused(*args):
    try:
      raise ConnectionRefusedError(111, "Connect call failed ('127.0.0.1', 9)")
    except ConnectionRefusedError as e:
      raise RuntimeError("Failed to read the checkpoint") from e

  ckpt = checkpoints.Checkpoints(workdir, every_steps=1, max_to_keep=1, storage_timeout_s=TIMEOUT_S)
  monkeypatch.setattr(ckpt, "_restore_step", refused)
  with pytest.raises(storage.Stopped, match=rf"^the bucket gs://{gcs.BUCKET} failed while reading the checkpoint "
                                            r"of step 1 \(\[Errno 111\] Connect call failed \('127.0.0.1', 9\)\); it "
                                            r"is left as it is: rerun the same command once storage is back\.$"):
    ckpt.restore(_abstract(_state(mesh, 0)))
  assert storage.stopped(workdir)
  assert "checkpoints/1/commit_success.txt" in emulator.files("runs/restore")
  assert not emulator.files("runs/restore/checkpoints_damaged")


@pytest.mark.slow  # a minute: gcsfs retries a refused connection 6 times, backing off 1 to 32 s (the quick test
# above raises a refusal under orbax's error in its place)
def test_a_bucket_that_refuses_connections_while_a_run_restores_is_the_same_sentence(emulator, monkeypatch):
  """The restore of the test above through a bucket whose endpoint refuses every connection (the proxy in front
  of the emulator, refusing): what orbax, tensorstore and gcsfs really raise is taken for storage, not for a
  damaged step."""
  import gcsfs
  from test_checkpoints import _abstract, _mesh, _state
  monkeypatch.setattr(storage, "_stopped", set())
  workdir = f"gs://{emulator.bucket}/runs/refused-restore"
  mesh = _mesh(1)
  with gcs.Proxy(emulator) as proxy:
    for name, value in proxy.env.items():
      monkeypatch.setenv(name, value)
    gcsfs.GCSFileSystem.clear_instance_cache()  # (one made for the emulator itself keeps its address)
    with checkpoints.Checkpoints(workdir, every_steps=1, max_to_keep=1, storage_timeout_s=TIMEOUT_S) as ckpt:
      ckpt.save(1, _state(mesh, 1), {"next_step": 1})
    ckpt = checkpoints.Checkpoints(workdir, every_steps=1, max_to_keep=1, storage_timeout_s=TIMEOUT_S)
    proxy.refuse()
    with pytest.raises(storage.Stopped, match=rf"^the bucket gs://{gcs.BUCKET} failed while reading the checkpoint "
                                              r"of step 1 \((.+)\); it is left as it is: rerun the same command once "
                                              r"storage is back\.$") as stopped:
      ckpt.restore(_abstract(_state(mesh, 0)))
  cause = re.search(r"step 1 \((.+)\); it is", str(stopped.value)).group(1)  # the client's own words for it
  assert re.match(r"\[Errno \d+\] (Connect call failed \('127\.0\.0\.1', \d+\)|Connection reset by peer)$",
                  cause), cause
  gcsfs.GCSFileSystem.clear_instance_cache()
  assert storage.stopped(workdir)
  assert "checkpoints/1/commit_success.txt" in emulator.files("runs/refused-restore")
  assert not emulator.files("runs/refused-restore/checkpoints_damaged")


def test_each_client_s_bound_is_set_in_its_own_settings_and_a_users_own_is_kept(monkeypatch):
  import fsspec.config
  monkeypatch.setattr(storage, "_set_here", set())
  monkeypatch.setattr(fsspec.config, "conf", {"gcs": {"requests_timeout": 99.0}})  # the user's, for gcs://
  monkeypatch.delenv("TENSORSTORE_CURL_LOW_SPEED_TIME_SECONDS", raising=False)
  monkeypatch.setenv("TENSORSTORE_CURL_LOW_SPEED_LIMIT_BYTES", "10")  # the user's
  monkeypatch.setattr(storage, "GCS_TIMEOUT", storage.GCS_TIMEOUT)
  storage.bound_clients(7.0)
  storage.bound_clients(5.0)  # a second run in the process: its own bound, where the first one's was set
  assert fsspec.config.conf == {"gs": {"requests_timeout": 5.0}, "gcs": {"requests_timeout": 99.0}}
  assert os.environ["TENSORSTORE_CURL_LOW_SPEED_TIME_SECONDS"] == "5"
  assert os.environ["TENSORSTORE_CURL_LOW_SPEED_LIMIT_BYTES"] == "10"
  assert storage.gcs_timeout() == 5.0 and storage.gcs_retry()._timeout == 5.0
