"""Orbax checkpoints of everything a run needs to resume exactly: train state + data position.

A workdir's checkpoints live in DIR/checkpoints/<step>/ with two items: `state` (the train state's arrays)
and `data` (the pipeline's position, {"next_step": s}, which does not depend on the number of hosts).

Saves are asynchronous: the state is copied off the devices, then written in the background while training
goes on. Every process takes part in every save; orbax writes each step into `<step>.orbax-checkpoint-tmp`
and renames it to `<step>` only once every process has finished (on gs://, which cannot rename, it marks a
finished step with a `commit_success.txt` instead), so a save cut off half way is never taken as the latest.

Preemption: a TPU VM gets SIGTERM before maintenance. With several processes, JAX's distributed runtime
catches it on whichever host gets it and makes all hosts agree on one step (`reached_preemption`: the step
after the furthest one any process had reached); with one process, a SIGTERM handler sets a flag. Either
way `save` then writes that step, whatever the interval, and the loop stops there.

A first Ctrl-C (SIGINT) in training is a preemption too (the current step is saved, the run stops and exits
with checkpoint.preempted_exit_code); a second one stops the process at once, like a kill.

Damage: a finished step that does not read back whole (a file emptied or deleted by a disk or a person, or
non-finite values written by an older version) is set aside, renamed into DIR/checkpoints_damaged/ (never
deleted), and the restore falls back to the newest step before it that reads back whole.

Paths go through etils.epath (as orbax's do), so a workdir may be a gs:// bucket.
"""
import json
import os
import signal
import sys
import threading

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from nerfpod import schema
from nerfpod.errors import UserError

# Fields that may differ when resuming a workdir: they change neither shapes nor the trajectory's inputs.
RESUMABLE_CHANGES = ("train.num_steps", "train.log_every", "train.image_every", "train.max_nonfinite_steps",
                     "checkpoint.", "eval.", "orbit.", "compile.")


def incompatible_fields(saved: dict, current: dict) -> list[str]:
  """Dotted names of config fields that differ between a workdir's config and this run's, bar the allowed.
  The saved config may use earlier names of fields (schema.LEGACY_NAMES)."""
  a, b = schema.migrate_flat(schema.flatten(saved)), schema.flatten(current)
  differing = sorted(k for k in set(a) | set(b) if a.get(k, "<absent>") != b.get(k, "<absent>"))
  return [k for k in differing if not any(k == p or (p.endswith(".") and k.startswith(p))
                                          for p in RESUMABLE_CHANGES)]


def check_workdir(workdir: str, writable: bool) -> None:
  """Refuses, in one sentence each, a --workdir that is a file, or (`writable`: training) one that cannot be
  made or written. gs:// paths are left to their own errors."""
  if "://" in str(workdir):
    return
  path = epath.Path(workdir)
  if path.exists() and not path.is_dir():
    raise UserError(f"--workdir={workdir} is an existing file, not a folder; pass a folder (a new one for a new "
                    f"run).")
  if not writable:
    return
  try:
    path.mkdir(parents=True, exist_ok=True)
    probe = path / f".nerfpod-write-test-{os.getpid()}"
    probe.write_text("")
    probe.unlink()
  except OSError as e:
    raise UserError(f"--workdir={workdir} cannot be written ({e.strerror or e}); pass a folder this user may "
                    f"write, or fix its permissions.") from None


def saved_config(workdir: str) -> dict | None:
  """The workdir's config.json, None where there is none; a malformed one is a UserError."""
  path = epath.Path(workdir) / "config.json"
  if not path.exists():
    return None
  try:
    saved = json.loads(path.read_text())
    if not isinstance(saved, dict):
      raise ValueError("not a JSON object")
  except (ValueError, UnicodeDecodeError) as e:
    raise UserError(f"{path} is not valid JSON ({e}); restore it (it records the config the checkpoints were "
                    f"trained with) or move it away to resume with this run's config.") from None
  return saved


def check_compatible(workdir: str, config_json: dict) -> None:
  """Refuses to resume a workdir whose checkpoints came from a config of another shape or data."""
  saved = saved_config(workdir)
  if latest_step(workdir) is None or saved is None:
    return
  differing = incompatible_fields(saved, config_json)
  if differing:
    was, now = schema.migrate_flat(schema.flatten(saved)), schema.flatten(config_json)
    shown = ", ".join(f"{k} ({was.get(k, '<absent>')!r} -> {now.get(k, '<absent>')!r})"
                      for k in differing[:6])
    more = f" and {len(differing) - 6} more" if len(differing) > 6 else ""
    raise UserError(f"workdir {workdir} holds checkpoints of a different config: {shown}{more}; use a new "
                    f"--workdir, or the settings of the workdir's config.json (only train.num_steps, the "
                    f"logging cadence, train.max_nonfinite_steps, checkpoint.*, eval.*, orbit.* and compile.* may "
                    f"change on resuming).")


def write_json(path, value, sort_keys: bool = False) -> None:
  """Writes `value` as indented JSON to `path` (local or gs://) whole or not at all: into PATH.tmp, then
  renamed; creates the folder."""
  path = epath.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.parent / f"{path.name}.tmp"
  # allow_nan=False: a NaN or infinity is an error here, not a bare NaN that strict JSON parsers refuse.
  tmp.write_text(json.dumps(value, indent=2, sort_keys=sort_keys, allow_nan=False))
  tmp.replace(path)


def write_config(workdir: str, config_json: dict) -> None:
  """Writes workdir/config.json (the resolved config) whole or not at all; process 0 only."""
  if jax.process_index() == 0:
    write_json(epath.Path(workdir) / "config.json", config_json, sort_keys=True)


def write_scene(workdir: str, scene_json: dict) -> None:
  """Writes workdir/scene.json (the scene's name, format, space, ray bounds and the capture -> scene
  similarity, so that renders and exports can be mapped back to a capture's frame); process 0 only."""
  if jax.process_index() == 0:
    write_json(epath.Path(workdir) / "scene.json", scene_json)


def checkpoint_dir(workdir: str) -> epath.Path:
  workdir = str(workdir)
  return epath.Path(workdir if "://" in workdir else epath.Path(workdir).absolute()) / "checkpoints"


def finished_steps(workdir: str) -> list[int]:
  """Steps of the complete checkpoints, oldest first; temporary (cut-off) ones are not among them."""
  directory = checkpoint_dir(workdir)
  if not directory.exists():
    return []
  return sorted(ocp.path.step.checkpoint_steps(directory))


def latest_step(workdir: str) -> int | None:
  """Newest complete checkpoint's step, without starting a manager."""
  steps = finished_steps(workdir)
  return steps[-1] if steps else None


class Checkpoints:
  """One orbax CheckpointManager for a workdir: items 'state' (a pytree) and 'data' (JSON position).

  Also the preemption watch: `reached_preemption(step)` is True at the one step all processes agree to
  stop at after a SIGTERM or a first Ctrl-C. Use as a context manager, or call close().
  """

  def __init__(self, workdir: str, every_steps: int, max_to_keep: int, read_only: bool = False):
    """`read_only` (evaluation, rendering): never writes, deletes or cleans anything in the workdir, which
    a training run may be writing at the same time, and leaves SIGTERM alone."""
    cm = ocp.checkpoint_managers
    self._closed = False
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, enable_async_checkpointing=True, create=not read_only, read_only=read_only,
        cleanup_tmp_directories=not read_only,  # leftovers of a save cut off by a crash
        # Every `every_steps` steps and at a preemption; explicitly so, as orbax's default policy would
        # also save the first step of every run.
        save_decision_policy=cm.AnySavePolicy([cm.FixedIntervalPolicy(every_steps),
                                               cm.PreemptionCheckpointingPolicy()]))
    self._directory = checkpoint_dir(workdir)
    self._read_only = read_only
    self.manager = ocp.CheckpointManager(self._directory, options=options, item_names=("state", "data"))
    self._sigterm = threading.Event()
    self._previous_handler = None
    self._previous_sigint = None
    self._interrupts = 0
    self._agree = jax.process_count() > 1 and not read_only
    if read_only:
      pass
    elif self._agree:
      # Tell the preemption service where this run stands (it resumes after the newest checkpoint): a
      # SIGTERM before the first step then makes the processes agree on the first step, not on step 1.
      self.reached_preemption(self.manager.latest_step() or 0)
    elif threading.current_thread() is threading.main_thread():
      # One process (jax.distributed or not): nobody to agree with, so just note the signal. (JAX's service
      # would also do, but orbax's save-finalising thread reports older steps to it, which with one
      # process can make the agreed step one the loop has already passed.)
      self._previous_handler = signal.signal(signal.SIGTERM, lambda *_: self._sigterm.set())
    if not read_only and threading.current_thread() is threading.main_thread():
      self._previous_sigint = signal.signal(signal.SIGINT, self._on_sigint)

  def _on_sigint(self, *_):
    """A first Ctrl-C: a preemption (the current step is saved, then the run stops); a second: stop now."""
    self._interrupts += 1
    if self._interrupts > 1:
      print("nerfpod: interrupted again: stopping now, without saving", file=sys.stderr, flush=True)
      os._exit(128 + signal.SIGINT)
    print("nerfpod: interrupted: saving the current step, then stopping (Ctrl-C again to stop at once)",
          file=sys.stderr, flush=True)
    if self._agree:
      os.kill(os.getpid(), signal.SIGTERM)  # JAX's preemption service makes every process agree on the step
    else:
      self._sigterm.set()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def restore(self, abstract_state, step: int | None = None):
    """(state, data position) of `step` (default: the newest that reads back whole), arrays placed as in
    `abstract_state`.

    The placement comes from `abstract_state`'s shardings, i.e. this run's mesh, whatever mesh wrote the
    checkpoint: a run can come back on another number of hosts or devices. Without `step`, a newest step
    that does not read back whole (missing or emptied files, non-finite values) is set aside into
    checkpoints_damaged/ (read-only: only skipped) with one line saying so, and the step before it is tried.
    """
    if step is not None:
      return self._restore_step(abstract_state, step)
    damaged = []
    for candidate in sorted(self.manager.all_steps(), reverse=True):
      try:
        return self._restore_step(abstract_state, candidate)
      except UserError:
        raise
      except Exception as e:  # noqa: BLE001 (whatever orbax or tensorstore raise on a damaged step)
        reason = " ".join(str(e).split())[:200] or type(e).__name__
        damaged.append(f"step {candidate}: {reason}")
        if self._read_only:
          where = "left in place (a training run on this workdir sets it aside)"
        else:
          where = f"set aside as {self._set_aside(candidate)}"
        if jax.process_index() == 0:
          print(f"nerfpod: warning: the checkpoint of step {candidate} in {self._directory} does not read back "
                f"whole ({reason}); {where}; falling back to the step before it", file=sys.stderr, flush=True)
    raise UserError(f"no checkpoint in {self._directory} reads back whole ({'; '.join(damaged)}); "
                    + ("" if self._read_only else f"they were set aside in {self._damaged_dir()}; ")
                    + "train again from scratch in a new --workdir (or rerun the training command, which now "
                      "starts from scratch).")

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

  def reached_preemption(self, step: int) -> bool:
    """True at the step where every process stops after a SIGTERM reached any of them.

    Call it at every step, with the same steps on every process (the distributed runtime picks the step
    after the furthest one any process had reached when the signal came).
    """
    if self._agree:
      return self.manager.reached_preemption(step)
    return self._sigterm.is_set()

  def save(self, step: int, state, data_position: dict, force: bool = False) -> bool:
    """Starts an asynchronous save of `state` at `step` if due, forced or preempted; returns whether it did."""
    if self.manager.latest_step() == step:
      return False
    force = force or self.reached_preemption(step)
    if not (force or self.manager.should_save(step)):
      return False
    # The step never lets a non-finite value into the state (it skips such updates); this is the last line
    # of defence, as a saved NaN would rotate the good checkpoints out.
    if not bool(all_finite(state)):
      if jax.process_index() == 0:
        print(f"nerfpod: warning: the train state at step {step} holds non-finite values; not saving it",
              file=sys.stderr, flush=True)
      return False
    return self.manager.save(step, args=ocp.args.Composite(
        state=ocp.args.StandardSave(state), data=ocp.args.JsonSave(data_position)), force=force)

  def wait(self) -> None:
    self.manager.wait_until_finished()

  def close(self) -> None:
    """Waits for the last save to be complete on disk; gives SIGTERM back to its previous handler. Once."""
    if self._closed:
      return
    self._closed = True
    self.manager.wait_until_finished()
    self.manager.close()
    if self._previous_handler is not None:
      signal.signal(signal.SIGTERM, self._previous_handler)
      self._previous_handler = None
    if self._previous_sigint is not None:
      signal.signal(signal.SIGINT, self._previous_sigint)
      self._previous_sigint = None


@jax.jit
def all_finite(tree) -> jax.Array:
  """Whether every floating-point leaf of `tree` is finite (a scalar bool, on the leaves' devices)."""
  checks = [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.inexact)]
  return jnp.all(jnp.stack(checks)) if checks else jnp.asarray(True)


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
    for candidate in reversed(steps):
      try:
        return read_numpy(workdir, candidate)
      except Exception as e:  # noqa: BLE001 (whatever orbax or tensorstore raise on a damaged step)
        reason = " ".join(str(e).split())[:200] or type(e).__name__
        print(f"nerfpod: warning: the checkpoint of step {candidate} in {checkpoint_dir(workdir)} does not read "
              f"back whole ({reason}); reading the step before it", file=sys.stderr, flush=True)
    raise UserError(f"no checkpoint in {checkpoint_dir(workdir)} reads back whole.")
  path = checkpoint_dir(workdir) / str(step)
  restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), _saved_tree(path / "state"))
  state = ocp.PyTreeCheckpointer().restore(path / "state",
                                           args=ocp.args.PyTreeRestore(restore_args=restore_args))
  position = ocp.Checkpointer(ocp.JsonCheckpointHandler()).restore(path / "data")
  return state, position, step
