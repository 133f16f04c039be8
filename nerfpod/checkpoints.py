"""Orbax checkpoints of everything a run needs to resume exactly: train state + data position.

Saves are asynchronous: the state is copied off the devices, then written in the background while training
goes on. Orbax writes each step into a temporary folder and renames it only once every process has finished,
so a save cut off half way is never taken as the latest checkpoint.
"""
import json
import os

import jax
import orbax.checkpoint as ocp

from nerfpod.errors import UserError

# Fields that may differ when resuming a workdir: they change neither shapes nor the trajectory's inputs.
RESUMABLE_CHANGES = ("train.num_steps", "train.log_every", "train.image_every", "checkpoint.", "eval.",
                     "orbit.")


def _flatten(tree, prefix=""):
  out = {}
  for key, value in tree.items():
    if isinstance(value, dict):
      out.update(_flatten(value, f"{prefix}{key}."))
    else:
      out[f"{prefix}{key}"] = value
  return out


def incompatible_fields(saved: dict, current: dict) -> list[str]:
  """Dotted names of config fields that differ between a workdir's config and this run's, bar the allowed."""
  a, b = _flatten(saved), _flatten(current)
  differing = sorted(k for k in set(a) | set(b) if a.get(k, "<absent>") != b.get(k, "<absent>"))
  return [k for k in differing if not any(k == p or (p.endswith(".") and k.startswith(p))
                                          for p in RESUMABLE_CHANGES)]


def check_compatible(workdir: str, config_json: dict) -> None:
  """Refuses to resume a workdir whose checkpoints came from a config of another shape or data."""
  path = os.path.join(workdir, "config.json")
  if not os.path.exists(path) or latest_step(workdir) is None:
    return
  with open(path) as f:
    saved = json.load(f)
  differing = incompatible_fields(saved, config_json)
  if differing:
    shown = ", ".join(f"{k} ({_flatten(saved).get(k, '<absent>')!r} -> {_flatten(config_json).get(k, '<absent>')!r})"
                      for k in differing[:6])
    raise UserError(f"workdir {workdir} holds checkpoints of a different config: {shown}; use a new "
                    f"--workdir or the workdir's own config.json settings.")


def checkpoint_dir(workdir: str) -> str:
  return os.path.join(os.path.abspath(workdir), "checkpoints")


def latest_step(workdir: str) -> int | None:
  """Newest complete checkpoint's step, without starting a manager (temporary folders are ignored)."""
  directory = checkpoint_dir(workdir)
  if not os.path.isdir(directory):
    return None
  steps = [int(name) for name in os.listdir(directory) if name.isdigit()]
  return max(steps) if steps else None


class Checkpoints:
  """One orbax CheckpointManager for a workdir: items 'state' (a pytree) and 'data' (JSON position)."""

  def __init__(self, workdir: str, every_steps: int, max_to_keep: int):
    options = ocp.CheckpointManagerOptions(save_interval_steps=every_steps, max_to_keep=max_to_keep,
                                           enable_async_checkpointing=True, create=True)
    self.manager = ocp.CheckpointManager(checkpoint_dir(workdir), options=options,
                                         item_names=("state", "data"))

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def restore(self, abstract_state, step: int | None = None):
    """(state, data position) of `step` (default: the newest), arrays placed as in `abstract_state`."""
    step = self.manager.latest_step() if step is None else step
    restored = self.manager.restore(step, args=ocp.args.Composite(
        state=ocp.args.StandardRestore(abstract_state), data=ocp.args.JsonRestore()))
    return restored["state"], restored["data"]

  def save(self, step: int, state, data_position: dict, force: bool = False) -> bool:
    """Starts an asynchronous save of `state` at `step` if due (or forced); returns whether it started."""
    return self.manager.save(step, args=ocp.args.Composite(
        state=ocp.args.StandardSave(state), data=ocp.args.JsonSave(data_position)), force=force)

  def wait(self) -> None:
    self.manager.wait_until_finished()

  def close(self) -> None:
    self.manager.wait_until_finished()
    self.manager.close()


def abstract_like(tree):
  """ShapeDtypeStructs with shardings: what StandardRestore needs to place a restored tree."""
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), tree)
