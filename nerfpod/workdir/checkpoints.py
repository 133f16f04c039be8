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

A bucket that stops answering (or fails) mid-run: for a workdir in a bucket, what a training run waits on here
(the opening of the checkpoints, the previous save when the next one is due, the last one at the end or at a
preemption) is waited on for at most checkpoint.storage_timeout_s (nerfpod.storage.within); past it, or on a
storage client's failure, the run stops with one storage.Stopped sentence naming the bucket, what failed and
the newest committed checkpoint, the save under way left behind uncommitted. The arrays' tensorstore requests
are retried TENSORSTORE_TRIES times at most (_BoundedRequests). A restore that the bucket fails is that
sentence too, never a step set aside as damaged.

When to stop for a preemption is nerfpod.run.preemption's; the workdir's other files are nerfpod.workdir's.
Paths go through etils.epath (as orbax's do), so a workdir may be a gs:// bucket.
"""
import dataclasses
from typing import Any
import errno
import functools
import logging
import os
import re
import sys
import traceback

import jax
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from nerfpod import storage
from nerfpod.errors import UserError
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


class _ReadOnlyIsAsked(logging.Filter):
  """Drops orbax's warnings that a read-only manager is read-only (nerfpod asks for it: evaluation, rendering,
  the viewer and the exports never write in a workdir); every other orbax message passes."""
  QUIET = ("Given directory is read only", "CheckpointManagerOptions.read_only=True, setting")

  def filter(self, record: logging.LogRecord) -> bool:
    return not str(record.msg).startswith(self.QUIET)


# How a full disk reads in the errors and logs of Python, tensorstore (its status carries errno 28, ENOSPC)
# and a quota.
DISK_FULL_TEXTS = ("No space left on device", "os_error_code='28'", "Disk quota exceeded")


def disk_full(error: BaseException | None) -> bool:
  """Whether `error`, or an error it was raised from, says the disk (or the user's quota) is full."""
  seen = set()
  while error is not None and id(error) not in seen:
    seen.add(id(error))
    if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT):
      return True
    if any(text in str(error) for text in DISK_FULL_TEXTS):
      return True
    error = error.__cause__ or error.__context__
  return False


class _DiskFullIsReported(logging.Filter):
  """Drops orbax's error logs (each with its traceback, up to 24 of them) of a save that failed on a full disk:
  the run stops on it with one sentence (nerfpod.run.modes)."""

  def filter(self, record: logging.LogRecord) -> bool:
    if record.levelno < logging.ERROR:
      return True
    return not (disk_full(record.exc_info[1] if record.exc_info else None)
                or any(text in record.getMessage() for text in DISK_FULL_TEXTS))


def remove_cut_off_saves(workdir: str) -> list[str]:
  """Removes the temporary folders of saves that did not finish (process 0, with no save under way: a run
  that stops on a full disk), so that the space they hold is free; returns their names."""
  directory = checkpoint_dir(workdir)
  if jax.process_index() != 0 or not directory.exists():
    return []
  removed = []
  for path in directory.iterdir():
    # orbax's temporary folder of a save under way: STEP.orbax-checkpoint-tmp, or with -TIMESTAMP after it
    if re.search(r"\.orbax-checkpoint-tmp(-\d+)?$", path.name) or path.name == ROTATED:
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
  bounded too (_BoundedRequests)."""
  whole = jax.process_count() == 1 and jax.default_backend() == "cpu"
  if not whole and storage_timeout_s is None:
    return  # orbax's own
  options = {"use_replica_parallel": False} if whole else {}
  handler = (ocp.type_handlers.ArrayHandler(**options) if storage_timeout_s is None else
             _BoundedRequests(storage_timeout_s, **options))
  absl_logger = logging.getLogger("absl")
  level = absl_logger.level
  absl_logger.setLevel(logging.ERROR)  # (orbax warns of any override, wanted or not)
  try:
    ocp.type_handlers.register_type_handler(jax.Array, handler, override=True)
  finally:
    absl_logger.setLevel(level)


# tensorstore's gcs driver retries a request up to 32 times, waiting up to 32 s between tries: nerfpod's
# arrays' requests are tried TENSORSTORE_TRIES times, at most checkpoint.storage_timeout_s apart (each try ends
# after that long without a byte: storage.bound_clients), as gcsfs tries its own.
TENSORSTORE_TRIES = 6


class _BoundedRequests(ocp.type_handlers.ArrayHandler):
  """orbax's ArrayHandler whose arrays' tensorstore requests are retried TENSORSTORE_TRIES times at most
  (tensorstore's `gcs_request_retries` context resource, in a context whose parent is orbax's own, so that
  its other resources stay shared)."""

  def __init__(self, storage_timeout_s: float, **kwargs):
    super().__init__(**kwargs)
    self._retries = {"gcs_request_retries": {"max_retries": TENSORSTORE_TRIES - 1, "initial_delay": "1s",
                                             "max_delay": f"{min(32.0, storage_timeout_s):g}s"}}

  def _bounded(self, infos):
    import tensorstore as ts
    children = {}
    for info in infos:
      parent = info.ts_context
      if parent is not None:
        if id(parent) not in children:
          children[id(parent)] = ts.Context(ts.Context.Spec(self._retries), parent=parent)
        info.ts_context = children[id(parent)]
    return infos

  async def serialize(self, values, infos, args=None):
    return await super().serialize(values, self._bounded(infos), args)

  async def deserialize(self, infos, args=None):
    return await super().deserialize(self._bounded(infos), args)


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
    that fails meanwhile (storage_failure) is one storage.Stopped sentence instead, the step left as it is.
    Readers that must not write go through restore_newest instead.
    """
    if step is not None:
      return self._restore_step(abstract_state, step)
    assert not self._read_only, "a read-only reader restores through restore_newest"
    damaged = []

    def set_aside(candidate: int, error: Exception) -> str:
      reason = damage_reason(error)
      if self._timeout is not None and storage_failure(error):  # the bucket failed, not the step: kept as it is
        storage.mark_stopped(self._workdir)
        raise storage.Stopped(f"the bucket {storage.bucket_of(self._workdir)} failed while reading the "
                              f"checkpoint of step {candidate} ({reason}); it is left as it is: rerun the same "
                              f"command once storage is back.") from None
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
    """Waits for the save under way, if any, to be committed (bounded: _bounded)."""
    if self._saving is not None:
      self._bounded(f"saving the checkpoint of step {self._saving}", self.manager.wait_until_finished)
      self._committed, self._saving = self._saving, None

  def _bounded(self, doing: str, work):
    """work() (a part of `doing`, in words: "saving the checkpoint of step 20"). For a workdir in a bucket,
    waited on for at most storage_timeout_s (storage.within); a bucket that gives no answer in that time, or
    fails (storage_failure: an error of another kind is raised as it is), is one storage.Stopped sentence
    naming it, what failed and the newest committed checkpoint."""
    if self._timeout is None:
      return work()
    bucket = storage.bucket_of(self._workdir)
    try:
      return storage.within(self._workdir, self._timeout, work)
    except storage.NoAnswer:
      what = f"stopped answering while {doing} (no answer in {self._timeout:g} s)"
    except UserError:
      raise
    except Exception as e:  # noqa: BLE001 (whatever orbax, tensorstore or gcsfs raise when storage fails)
      if not storage_failure(e):
        raise
      what = f"failed while {doing} ({damage_reason(e)})"
      storage.mark_stopped(self._workdir)  # (the run stops on it: its other calls there give up at once)
    newest = (f"the newest committed checkpoint is step {self._committed}: rerun the same command once storage "
              f"is back (it resumes from there)" if self._committed is not None else
              "no checkpoint had been committed yet: rerun the same command once storage is back")
    raise storage.Stopped(f"the bucket {bucket} {what}; {newest}.")

  def close(self) -> None:
    """Waits for the last save to be complete on disk (bounded for a bucket: _bounded). Once. Where the
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
    damaged[step] = damage_reason(error)
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
              f"({damage_reason(e)}); {then}", file=sys.stderr, flush=True)
  return None


def none_reads_back_whole(workdir: str, damaged: dict) -> UserError:
  """The sentence for a workdir none of whose checkpoints reads back whole (`damaged`: {step: why})."""
  return UserError(f"no checkpoint in {checkpoint_dir(workdir)} reads back whole ("
                   + "; ".join(f"step {s}: {r}" for s, r in sorted(damaged.items(), reverse=True))
                   + "); they are left in place: train again from scratch in a new --workdir (or rerun the "
                     "training command, which sets them aside and starts from scratch).")


def damage_reason(error: BaseException) -> str:
  """Why a read failed, in one line: the innermost cause's message (orbax wraps tensorstore's error, which
  names the file and what is wrong with it, in one that names neither)."""
  while error.__cause__ is not None:
    error = error.__cause__
  return " ".join(str(error).split())[:300] or type(error).__name__


class _StorageFailureIsReported(logging.Filter):
  """Drops the error logs, each with its traceback, of orbax's save threads and of gcsfs's retries whose error
  is a storage client's failure to reach or hear from its service (a connection refused, reset or timed out,
  an HTTP error, a tensorstore request given up): the error itself reaches the caller, and a run whose bucket
  fails says so in one sentence (Checkpoints._bounded; storage._call for what a scene reads)."""

  def filter(self, record: logging.LogRecord) -> bool:
    return not (record.levelno >= logging.ERROR and record.exc_info and storage_failure(record.exc_info[1]))


# tensorstore's status codes of a request that did not get through (an error raised in its C++ code begins
# with its code).
_UNREACHED_CODES = ("UNAVAILABLE", "DEADLINE_EXCEEDED", "ABORTED", "UNAUTHENTICATED", "PERMISSION_DENIED")


def _storage_error_types() -> tuple:
  """The exception types of the storage clients' failures to reach or hear from their services."""
  kinds = [ConnectionError, TimeoutError]
  for module, names in (("aiohttp", ("ClientError",)), ("requests.exceptions", ("RequestException",)),
                        ("google.api_core.exceptions", ("GoogleAPIError",)),
                        ("google.auth.exceptions", ("TransportError", "RefreshError")),
                        ("gcsfs.retry", ("HttpError",)), ("fsspec.exceptions", ("FSTimeoutError",))):
    found = sys.modules.get(module)  # (a client not imported raised nothing)
    kinds += [getattr(found, name) for name in names if found is not None and hasattr(found, name)]
  return tuple(kinds)


def storage_failure(error: BaseException | None) -> bool:
  """Whether `error`, or an error it was raised from, is a storage client's failure to reach or hear from its
  service (_StorageFailureIsReported)."""
  kinds = _storage_error_types()
  seen = set()
  while error is not None and id(error) not in seen:
    seen.add(id(error))
    if isinstance(error, kinds) or (isinstance(error, ValueError)
                                     and str(error).split(":", 1)[0] in _UNREACHED_CODES):
      return True
    error = error.__cause__ or error.__context__
  return False


class _AbandonedReadTasks(logging.Filter):
  """Drops asyncio's "... exception was never retrieved" for orbax's reads (an abandoned read that failed
  too, reported when its task, or the future gathering several, is collected: a traceback per array), and
  its "Task was destroyed but it is pending" for those still under way at exit. A task's line names the
  coroutine's file; a gathering future's names none, so its exception's traceback is read too; a future
  tensorstore itself failed has no traceback: its status-code message tells."""

  def filter(self, record):
    message = record.getMessage()
    if message.startswith("Task was destroyed but it is pending"):  # one cut off before it failed
      return not _in_orbax(message)
    if "exception was never retrieved" not in message:
      return True
    error = record.exc_info[1] if record.exc_info else None
    return not (_in_orbax(message) or _raised_in_orbax(error) or _tensorstore_status(error))


# absl status codes, which begin the message of an error raised in tensorstore's C++ code.
_STATUS_CODES = ("CANCELLED", "UNKNOWN", "INVALID_ARGUMENT", "DEADLINE_EXCEEDED", "NOT_FOUND", "ALREADY_EXISTS",
                 "PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION", "ABORTED", "OUT_OF_RANGE",
                 "UNIMPLEMENTED", "INTERNAL", "UNAVAILABLE", "DATA_LOSS", "UNAUTHENTICATED")


def _tensorstore_status(error) -> bool:
  """Whether `error` is one tensorstore set on a future from its C++ code (no Python frame, a status-code
  message): a read orbax started and abandoned, where nothing else in a process awaits tensorstore futures
  without their results."""
  return (error is not None and error.__traceback__ is None
          and str(error).split(":", 1)[0] in _STATUS_CODES)


def _in_orbax(text: str) -> bool:
  """Whether `text` (a file name, or a report naming one) names a file of orbax's."""
  return f"{os.sep}orbax{os.sep}" in text


def _raised_in_orbax(error) -> bool:
  """Whether `error`, or an error it was raised from, passed through orbax's code."""
  seen = set()
  while error is not None and id(error) not in seen:
    seen.add(id(error))
    if any(_in_orbax(frame.filename) for frame in traceback.extract_tb(error.__traceback__)):
      return True
    error = error.__cause__ or error.__context__
  return False


def quiet_library_reports() -> None:
  """Keeps what orbax, asyncio and tensorstore report about nerfpod's own doing out of a process's output: a
  read-only manager's warnings that it is read-only (asked for: _ReadOnlyIsAsked), the error logs of a save that
  failed on a full disk (the run says it in one sentence: _DiskFullIsReported), those of orbax's save threads and
  gcsfs's retries on storage that failed (_StorageFailureIsReported: the run says it in one sentence) and the
  reads orbax abandons when a restore fails (quiet_abandoned_reads). Each filter drops only those; every other
  report passes. The entry points call it (nerfpod.main, the exports, the viewer), once per process; calling it
  again changes nothing. The texts matched are pinned to the library versions that emit them by
  tests/test_checkpoints.py."""
  absl_log = logging.getLogger("absl")
  for quiet in (_ReadOnlyIsAsked, _DiskFullIsReported, _StorageFailureIsReported):
    if not any(isinstance(f, quiet) for f in absl_log.filters):
      absl_log.addFilter(quiet())
  for name in ("gcsfs", "fsspec"):  # (their loggers' records reach the root's handler, absl's, without absl's)
    client_log = logging.getLogger(name)
    if not any(isinstance(f, _StorageFailureIsReported) for f in client_log.filters):
      client_log.addFilter(_StorageFailureIsReported())
  sys.unraisablehook = quiet_abandoned_reads(sys.unraisablehook)


def quiet_abandoned_reads(hook):
  """`hook` (sys.unraisablehook), less the reports of the reads orbax abandons when a restore fails (a
  damaged step): orbax stops at the first failed read and closes its event loop with the other reads still
  under way, so each of those later reports "Event loop is closed" (from tensorstore's thread) or, at exit,
  an unfinished coroutine: up to hundreds of lines after the one warning line that says what happened.
  Also quiets asyncio's log of those reads that failed in turn (a logging filter, installed once). A hook
  that is already one of these is returned as it is."""
  if getattr(hook, "quiets_abandoned_reads", False):
    return hook
  asyncio_log = logging.getLogger("asyncio")
  if not any(isinstance(f, _AbandonedReadTasks) for f in asyncio_log.filters):
    asyncio_log.addFilter(_AbandonedReadTasks())

  def quiet(unraisable):
    error, trace = unraisable.exc_value, unraisable.exc_traceback
    closed_loop = (isinstance(error, RuntimeError) and str(error) == "Event loop is closed" and trace is not None
                   and trace.tb_frame.f_code.co_name == "call_soon_threadsafe")  # called from no Python frame
    code = getattr(unraisable.object, "cr_code", None)
    abandoned_read = code is not None and _in_orbax(code.co_filename)
    if not (closed_loop or abandoned_read):
      hook(unraisable)
  quiet.quiets_abandoned_reads = True
  return quiet


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
