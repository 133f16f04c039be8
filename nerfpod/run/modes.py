"""The run: what each `--mode` does, in order. Train, then evaluate, then render the orbit; or one alone.

    train_and_evaluate(config, workdir)   --mode=train (the default)
    evaluate_workdir(config, workdir)     --mode=eval: the workdir's newest checkpoint -> eval/metrics.json
    render_workdir(config, workdir)       --mode=render: its orbit -> renders/orbit.zarr and the videos

Each checks the whole config first (nerfpod.schema; a mistake is a UserError before any work) and builds
the shared pieces once (nerfpod.run.components). Calls flow one way: this module calls train, evaluate and
orbit, which call the components below them, and none of them calls back up here.

What a run shows goes through one monitor.Writer (process 0): TensorBoard, and W&B where
config.monitor.wandb asks. Evaluation and the orbit write to it themselves; this module adds what they
return: the metrics of every view (a table) and the orbit's videos.
"""
import contextlib
import glob
import json
import os

import jax

from nerfpod import monitor, schema, storage
from nerfpod.run import components, evaluate, orbit, train, trained
from nerfpod.workdir import checkpoints, failures, files as workdir_files, lock as workdir_lock
from nerfpod.errors import UserError


def _build(config, workdir: str) -> components.Components:
  """Checks a resumed workdir's config against this run's, then builds the pieces."""
  newest = checkpoints.latest_step(workdir)
  workdir_files.check_compatible(workdir, json.loads(config.to_json_best_effort()), has_checkpoint=newest is not None)
  return components.build(config)


def train_and_evaluate(config, workdir: str) -> dict | None:
  """Trains (resuming from workdir's newest checkpoint), evaluates the held-out views, renders the orbit.

  Returns the metrics written to workdir/eval/metrics.json, or None when a SIGTERM (preemption) or a first
  Ctrl-C stopped training: the state was then saved at a step all processes agreed on, and nothing else is
  done (the entry point exits with checkpoint.preempted_exit_code).
  """
  schema.validate(config, jax.device_count())
  storage.bound_clients(config.checkpoint.storage_timeout_s)  # before the first request to a bucket
  new_workdir = not storage.is_url(workdir) and not os.path.exists(workdir)
  workdir_files.check_workdir(workdir, writable=True)
  lock = _hold(workdir)
  try:
    comps = _build(config, workdir)
    components.check_regions_seen(comps)  # a region no training camera sees, before anything is written
  except UserError:
    lock.release()
    if new_workdir and jax.process_index() == 0:
      _remove_if_empty(workdir)  # a data or config mistake leaves no empty folder behind
    raise
  try:
    with _disk_full_is_one_sentence(workdir, training=True):
      watch = monitor.Monitor(workdir, config.train.num_steps, config.train.batch_size, config)
      exit_code = 1  # for the W&B run: an exception, unless training stops early (preempted) or ends
      try:
        outcome = train.train(comps, workdir, watch)
        if outcome is None:
          exit_code = config.checkpoint.preempted_exit_code
          return None
        state, step = outcome
        result = _evaluate(comps, state.params, workdir, step, writer=watch.writer)
        if config.orbit.render_after_training:
          _render_orbit(comps, state.params, workdir, step, writer=watch.writer)
        exit_code = 0
      finally:
        watch.close(exit_code)
  finally:
    lock.release()
  return result


@contextlib.contextmanager
def _disk_full_is_one_sentence(workdir: str, training: bool):
  """Turns a full disk (whichever write hit it: a checkpoint, config.json, events, metrics, the archive) into
  one sentence naming the workdir and its newest complete checkpoint, after removing what the failed writes
  left half done (cut-off saves, empty event files), so that a rerun after freeing space resumes cleanly."""
  try:
    yield
  except Exception as e:  # noqa: BLE001 (orbax, tensorstore, tensorboardX and Python raise it differently)
    if not failures.disk_full(e):
      raise
    if jax.process_index() == 0 and not storage.is_url(workdir):
      try:
        checkpoints.remove_cut_off_saves(workdir)
        for events in glob.glob(os.path.join(glob.escape(str(workdir)), "events.out.tfevents.*")):
          if os.path.getsize(events) == 0:  # its header could not even be written
            os.remove(events)
      except OSError:
        pass
    newest = checkpoints.latest_step(workdir)
    safe = (f"the newest complete checkpoint, step {newest}, is safe" if newest is not None else
            "no checkpoint had been saved yet")
    then = ("rerun the same command, which resumes from it" if training and newest is not None else
            "run the same command again")
    raise UserError(f"the disk holding workdir {workdir} is full (No space left on device); {safe}; free "
                    f"space there (or pass a --workdir on a larger disk) and {then}.") from None


def _hold(workdir: str) -> workdir_lock.WorkdirLock:
  """The workdir's lock, taken by process 0 for the whole run; every process raises the refusal."""
  lock = workdir_lock.WorkdirLock(workdir)
  refusal = None
  if jax.process_index() == 0:
    try:
      lock.acquire()
    except UserError as e:
      refusal = e
  if jax.process_count() > 1:
    import numpy as np
    from jax.experimental import multihost_utils
    taken = bool(multihost_utils.broadcast_one_to_all(np.int32(refusal is None)))
    if not taken and refusal is None:
      refusal = UserError(f"workdir {workdir} is in use by another training run (process 0's message names "
                          f"it); wait for that run to end or stop it, or pass another --workdir.")
  if refusal is not None:
    raise refusal
  return lock


def _remove_if_empty(workdir: str) -> None:
  try:
    os.rmdir(workdir)
  except OSError:  # not empty (or already gone): leave it
    pass


def _evaluate(comps, params, workdir: str, step: int, writer=None) -> dict:
  """evaluate.evaluate, then (process 0) every view's metrics as one table, beside the means it logged."""
  result = evaluate.evaluate(comps, params, workdir, step, writer=writer)
  if writer is not None and result["views"]:
    columns = list(dict.fromkeys(key for view in result["views"] for key in view))
    writer.add_table(f"eval/{result['split']}/views", columns,
                     [[view.get(key) for key in columns] for view in result["views"]], step)
    writer.flush()
  broken = [view for view in result["views"] if view["psnr"] is None]
  if broken:  # a diverged model renders NaN: not a result to exit 0 with (nor to render an orbit of)
    raise UserError(f"the evaluation of step {step} is not finite: {len(broken)} of {len(result['views'])} held-out "
                    f"views rendered non-finite values ({broken[0].get('reason', 'psnr not finite')}), so the model "
                    f"diverged; {workdir}/eval/metrics.json holds nulls for them; train again in a new --workdir "
                    f"with a lower train.lr_init or a train.grad_clip > 0.")
  return result


def _render_orbit(comps, params, workdir: str, step: int, writer=None) -> dict:
  """orbit.render_orbit, then (process 0) its videos, one per channel (orbit_rgb.mp4 -> orbit/rgb)."""
  result = orbit.render_orbit(comps, params, workdir, step, writer=writer)
  if writer is not None:
    for path in result["files"]:
      name = os.path.basename(str(path))
      if name.endswith(".mp4"):
        writer.add_video(f"orbit/{name.removesuffix('.mp4').removeprefix('orbit_')}", str(path), step)
    writer.flush()
  return result


def _from_newest_checkpoint(config, workdir: str, work):
  """work(components, params, workdir, step, writer=...) on workdir's newest checkpoint that reads back whole
  (nerfpod.run.trained, read-only); the writer goes on with the run's TensorBoard events and its W&B run."""
  storage.bound_clients(config.checkpoint.storage_timeout_s)  # before the first request to a bucket
  restored = trained.restore(workdir, config)
  with _disk_full_is_one_sentence(workdir, training=False):
    writer = monitor.summary_writer(workdir, config)
    exit_code = 1
    try:
      result = work(restored.comps, restored.params, workdir, restored.step, writer=writer)
      exit_code = 0
      return result
    finally:
      if writer is not None:
        writer.close(exit_code)


def evaluate_workdir(config, workdir: str) -> dict:
  """--mode=eval: evaluates workdir's newest checkpoint (no training) and writes eval/metrics.json."""
  return _from_newest_checkpoint(config, workdir, _evaluate)


def render_workdir(config, workdir: str) -> dict:
  """--mode=render: the orbit of workdir's newest checkpoint, into the archive and videos."""
  return _from_newest_checkpoint(config, workdir, _render_orbit)
