"""Training: the loop (resume, steps, checkpoints, preemption, previews, logging); the step is nerfpod.run.step."""
import dataclasses
import json
import os
import sys

import jax
from absl import logging

from nerfpod import distributed
from nerfpod.render import renderer, video
from nerfpod.run import components, preemption, profiling, train_state
from nerfpod.workdir import checkpoints
from nerfpod.run import step as train_step
from nerfpod.workdir.files import saved_config, write_config, write_regions, write_scene
from nerfpod.run.train_state import TrainState
from nerfpod.errors import UserError
from nerfpod.nerf import regions


# Host <-> device transfers the loop may make without saying so (jax.transfer_guard's level): the tests set
# NERFPOD_LOOP_TRANSFER_GUARD=disallow (tests/conftest.py, for their processes too), so that a value moved
# implicitly (a host value in a device computation, a key on one device passed to the mesh's program, and on
# an accelerator float(x) of a device array) fails there instead of quietly costing a transfer every step.
TRANSFER_GUARD = os.environ.get("NERFPOD_LOOP_TRANSFER_GUARD", "allow")


class SkipCount:
  """Steps skipped for a non-finite loss or gradient: the total (logged as train/skipped) and the current
  streak of them in a row. A streak stops training with one sentence at `limit` steps, and so does a run that
  ends inside one (`check_ended`). While a streak lasts, the newest checkpoint saved before its first step is
  pinned (kept past checkpoint.max_to_keep) and named in that sentence: the steps that follow hold no update
  and may hold parameters that had already grown useless before the first non-finite value. The streak is
  part of the data position saved with each checkpoint (`position`), so a resumed run continues it."""

  def __init__(self, limit: int, ckpt, position: dict | None = None):
    position = position or {}
    self.limit, self.ckpt = limit, ckpt
    self.total = int(position.get("skipped", 0))
    self.in_row = int(position.get("skipped_in_row", 0))
    self.first = position.get("streak_from")  # the streak's first skipped step
    self.before = position.get("checkpoint_before_streak")  # the newest checkpoint saved before it
    self._unchecked = None  # (step, flag on the device) of the step dispatched last, not read yet
    if self.in_row:
      ckpt.pin(self.before)

  def dispatched(self, step: int, skipped) -> None:
    """Step `step` (counted from 1) is dispatched, `skipped` its flag on the device: the previous step's flag
    is read now, when the device is busy with this one (reading this one's would wait for it)."""
    self.settle()
    self._unchecked = (step, skipped)

  def settle(self) -> None:
    """Reads the flag of the step dispatched last, where not read yet (before its position is saved)."""
    if self._unchecked is not None:
      step, skipped = self._unchecked
      self._unchecked = None
      self.record(step, skipped)

  def record(self, step: int, skipped) -> None:
    """Whether step `step` (counted from 1) was skipped."""
    if not int(jax.device_get(skipped)):
      if self.in_row:
        self.ckpt.unpin()
      self.in_row, self.first, self.before = 0, None, None
      return
    self.total += 1
    self.in_row += 1
    if self.in_row == 1:
      self.first, self.before = step, self.ckpt.newest_before(step)
      self.ckpt.pin(self.before)
      if jax.process_index() == 0:
        print(f"nerfpod: warning: step {step} had a non-finite loss or gradient; skipped its update",
              file=sys.stderr, flush=True)
    if self.in_row >= self.limit:
      raise UserError(f"training diverged: the last {self.in_row} steps (to step {step}) all had a non-finite "
                      f"loss or gradient and were skipped (train.max_nonfinite_steps={self.limit}); "
                      f"{self._advice()}")

  def check_ended(self, step: int) -> None:
    """Refuses a run whose last step `step` lies inside a streak of skipped steps."""
    if self.in_row:
      raise UserError(f"training diverged: it ended at step {step} inside a run of {self.in_row} skipped steps "
                      f"(from step {self.first}, each with a non-finite loss or gradient); {self._advice()}")

  def _advice(self) -> str:
    where = (f"the newest checkpoint before it is step {self.before}" if self.before is not None else
             "no checkpoint was saved before it")
    return (f"no non-finite value was saved, and {where}; train again in a new --workdir with a lower "
            f"train.lr_init or a train.grad_clip > 0.")

  def position(self, next_step: int) -> dict:
    """The data position saved with a checkpoint: the next step, and the skip counts where there are any."""
    position = {"next_step": next_step}
    if self.total:
      position["skipped"] = self.total
    if self.in_row:
      position.update(skipped_in_row=self.in_row, streak_from=self.first, checkpoint_before_streak=self.before)
    return position

  def with_total(self, metrics: dict) -> dict:
    """The fetched step metrics with 'skipped' (that step's flag) replaced by the total so far."""
    return dict(metrics, skipped=self.total)


class CollapseWatch:
  """One warning line when proposal sampling has collapsed (stepfun.resampling_weights' trap) over a log
  window: at two log steps in a row, the NeRF's sampling window spans under WINDOW of the ray and more than
  HEAVY of the rays' last proposal round holds nearly all its weight in one interval (step.proposal_diagnostics).
  A healthy run of the cup reads a window of about 0.43 and no heavy rays (docs/training.md)."""
  WINDOW, HEAVY = 0.05, 0.5

  def __init__(self):
    self.since = None  # the first log step of the present collapse
    self.warned = False

  def check(self, step: int, metrics: dict) -> str | None:
    """The warning at this log step, or None."""
    if "window" not in metrics:
      return None
    collapsed = float(metrics["window"]) < self.WINDOW and float(metrics["heavy"]) > self.HEAVY
    if not collapsed:
      self.since = None
      return None
    if self.since is None:
      self.since = step
      return None
    if self.warned:
      return None
    self.warned = True
    return (f"step {step}: proposal sampling has collapsed since step {self.since}: the NeRF's samples span "
            f"{float(metrics['window']):.3f} of each ray, {float(metrics['heavy']):.0%} of the rays' last proposal "
            f"holds over 99% of its weight in one interval and the interlevel loss reads "
            f"{float(metrics['interlevel']):.1e}, so the proposals no longer learn; resume with "
            f"--config.render.proposal_padding=0.01 (docs/training.md, proposal sampling's diagnostics).")


class DropWatch:
  """model.region_capacity > 0: the rays the step dropped (a ray whose segment in some region found no row
  within the capacity C is dropped whole: the step's metric regions/dropped), summed over each log window (the
  steps since the previous log line). A window that dropped more than LIMIT of its rays stops training with one
  sentence. The window's counts stay on the device until its log step (no wait per step). `auto`: the fraction
  is model.region_capacity=auto's (the sentence says so)."""
  LIMIT = 1e-3

  def __init__(self, fraction: float, batch_size: int, auto: bool = False, split_fractions: tuple = ()):
    self.fraction, self.batch_size, self.auto = fraction, batch_size, auto
    self.split_fractions = tuple(split_fractions)  # model.region_split's classes' (region_split_capacity)
    self.window = []  # (step, dropped, fill, capacity) of each step of the window, on the device

  def dispatched(self, step: int, metrics) -> None:
    self.window.append((step, metrics["regions/dropped"], metrics["regions/fill"], metrics["regions/capacity"]))

  def check(self) -> None:
    """At a log step: refuses a window (its steps so far) that dropped over LIMIT of its rays."""
    window, self.window = jax.device_get(self.window), []
    if not window:
      return
    dropped = sum(float(d) for _, d, _, _ in window)
    rays = len(window) * self.batch_size
    if dropped <= self.LIMIT * rays:
      return
    fill = max(float(f) for _, _, f, _ in window)
    capacity = int(window[-1][3])
    shown = f"auto (F = {self.fraction:g})" if self.auto else f"{self.fraction:g}"
    if self.split_fractions:
      larger = tuple(min(1.0, _round_up(f * fill * 1.1, 0.05)) for f in self.split_fractions)
      raise UserError(f"training dropped {dropped:,.0f} of the {rays:,} rays of steps {window[0][0]} to "
                      f"{window[-1][0]} ({dropped / rays:.2%}, over the {self.LIMIT:.1%} a run may drop): "
                      f"model.region_split_capacity=({', '.join(f'{f:g}' for f in self.split_fractions)}) gives "
                      f"the regions' sample classes {capacity} rows in all of each device's rays and the fullest "
                      f"class of a region filled {fill:.2f} x its rows, so rays over capacity were dropped whole; "
                      f"resume with --config.model.region_split_capacity='({','.join(f'{f:g}' for f in larger)})' "
                      f"(or --config.model.region_capacity=0: every ray through every region).")
    raise UserError(f"training dropped {dropped:,.0f} of the {rays:,} rays of steps {window[0][0]} to "
                    f"{window[-1][0]} ({dropped / rays:.2%}, over the {self.LIMIT:.1%} a run may drop): "
                    f"model.region_capacity={shown} gives each region C = {capacity} rows of each "
                    f"device's rays and the fullest region's rays with a segment in it filled {fill:.2f} x C, so "
                    f"rays over capacity were dropped whole; resume with --config.model.region_capacity="
                    f"{min(1.0, _round_up(self.fraction * fill * 1.1, 0.05)):g} (or 0: every ray through every "
                    f"region).")


def _round_up(value: float, step: float) -> float:
  return round(-(-value // step) * step, 6)


class StepLog:
  """The log line and scalars of the first step, every train.log_every-th and the last: one call site,
  monitor.scalars. A step's metrics are fetched one step late, once the next step is dispatched, so that
  logging never waits for the device; `flush` logs what is still pending (the end of a run, a preemption)."""

  def __init__(self, monitor, train_config, start_step: int, skips: SkipCount, drops: DropWatch | None = None):
    self.monitor, self.skips, self.drops = monitor, skips, drops
    self.learning_rate = jax.jit(train_state.learning_rate_schedule(train_config))  # of a step on the device
    self.every, self.last, self.first = train_config.log_every, train_config.num_steps, start_step + 1
    self.pending = None  # (step, metrics on the device)
    self.collapse = CollapseWatch()

  def dispatched(self, step: int, metrics) -> None:
    self.flush()
    if self.drops is not None:
      self.drops.dispatched(step, metrics)
    if step % self.every == 0 or step in (self.first, self.last):
      self.pending = (step, metrics)

  def flush(self) -> None:
    if self.pending is not None:
      step, metrics = self.pending
      self.pending = None
      lr = float(jax.device_get(self.learning_rate(jax.device_put(step - 1))))
      metrics = jax.device_get(metrics)
      self.monitor.scalars(step, self.skips.with_total(metrics), lr)
      warning = self.collapse.check(step, metrics)
      if warning and jax.process_index() == 0:
        print(f"nerfpod: warning: {warning}", file=sys.stderr, flush=True)
      if self.drops is not None:  # the window ends here (logged): refused where it dropped too many rays
        self.drops.check()


def resolve_capacity(comps: components.Components, workdir: str, resuming: bool) -> components.Components:
  """`comps` with model.region_capacity=auto (model.regions > 1) resolved to a fraction, the same on every process:
  where the run resumes (`resuming`: the workdir holds a checkpoint) and the workdir's config.json records a
  fraction > 0 (what its run trained with: config.json is the resolved config), that one, so that the resumed
  run compiles the same step; else measured on the training rays (step.measure_capacity). Process 0 says which
  in one line; config.json then records the fraction (_announce). Any other config: `comps` as they are."""
  config = comps.config
  if config.model.regions == 1 or config.model.region_capacity != "auto":
    return comps
  saved = ((saved_config(workdir) or {}).get("model") or {}) if resuming else {}
  recorded, recorded_split = saved.get("region_capacity"), tuple(saved.get("region_split_capacity") or ())
  classes = int(config.model.region_split)
  is_fraction = lambda f: isinstance(f, (int, float)) and not isinstance(f, bool) and 0.0 < f <= 1.0  # noqa: E731
  if is_fraction(recorded) and (classes <= 1 or (len(recorded_split) == classes
                                                 and all(is_fraction(f) for f in recorded_split))):
    fraction, split_fractions = float(recorded), tuple(float(f) for f in recorded_split) if classes > 1 else ()
    rows = train_step.region_rows(config, comps.mesh)
    if split_fractions:
      line = (f"model.region_capacity=auto: F = {', '.join(f'{f:g}' for f in split_fractions)} for the sample "
              f"classes, as the workdir's config.json records (the fractions its run trained with): C = "
              f"{', '.join(str(regions.capacity_rows(f, rows)) for f in split_fractions)} of {rows} rows per region")
    else:
      line = (f"model.region_capacity=auto: F = {fraction:g}, as the workdir's config.json records (the fraction "
              f"its run trained with): C = {regions.capacity_rows(fraction, rows)} of {rows} rows per region")
  else:
    measured = train_step.measure_capacity(config, comps.scene, comps.mesh, comps.model.partition, comps.near,
                                           comps.far)
    fraction, split_fractions, line = measured.fraction, measured.split_fractions, measured.line()
    comps = dataclasses.replace(comps, capacity_measured=measured)  # (train.microbatches=0: fitted_capacity)
  if jax.process_index() == 0:
    print(f"nerfpod: {line}", flush=True)
  return dataclasses.replace(comps, config=train_step.with_capacity(config, fraction, split_fractions))


def _restore_or_init(comps: components.Components, ckpt) -> tuple[TrainState, int, dict | None]:
  """(state, first step, data position): the newest checkpoint's, or a new state."""
  if ckpt.latest_step() is None:
    return comps.init_state(), 0, None
  state, position = ckpt.restore(comps.state_shapes)
  start_step = int(position["next_step"])
  logging.info("resumed from step %d", start_step)
  return state, start_step, position


def _announce(comps: components.Components, workdir: str, start_step: int) -> None:
  """(Process 0) the workdir's config.json and scene.json, and the run's first lines."""
  if jax.process_index() != 0:
    return
  config, tc = comps.config, comps.config.train
  write_config(workdir, json.loads(config.to_json_best_effort()))
  write_scene(workdir, comps.scene.description())
  if config.model.regions > 1:  # where each region's fields live (regions.json)
    write_regions(workdir, config.model.region_cut, comps.model.region_planes)
  slices = distributed.num_slices(comps.mesh)
  print(f"nerfpod: JAX {jax.__version__} on {jax.default_backend()}: {jax.device_count()} x "
        f"{jax.devices()[0].device_kind}", flush=True)
  print(f"nerfpod: scene {comps.scene.name} ({len(comps.scene.split('train'))} training views), "
        f"{jax.process_count()} process(es), {jax.device_count()} device(s)"
        f"{f' in {slices} slices' if slices > 1 else ''}, "
        f"steps {start_step}..{tc.num_steps}, {tc.batch_size} rays/step", flush=True)


def _preview(comps: components.Components, params, monitor, step: int) -> None:
  """The first held-out view (of eval.split) at this step, colour and depth, to TensorBoard."""
  config = comps.config
  view = comps.scene.split(config.eval.split)
  out = renderer.render_image(comps.renderer, params, comps.mesh, view.poses[0], view.cameras[0],
                              config.data.pixel_center, config.eval.chunk)
  monitor.images(step, {"preview/rgb": out["rgb"],
                        "preview/depth": video.depth_image(out["depth"], comps.near, comps.far)[..., None]})


def train(comps: components.Components, workdir: str, monitor) -> tuple[TrainState, int] | None:
  """Trains from workdir's newest checkpoint (or from scratch) to train.num_steps, checkpointing as it goes.

  Returns (state, step) at the end, or None when a SIGTERM (preemption) stopped training: the state was
  then saved at a step all processes agreed on. The workdir's config.json is written once the checkpoint,
  if any, has been restored: a refused resume leaves it as it was.
  """
  config = comps.config
  tc = config.train
  ckpt = checkpoints.Checkpoints(workdir, config.checkpoint.every_steps, config.checkpoint.max_to_keep,
                                 storage_timeout_s=config.checkpoint.storage_timeout_s)
  auto_capacity = config.model.region_capacity == "auto"
  watch = preemption.Watch(ckpt.latest_step() or 0)
  profile = profiling.StepProfile(workdir, tc.profile_steps)
  try:
    comps = resolve_capacity(comps, workdir, resuming=ckpt.latest_step() is not None)  # before the step compiles
    config = comps.config
    # The step compiles while the state is restored or initialised (not when training is already done).
    compiling = train_step.start_compiling(comps) if (ckpt.latest_step() or 0) < tc.num_steps else None
    state, start_step, position = _restore_or_init(comps, ckpt)
    if start_step < tc.num_steps:  # (a damaged newest checkpoint may have put start_step back)
      # A step the devices cannot hold is refused here, before the workdir holds anything of this run.
      step_fn, comps = (compiling or train_step.start_compiling(comps)).result()
      config = comps.config  # (a measured auto capacity's margin for the fitted micro-batches: config.json's)
      if jax.process_count() > 1:
        # Every process has compiled before the first step: wait for all of them (see wait_for_all).
        distributed.wait_for_all(f"nerfpod_train_step_compiled_{start_step}")
    _announce(comps, workdir, start_step)
    skips = SkipCount(tc.max_nonfinite_steps, ckpt, position)
    drops = (DropWatch(config.model.region_capacity, tc.batch_size, auto=auto_capacity,
                       split_fractions=regions.class_capacities(config.model.region_capacity,
                                                                config.model.region_split,
                                                                tuple(config.model.region_split_capacity)))
             if config.model.regions > 1 and config.model.region_capacity else None)
    log = StepLog(monitor, tc, start_step, skips, drops)
    key = train_state.rays_key(tc.seed, comps.mesh)
    batches = comps.batches(start_step)

    with jax.transfer_guard(TRANSFER_GUARD):  # (the tests: 'disallow', every transfer an explicit one)
      for step in range(start_step, tc.num_steps):
        done = step + 1
        local = next(batches)
        assert int(local.pop("step")) == step, "data pipeline out of step with training"
        profile.starting(done)
        state, metrics = step_fn(state, distributed.to_global(comps.mesh, local), key)
        profile.finished(done, state)
        skips.dispatched(done, metrics["skipped"])
        log.dispatched(done, metrics)
        preempted = watch.reached(done)
        if preempted or done % config.checkpoint.every_steps == 0:
          skips.settle()  # the position saved counts this step's skip
        ckpt.save(done, state, skips.position(done), force=preempted)
        if preempted:
          log.flush()
          ckpt.close()  # waits until the step is on disk
          if jax.process_index() == 0:
            print(f"nerfpod: preempted: saved step {done} in {checkpoints.checkpoint_dir(workdir)} and "
                  f"stopped; the same command resumes from there.", flush=True)
          return None
        if tc.image_every and done % tc.image_every == 0:
          _preview(comps, state.params, monitor, done)
      skips.settle()
      log.flush()
    final_step = int(jax.device_get(state.step))
    if ckpt.latest_step() != final_step:
      ckpt.save(final_step, state, skips.position(final_step), force=True)
    skips.check_ended(final_step)
  finally:
    profile.close()
    ckpt.close()  # also on an exception: waits for a save under way
    watch.close()  # gives SIGTERM and SIGINT back
  return state, final_step
