"""The one door to a trained workdir: its config, scene, model and newest checkpoint that reads back whole.

    check(workdir)                  the workdir's config, refused at once (no JAX) where it has no checkpoint
    restore(workdir)                a Trained: what the exports and the viewer start from (the workdir's own
                                    config.json, every device of this process's runtime)
    restore(workdir, config)        the same for --mode=eval and --mode=render (the command line's config,
                                    checked against the workdir's, on the run's mesh)
    newer(workdir, comps, above, damaged)
                                    (step, params) of the newest checkpoint after step `above` that reads back
                                    whole, or None: the viewer's poll while a training run goes on

Restoring only reads: the newest finished step that reads back whole (checkpoints.restore_newest: a damaged
step is said in one warning line and left in place for a training run to set aside), nothing written,
deleted or locked, so a training run may go on beside. A workdir without config.json or a checkpoint, an
unreachable one, or one none of whose checkpoints reads back whole is one sentence (UserError).
"""
import dataclasses
import json
import os
from typing import Any

import jax
import numpy as np

from nerfpod import distributed, schema, storage
from nerfpod.nerf import poses as pose_math
from nerfpod.run import compilation, components
from nerfpod.workdir import checkpoints, files as workdir_files
from nerfpod.errors import UserError


@dataclasses.dataclass(frozen=True)
class Trained:
  """A workdir's checkpoint with everything needed to render it and query its field."""
  workdir: str
  config: Any
  comps: components.Components
  params: Any
  step: int
  capture_to_scene: np.ndarray  # (4, 4) similarity: a capture point X lies at capture_to_scene @ X here
  damaged: dict = dataclasses.field(default_factory=dict)  # {newer step: why it does not read back whole}

  @property
  def scale(self) -> float:
    """Scene units per capture unit."""
    return pose_math.scale_of(self.capture_to_scene)

  def points_out(self, points_Nx3, normalized: bool) -> np.ndarray:
    """Scene points in the capture's coordinates (or as they are, `normalized`)."""
    points = np.asarray(points_Nx3, np.float64)
    if normalized:
      return points
    inverse = np.linalg.inv(self.capture_to_scene)
    return points @ inverse[:3, :3].T + inverse[:3, 3]

  def directions_out(self, directions_Nx3, normalized: bool) -> np.ndarray:
    """Unit directions (normals) in the capture's coordinates (or as they are)."""
    directions = np.asarray(directions_Nx3, np.float64)
    if normalized:
      return directions
    rotation = self.capture_to_scene[:3, :3] / self.scale
    return directions @ rotation  # R^T d, row-wise

  def poses_out(self, poses_Nx4x4, normalized: bool) -> np.ndarray:
    """Camera-to-world poses in the capture's coordinates (or as they are)."""
    poses = np.asarray(poses_Nx4x4, np.float64)
    return poses if normalized else pose_math.transform_poses(np.linalg.inv(self.capture_to_scene), poses)

  def field_name(self) -> str:
    """The NeRF field whose density and colour the renderer shows: the fine one of a hierarchical model."""
    return "fine" if self.config.render.num_importance > 0 else "coarse"


def _no_checkpoint(workdir: str, config) -> UserError:
  return UserError(f"workdir {workdir} holds no checkpoint yet; train first (nerfpod train --config=... "
                   f"--workdir={workdir}: its first save comes after checkpoint.every_steps="
                   f"{config.checkpoint.every_steps} steps) or pass the --workdir of a trained run.")


def check(workdir: str, config=None):
  """The config to restore `workdir` with (its config.json, or `config` checked against it and this run's
  devices), refused in one sentence where the workdir has no config.json or no checkpoint, or cannot be
  reached. Cheap: no JAX computation (a command checks this before it makes anything)."""
  workdir = str(workdir)
  given = config is not None
  if given:
    schema.validate(config, jax.device_count())
  workdir_files.check_workdir(workdir, writable=False)  # an existing file: one sentence
  if not storage.is_url(workdir) and not os.path.isdir(workdir):
    raise UserError(f"workdir {workdir} does not exist; check the --workdir path, or train first (nerfpod train "
                    f"--config=configs/default.py --workdir={workdir}).")
  if not given:
    config = workdir_files.read_config(workdir)
  if checkpoints.latest_step(workdir) is None:  # an unreachable bucket: one sentence
    raise _no_checkpoint(workdir, config)
  if given:  # the command line's model must be the one the checkpoints hold
    workdir_files.check_compatible(workdir, json.loads(config.to_json_best_effort()), has_checkpoint=True)
  return config


def restore(workdir: str, config=None) -> Trained:
  """The newest checkpoint of `workdir` that reads back whole, with its config, components and capture
  transform (module docstring). Without `config`: the workdir's own config.json, on every device of this
  process's runtime (the slices its devices report, not the run's mesh.slices: a count simulated on another
  machine may not divide these devices, and the pixels do not depend on it); the process's host settings are
  tuned for it. With `config` (--mode=eval or render): that config, on its own mesh."""
  workdir = str(workdir)
  own = config is None
  config = check(workdir, config)
  if own:
    compilation.tune_host(config)
  comps = components.build(config, distributed.make_mesh() if own else None)
  damaged = {}
  found = checkpoints.restore_newest(workdir, comps.state_shapes, damaged=damaged)
  if found is None:
    raise checkpoints.none_reads_back_whole(workdir, damaged)
  step, state = found
  transform = np.asarray(comps.scene.transform, np.float64)
  scene_json = storage.path(workdir) / "scene.json"
  if scene_json.exists():  # what the run trained with (the loader gives the same from the same data)
    transform = np.asarray(json.loads(scene_json.read_text())["capture_to_scene"], np.float64)
  if jax.process_index() == 0:
    print(f"nerfpod: restored step {step} of {workdir}", flush=True)
  return Trained(workdir, config, comps, state.params, step, transform, damaged)


def newer(workdir: str, comps: components.Components, above: int, damaged: dict) -> tuple[int, Any] | None:
  """(step, params) of the newest step of `workdir` after `above` that reads back whole, placed as `comps`
  (a restored Trained's) places them; None where there is none. A step that does not read back whole is said
  in one warning line, added to `damaged` ({step: why}; the steps already there are not read again) and left
  in place."""
  found = checkpoints.restore_newest(str(workdir), comps.state_shapes, above, damaged)
  return None if found is None else (found[0], found[1].params)
