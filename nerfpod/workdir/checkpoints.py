"""Orbax checkpoints of everything a run needs to resume exactly: train state + data position.

A workdir's checkpoints live in DIR/checkpoints/<step>/ with two items: `state` (the train state's arrays)
and `data` (the pipeline's position, {"next_step": s}, which does not depend on the number of hosts).

Saves are asynchronous: the state is copied off the devices, then written in the background while training
goes on. Every process takes part in every save; orbax writes each step into `<step>.orbax-checkpoint-tmp`
and renames it to `<step>` only once every process has finished (on gs://, which cannot rename, it marks a
finished step with a `commit_success.txt` instead), so a save cut off half way is never taken as the latest.
A state holding a non-finite value is never saved.

Rotation: a step rotated out (beyond checkpoint.max_to_keep) is first renamed into DIR/checkpoints/.rotated/
(one atomic rename), and only then deleted, by process 0, before the next save and when the run ends; so a
process killed while deleting leaves its remains there, never a half-deleted step folder beside the good ones
(which orbax would list as a step without its metadata). On gs://, where orbax deletes objects directly, a cut-off
deletion leaves objects of a step without its metadata, which is never the newest step.

Damage: a finished step that does not read back whole (a file emptied or deleted by a disk or a person, or
non-finite values written by an older version) is set aside, renamed into DIR/checkpoints_damaged/ (never
deleted), and the restore falls back to the newest step before it that reads back whole.

A bucket that stops answering (or fails) mid-run: what a training run waits on in it is bounded
(nerfpod.workdir.watchdog), and a restore that the bucket fails is its one storage.Stopped sentence, never a
step set aside as damaged. What orbax reports of nerfpod's own doing is kept quiet by its settings here and by
nerfpod.workdir.quiet.

When to stop for a preemption is nerfpod.run.preemption's; the workdir's other files are nerfpod.workdir's.
Paths go through etils.epath (as orbax's do), so a workdir may be a gs:// bucket.
"""
import contextlib
import dataclasses
from typing import Any
import functools
import logging
import sys

import jax
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.workdir import failures, library_texts, watchdog
from nerfpod.workdir.finite import all_finite

def checkpoint_dir(workdir: str) -> epath.Path:
  workdir = str(workdir)
  return epath.Path(workdir if storage.is_url(workdir) else epath.Path(workdir).absolute()) / "checkpoints"


ROTATED = ".rotated"  # where rotated-out steps wait to be deleted (a folder of the checkpoints' folder)


def finished_steps(workdir: str) -> list[int]:
  """Steps of the complete checkpoints, oldest first; temporary (cut-off) ones are not among them. A workdir
  that cannot be listed (a bucket without network or credentials) is one sentence."""
  directory = checkpoint_dir(workdir)
  storage.check_reachable(workdir)  # no network: one sentence now, not after a bucket client's retries
  storage.forget_listings()  # a bucket's steps as they are now (another process may have saved one since)
  try:
    if not directory.exists():
      return []
    return sorted(ocp.path.step.checkpoint_steps(directory))
  except Exception as e:  # noqa: BLE001 (whatever a file system or bucket client raises)
    raise UserError(f"could not list the checkpoints of {workdir} ({' '.join(str(e).split())[:300]}); check the "
                    f"--workdir path and, for gs://, your network and credentials.") from None


def latest_step(workdir: str) -> int | None:
  """Newest complete checkpoint's step, without starting a manager."""
  steps = finished_steps(workdir)
  return steps[-1] if steps else None


def remove_cut_off_saves(workdir: str) -> list[str]:
  """Removes the temporary folders of saves that did not finish (process 0, with no save under way: a run
  that stops on a full disk), so that the space they hold is free; returns their names."""
  directory = checkpoint_dir(workdir)
  if jax.process_index() != 0 or not directory.exists():
    return []
  removed = []
  for path in directory.iterdir():
    if library_texts.is_cut_off_save(path.name) or path.name == ROTATED:
      path.rmtree()
      removed.append(path.name)
  return removed


@functools.cache
def _register_array_handler(storage_timeout_s: float | None = None) -> None:
  """orbax's handler for jax.Array, as nerfpod saves them.

  With one process on a CPU, orbax saves each replicated array from one replica, whole: its default
  (replica-parallel) slices every array into one piece per replica, each an eager dispatch (and, the first
  time in a process, a compilation per shape), to copy within one host's memory (docs/results.md has the
  cost). Several processes, or accelerators (whose replicas copy to the host in parallel), keep orbax's
  default. Either way the checkpoint holds the same arrays, and reads back the same. With
  `storage_timeout_s` (a training run whose workdir is in a bucket), the arrays' tensorstore requests are
  bounded too (watchdog.BoundedRequests)."""
  whole = jax.process_count() == 1 and jax.default_backend() == "cpu"
  if not whole and storage_timeout_s is None:
    return  # orbax's own
  options = {"use_replica_parallel": False} if whole else {}
  handler = (ocp.type_handlers.ArrayHandler(**options) if storage_timeout_s is None else
             watchdog.BoundedRequests(storage_timeout_s, **options))
  with _orbax_errors_only():  # (orbax warns of any override, wanted or not)
    ocp.type_handlers.register_type_handler(jax.Array, handler, override=True)


@contextlib.contextmanager
def _orbax_errors_only():
  """Within it, orbax's logger (absl's) passes errors only: for what orbax warns of when nerfpod asks for it on
  purpose (an override of its array handler, a read-only manager: nerfpod's readers never write in a
  workdir)."""
  absl_logger = logging.getLogger("absl")
  level = absl_logger.level
  absl_logger.setLevel(logging.ERROR)
  try:
    yield
  finally:
    absl_logger.setLevel(level)


@dataclasses.dataclass
class _Pinned:
  """Orbax's preservation policy for the steps in `steps` (a set the owner changes): kept past max_to_keep."""
  steps: set

  def should_preserve(self, checkpoints, *, context):
    del context
    return [info.step in self.steps for info in checkpoints]


class Checkpoints:
  """One orbax CheckpointManager for a workdir: items 'state' (a pytree) and 'data' (JSON position). Use as a
  context manager, or call close()."""

  def __init__(self, workdir: str, every_steps: int, max_to_keep: int, read_only: bool = False,
               storage_timeout_s: float | None = None):
    """`read_only` (evaluation, rendering, the viewer): never writes, deletes or cleans anything in the
    workdir, which a training run may be writing at the same time. `storage_timeout_s` (a training run's
    checkpoint.storage_timeout_s): for a workdir in a bucket, how long the run waits on a save (or on opening
    the manager) before it stops with one sentence (storage.Stopped); None: as long as it takes."""
    cm = ocp.checkpoint_managers
    self._closed = False
    self._workdir = str(workdir)
    self._timeout = storage_timeout_s if storage.is_url(workdir) else None
    self._saving = None  # the step of the save under way, not known to be committed yet
    self._pinned = set()
    # The newest max_to_keep steps, and any step pinned (the last one before a run of skipped steps).
    keep = None if read_only else cm.AnyPreservationPolicy([cm.LatestN(max_to_keep), _Pinned(self._pinned)])
    options = ocp.CheckpointManagerOptions(
        save_interval_steps=0 if read_only else 1,  # (orbax's default, 1, is overridden, with a warning)
        preservation_policy=keep, enable_async_checkpointing=True, create=not read_only, read_only=read_only,
        cleanup_tmp_directories=not read_only,  # leftovers of a save cut off by a crash
        todelete_subdir=None if read_only else ROTATED,  # rename first, delete after (the module's docstring)
        # Every `every_steps` steps and at a preemption; explicitly so, as orbax's default policy would
        # also save the first step of every run.
        save_decision_policy=None if read_only else cm.AnySavePolicy([cm.FixedIntervalPolicy(every_steps),
                                                                      cm.PreemptionCheckpointingPolicy()]))
    self._directory = checkpoint_dir(workdir)
    self._read_only = read_only
    self._every_steps = every_steps
    _register_array_handler(self._timeout)
    def open_manager():
      # (a read-only manager's warning that it is read-only: asked for)
      with _orbax_errors_only() if read_only else contextlib.nullcontext():
        manager = ocp.CheckpointManager(self._directory, options=options, item_names=("state", "data"))
      if not read_only:
        self._delete_rotated()
      return manager
    self._committed = None  # (what a stopped storage's sentence names; known once the manager lists the steps)
    self.manager = self._bounded("opening the checkpoints", open_manager)
    self._committed = self.manager.latest_step()  # the newest committed step

  def _delete_rotated(self) -> None:
    """Deletes the steps rotated out into .rotated/ (process 0): what orbax renamed there is whole or gone."""
    rotated = self._directory / ROTATED
    if jax.process_index() != 0 or not rotated.exists():
      return
    for path in rotated.iterdir():
      path.rmtree() if path.is_dir() else path.unlink()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def newest_before(self, step: int) -> int | None:
    """The newest step saved (or being saved) before `step`, None where there is none."""
    earlier = [s for s in self.manager.all_steps() if s < step]
    return max(earlier) if earlier else None

  def pin(self, step: int | None) -> None:
    """Keeps `step` however many newer steps are saved, until unpin(); None: nothing to keep."""
    if step is not None:
      self._pinned.add(step)

  def unpin(self) -> None:
    self._pinned.clear()

  def restore(self, abstract_state, step: int | None = None):
    """(state, data position) of `step` (default: the newest that reads back whole), arrays placed as in
    `abstract_state`.

    The placement comes from `abstract_state`'s shardings, i.e. this run's mesh, whatever mesh wrote the
    checkpoint: a run can come back on another number of hosts or devices. Without `step` (a training run
    resuming), a newest step that does not read back whole (missing or emptied files, non-finite values) is
    set aside into checkpoints_damaged/ with one line saying so, and the step before it is tried; a bucket
    that fails meanwhile (failures.storage_failure) is one storage.Stopped sentence instead, the step left as it is.
    Readers that must not write go through restore_newest instead.
    """
    if step is not None:
      return self._restore_step(abstract_state, step)
    assert not self._read_only, "a read-only reader restores through restore_newest"
    damaged = []

    def set_aside(candidate: int, error: Exception) -> str:
      reason = failures.reason(error)
      if self._timeout is not None and failures.storage_failure(error):  # the bucket failed, not the step
        raise watchdog.failed_reading(self._workdir, candidate, reason) from None
      damaged.append(f"step {candidate}: {reason}")
      return f"set aside as {self._set_aside(candidate)}; falling back to the step before it"
    found = newest_whole(self._directory, self.manager.all_steps(),
                         lambda candidate: self._restore_step(abstract_state, candidate), set_aside)
    if found is not None:
      return found[1]
    raise UserError(f"no checkpoint in {self._directory} reads back whole ({'; '.join(damaged)}); they were set "
                    f"aside in {self._damaged_dir()}; train again from scratch in a new --workdir (or rerun the "
                    f"training command, which now starts from scratch).")

  def _damaged_dir(self) -> epath.Path:
    return self._directory.parent / "checkpoints_damaged"

  def _set_aside(self, step: int) -> epath.Path:
    """Renames a damaged step's folder into checkpoints_damaged/ (process 0, then every process waits for it
    to be gone) and makes the manager forget it; returns where it went."""
    target = self._damaged_dir() / str(step)
    suffix = 1
    while target.exists():
      suffix += 1
      target = self._damaged_dir() / f"{step}-{suffix}"
    if jax.process_index() == 0:
      target.parent.mkdir(parents=True, exist_ok=True)
      (self._directory / str(step)).rename(target)
    if jax.process_count() > 1:
      from jax.experimental import multihost_utils
      multihost_utils.sync_global_devices(f"nerfpod_set_aside_{step}")
    self.manager.reload()
    return target

  def _restore_step(self, abstract_state, step: int):
    """(state, position) of one step, or an exception where it does not read back whole."""
    # Checked before restoring: orbax would fail half way, with a stack trace and its reads still pending.
    differences = state_differences(self._directory / str(step) / "state", abstract_state)
    if differences:
      raise UserError(f"the checkpoint of step {step} in {self._directory} holds a train state of another "
                      f"shape than this run's ({differences}): it was written by another model or nerfpod "
                      f"version; use a new --workdir (or that version).")
    restored = self.manager.restore(step, args=ocp.args.Composite(
        state=ocp.args.StandardRestore(abstract_state), data=ocp.args.JsonRestore()))
    if not bool(all_finite(restored["state"])):
      raise ValueError("it holds non-finite values")
    position = restored["data"]
    if not isinstance(position, dict) or not isinstance(position.get("next_step"), int):
      raise ValueError(f"its data position {position!r} is not {{'next_step': N}}")
    return restored["state"], position

  def save(self, step: int, state, data_position: dict, force: bool = False) -> bool:
    """Starts an asynchronous save of `state` at `step` if due or forced (a preemption's step); returns
    whether it did."""
    if not force and step % self._every_steps:  # (the policy's interval, without orbax's per-step work)
      return False
    if self.manager.latest_step() == step:
      return False
    if not (force or self.manager.should_save(step)):
      return False
    # The step never lets a non-finite value into the state (it skips such updates); this is the last line
    # of defence, as a saved NaN would rotate the good checkpoints out.
    if not bool(all_finite(state)):
      if jax.process_index() == 0:
        print(f"nerfpod: warning: the train state at step {step} holds non-finite values; not saving it",
              file=sys.stderr, flush=True)
      return False
    self._finish_save()  # (orbax's save would wait for it too, unbounded)

    def start():
      self._delete_rotated()  # what the previous save rotated out
      return self.manager.save(step, args=ocp.args.Composite(
          state=ocp.args.StandardSave(state), data=ocp.args.JsonSave(data_position)), force=force)
    started = self._bounded(f"saving the checkpoint of step {step}", start)
    if started:
      self._saving = step
    return started

  def _finish_save(self) -> None:
    """Waits for the save under way, if any, to be committed (bounded: watchdog.bounded)."""
    if self._saving is not None:
      self._bounded(f"saving the checkpoint of step {self._saving}", self.manager.wait_until_finished)
      self._committed, self._saving = self._saving, None

  def _bounded(self, doing: str, work):
    """work(), bounded for a workdir in a bucket (watchdog.bounded: one storage.Stopped sentence naming the
    newest committed checkpoint)."""
    return watchdog.bounded(self._workdir, self._timeout, doing, work, self._committed)

  def close(self) -> None:
    """Waits for the last save to be complete on disk (bounded for a bucket: watchdog.bounded). Once. Where the
    bucket stopped answering, waits for nothing (what was under way is left behind, never committed)."""
    if self._closed:
      return
    self._closed = True
    if storage.stopped(self._workdir):
      return
    self._finish_save()

    def finish():
      self.manager.close()
      if not self._read_only:
        self._delete_rotated()
    self._bounded("closing the checkpoints", finish)


def restore_newest(workdir: str, abstract_state, above: int = -1,
                   damaged: dict | None = None) -> tuple[int, Any] | None:
  """(step, train state) of the newest finished step after `above` that reads back whole, restored read-only
  onto `abstract_state`'s placement; None where none does: the one way evaluation, rendering, the viewer and
  the exports read a checkpoint. Nothing in the workdir is written, deleted or cleaned, so a training run may
  go on beside. Newest first: a step that does not read back whole is said in one warning line (process 0),
  added to `damaged` ({step: why}; the steps already there are not read again) and left in place (a training
  run sets it aside); a step gone meanwhile (rotated out by a training run's max_to_keep) is passed over in
  silence. A checkpoint of another model is one sentence (UserError)."""
  damaged = {} if damaged is None else damaged

  def leave_in_place(step: int, error: Exception) -> str | None:
    if step not in finished_steps(workdir):
      return None
    damaged[step] = failures.reason(error)
    return "left in place (a training run on this workdir sets it aside); falling back to the step before it"
  with Checkpoints(workdir, every_steps=1, max_to_keep=1, read_only=True) as ckpt:  # (a reader saves nothing)
    steps = [s for s in finished_steps(workdir) if s > above and s not in damaged]
    found = newest_whole(checkpoint_dir(workdir), steps, lambda step: ckpt.restore(abstract_state, step)[0],
                         leave_in_place)
  return found


def newest_whole(directory, steps, read, damaged_step) -> tuple[int, Any] | None:
  """(step, read(step)) of the newest of `steps` that reads back whole, None where none does: the one loop
  through which every reader of a workdir's checkpoints (Checkpoints.restore, restore_newest, read_numpy)
  falls back from a damaged step to the one before it. A UserError (a checkpoint of another model) ends it as
  it is; any other exception from read(step) is the step's damage: damaged_step(step, error) deals with the
  step (or raises) and returns what became of it, said after the reason in one warning line (process 0), or
  None to pass over it in silence (a step gone meanwhile). `directory`: the checkpoints' folder, for the
  warning."""
  for step in sorted(steps, reverse=True):
    try:
      return step, read(step)
    except UserError:
      raise
    except Exception as e:  # noqa: BLE001 (whatever orbax or tensorstore raise on a damaged step)
      then = damaged_step(step, e)
      if then is not None and jax.process_index() == 0:
        print(f"nerfpod: warning: the checkpoint of step {step} in {directory} does not read back whole "
              f"({failures.reason(e)}); {then}", file=sys.stderr, flush=True)
  return None


def none_reads_back_whole(workdir: str, damaged: dict) -> UserError:
  """The sentence for a workdir none of whose checkpoints reads back whole (`damaged`: {step: why})."""
  return UserError(f"no checkpoint in {checkpoint_dir(workdir)} reads back whole ("
                   + "; ".join(f"step {s}: {r}" for s, r in sorted(damaged.items(), reverse=True))
                   + "); they are left in place: train again from scratch in a new --workdir (or rerun the "
                     "training command, which sets them aside and starts from scratch).")


def _saved_tree(path):
  """The tree of array metadata (shapes, dtypes) of the pytree item saved at `path`, read without its data."""
  # The handler's own reader: the checkpointer's would also look for step metadata in the item's folder,
  # where there is none, and log a warning on every resume.
  return ocp.PyTreeCheckpointHandler().metadata(epath.Path(path)).tree


def _leaf_shapes(tree) -> dict[str, tuple]:
  """{"opt_state/0/mu/w": shape, ...}: a tree's leaves by key path, the same for a train state and for the
  nested dicts orbax's metadata describes it with."""
  def name(key):
    return str(getattr(key, "key", getattr(key, "name", getattr(key, "idx", key))))
  return {"/".join(name(k) for k in path): tuple(getattr(leaf, "shape", ()))
          for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def state_differences(path, abstract_state, limit: int = 3) -> str:
  """The first differences between the train state saved at `path` and `abstract_state`, in words; empty
  where their leaves and shapes agree (or the saved metadata cannot be read)."""
  try:
    saved = _leaf_shapes(_saved_tree(path))
  except Exception:  # noqa: BLE001 (no readable metadata: nothing to compare)
    return ""
  now = _leaf_shapes(abstract_state)
  differences = [f"{k}: {saved[k]} saved, {now[k]} now" if k in saved and k in now else
                 f"{k}: {'saved only' if k in saved else 'new'}"
                 for k in sorted(set(saved) | set(now), key=lambda k: (not k.startswith("params"), k))
                 if saved.get(k) != now.get(k)]
  more = f" and {len(differences) - limit} more" if len(differences) > limit else ""
  return "; ".join(differences[:limit]) + more


def read_numpy(workdir: str, step: int | None = None) -> tuple[dict, dict, int]:
  """(state as nested dicts of NumPy arrays, data position, step) of a workdir's checkpoint, on any host and
  without a mesh: for tools and tests that inspect parameters. Default step: the newest."""
  if step is None:  # the newest that reads back whole, as a read-only restore does
    steps = finished_steps(workdir)
    if not steps:
      raise UserError(f"workdir {workdir} holds no complete checkpoint.")
    found = newest_whole(checkpoint_dir(workdir), steps, lambda candidate: read_numpy(workdir, candidate),
                         lambda candidate, error: "reading the step before it")
    if found is None:
      raise UserError(f"no checkpoint in {checkpoint_dir(workdir)} reads back whole.")
    return found[1]
  path = checkpoint_dir(workdir) / str(step)
  restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), _saved_tree(path / "state"))
  state = ocp.PyTreeCheckpointer().restore(path / "state",
                                           args=ocp.args.PyTreeRestore(restore_args=restore_args))
  position = ocp.Checkpointer(ocp.JsonCheckpointHandler()).restore(path / "data")
  return state, position, step
