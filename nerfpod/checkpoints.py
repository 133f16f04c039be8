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

Paths go through etils.epath (as orbax's do), so a workdir may be a gs:// bucket.
"""
import json
import signal
import threading

import jax
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from nerfpod import schema
from nerfpod.errors import UserError

# Fields that may differ when resuming a workdir: they change neither shapes nor the trajectory's inputs.
RESUMABLE_CHANGES = ("train.num_steps", "train.log_every", "train.image_every", "checkpoint.", "eval.",
                     "orbit.", "compile.")


def incompatible_fields(saved: dict, current: dict) -> list[str]:
  """Dotted names of config fields that differ between a workdir's config and this run's, bar the allowed.
  The saved config may use earlier names of fields (schema.LEGACY_NAMES)."""
  a, b = schema.migrate_flat(schema.flatten(saved)), schema.flatten(current)
  differing = sorted(k for k in set(a) | set(b) if a.get(k, "<absent>") != b.get(k, "<absent>"))
  return [k for k in differing if not any(k == p or (p.endswith(".") and k.startswith(p))
                                          for p in RESUMABLE_CHANGES)]


def check_compatible(workdir: str, config_json: dict) -> None:
  """Refuses to resume a workdir whose checkpoints came from a config of another shape or data."""
  path = epath.Path(workdir) / "config.json"
  if latest_step(workdir) is None or not path.exists():
    return
  saved = json.loads(path.read_text())
  differing = incompatible_fields(saved, config_json)
  if differing:
    was, now = schema.migrate_flat(schema.flatten(saved)), schema.flatten(config_json)
    shown = ", ".join(f"{k} ({was.get(k, '<absent>')!r} -> {now.get(k, '<absent>')!r})"
                      for k in differing[:6])
    more = f" and {len(differing) - 6} more" if len(differing) > 6 else ""
    raise UserError(f"workdir {workdir} holds checkpoints of a different config: {shown}{more}; use a new "
                    f"--workdir, or the settings of the workdir's config.json (only train.num_steps, the "
                    f"logging cadence, checkpoint.*, eval.*, orbit.* and compile.* may change on resuming).")


def write_json(path, value, sort_keys: bool = False) -> None:
  """Writes `value` as indented JSON to `path` (local or gs://) whole or not at all: into PATH.tmp, then
  renamed; creates the folder."""
  path = epath.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.parent / f"{path.name}.tmp"
  tmp.write_text(json.dumps(value, indent=2, sort_keys=sort_keys))
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
  stop at after a SIGTERM. Use as a context manager, or call close().
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
    self.manager = ocp.CheckpointManager(self._directory, options=options, item_names=("state", "data"))
    self._sigterm = threading.Event()
    self._previous_handler = None
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

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def restore(self, abstract_state, step: int | None = None):
    """(state, data position) of `step` (default: the newest), arrays placed as in `abstract_state`.

    The placement comes from `abstract_state`'s shardings, i.e. this run's mesh, whatever mesh wrote the
    checkpoint: a run can come back on another number of hosts or devices.
    """
    step = self.manager.latest_step() if step is None else step
    # Checked before restoring: orbax would fail half way, with a stack trace and its reads still pending.
    differences = state_differences(self._directory / str(step) / "state", abstract_state)
    if differences:
      raise UserError(f"the checkpoint of step {step} in {self._directory} holds a train state of another "
                      f"shape than this run's ({differences}): it was written by another model or nerfpod "
                      f"version; use a new --workdir (or that version).")
    restored = self.manager.restore(step, args=ocp.args.Composite(
        state=ocp.args.StandardRestore(abstract_state), data=ocp.args.JsonRestore()))
    return restored["state"], restored["data"]

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


def _saved_tree(path):
  """The tree of array metadata (shapes, dtypes) of the pytree item saved at `path`, read without its data."""
  return ocp.PyTreeCheckpointer().metadata(path).item_metadata.tree


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
  step = latest_step(workdir) if step is None else step
  if step is None:
    raise UserError(f"workdir {workdir} holds no complete checkpoint.")
  path = checkpoint_dir(workdir) / str(step)
  restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), _saved_tree(path / "state"))
  state = ocp.PyTreeCheckpointer().restore(path / "state",
                                           args=ocp.args.PyTreeRestore(restore_args=restore_args))
  position = ocp.Checkpointer(ocp.JsonCheckpointHandler()).restore(path / "data")
  return state, position, step
