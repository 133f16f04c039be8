"""Training: the sharded train step and the loop (resume, steps, checkpoints, previews, logging)."""
import concurrent.futures
import json
import sys
from typing import Any

import jax
import jax.numpy as jnp
import optax
from absl import logging
from jax.sharding import PartitionSpec as P

from nerfpod import checkpoints, components, distributed, render, video
from nerfpod.components import TrainState
from nerfpod.errors import UserError
from nerfpod.nerf import stepfun


def per_ray_uniforms(key, ray_ids, count: int):
  """(R, count) uniform numbers, ray i's drawn from fold_in(key, ray_ids[i]): the same for a ray whatever
  device or host renders it, so results do not depend on how the batch is split."""
  return jax.vmap(lambda i: jax.random.uniform(jax.random.fold_in(key, i), (count,)))(ray_ids)


def make_train_step(model, optimizer, mesh, near: float, far: float, background,
                    random_background: bool = False, microbatches: int = 1,
                    compiler_options: dict | None = None, interlevel_weight: float = 1.0,
                    distortion_weight: float = 0.0, ordered_mean: bool = True):
  """The jitted step(state, batch, key) -> (state, metrics); batch sharded over the mesh, state donated.

  Each device renders its rays and takes gradients of its mean squared error; gradients and losses are
  averaged across devices (every device holds the same number of rays, so that is the global mean) and every
  device applies the same Adam update to its replica of the parameters. With `ordered_mean` the mean is
  summed in an order that does not depend on the processes (distributed.ordered_mean: any topology of the
  same device count gives the same bits, at log2(N) exchanges of the gradients); without, it is one
  all-reduce (jax.lax.pmean), whose summation order is the collective's own (gradient_mean_is_ordered). A step whose loss, gradient or update is not finite leaves the state as it was.
  With `random_background` and batches that carry alpha, each ray's target is recomposited on a random
  colour (Instant-NGP's trick): empty space must then be transparent rather than painted the background
  colour, which gives clean depth, opacity and disparity.
  With `microbatches` > 1, each device's rays are processed in that many sequential slices whose gradients
  are averaged (gradient accumulation): the same result in a fraction of the activation memory.
  `compiler_options`: XLA options to compile the step with (xla_options.compiler_options).
  With proposal sampling (model.proposal_samples), the loss adds `interlevel_weight` times mip-NeRF 360's
  interlevel loss of every proposal round and `distortion_weight` times the distortion loss of the NeRF's
  weights; both are also returned as metrics.
  """
  background = jnp.asarray(background, jnp.float32)
  num_devices = mesh.shape[distributed.DATA_AXIS]

  def loss_fn(params, batch, key):
    # Round i's numbers come from stream i (0: coarse/stratified, 1: fine), skipping 2 (the backgrounds).
    uniforms = [per_ray_uniforms(jax.random.fold_in(key, i if i < 2 else i + 1), batch["ray_ids"], count)
                for i, count in enumerate(model.sample_counts())]
    target, ray_background = batch["rgb"], background
    if random_background and "alpha" in batch:
      ray_background = per_ray_uniforms(jax.random.fold_in(key, 2), batch["ray_ids"], 3)
      target = target + (1.0 - batch["alpha"][:, None]) * (ray_background - background)
    levels = model.apply(params, batch["origins"], batch["directions"], near, far, ray_background, *uniforms)
    mses = jnp.stack([jnp.mean((level["rgb"] - target)**2) for level in levels])
    loss = jnp.sum(mses)
    extra = {}
    final = levels[-1]
    if "proposals" in final:
      # The proposals learn to bound the NeRF's weights (a fixed target for them: no gradient into the NeRF
      # from this loss); the photometric loss reaches only the NeRF (sample positions carry no gradient).
      target_weights = jax.lax.stop_gradient(final["weights"])
      extra["interlevel"] = sum(jnp.mean(stepfun.interlevel_loss(final["s_edges"], target_weights,
                                                                 p["s_edges"], p["weights"]))
                                for p in final["proposals"])
      extra["distortion"] = jnp.mean(stepfun.distortion_loss(final["s_edges"], final["weights"]))
      loss = loss + interlevel_weight * extra["interlevel"] + distortion_weight * extra["distortion"]
    return loss, (mses, extra)

  value_and_grad = jax.value_and_grad(loss_fn, has_aux=True)

  def accumulate(params, batch, key):
    """(loss, mses), grads of the mean over this device's rays, one micro-batch at a time."""
    if microbatches == 1:
      return value_and_grad(params, batch, key)
    slices = jax.tree.map(lambda x: x.reshape((microbatches, -1) + x.shape[1:]), batch)
    def body(total, micro):
      value, grads = value_and_grad(params, micro, key)
      return jax.tree.map(lambda a, b: a + b / microbatches, total, (value, grads)), None
    zeros = jax.tree.map(jnp.zeros_like, jax.eval_shape(value_and_grad, params,
                                                        jax.tree.map(lambda x: x[0], slices), key))
    return jax.lax.scan(body, zeros, slices)[0]

  def local_step(state, batch, key):
    key = jax.random.fold_in(key, state.step)
    # Differentiate w.r.t. a device-varying view of the replicated parameters: each device then gets the
    # gradient of its own rays' loss. (Differentiating the replicated value directly would make shard_map
    # sum the cotangents across devices already, and the pmean below would then give N times the mean.)
    params = jax.lax.pcast(state.params, distributed.DATA_AXIS, to="varying")
    (loss, (mses, extra)), grads = accumulate(params, batch, key)
    if ordered_mean:
      grads, loss, mses, extra = distributed.ordered_mean((grads, loss, mses, extra), distributed.DATA_AXIS,
                                                          num_devices)
    else:
      grads, loss, mses, extra = jax.lax.pmean((grads, loss, mses, extra), distributed.DATA_AXIS)
    updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    # A non-finite loss, gradient or update never reaches the state: the step is skipped (the parameters and
    # Adam's moments and count stay as they were; the data moves on) and counted in metrics["skipped"].
    finite = checkpoints.all_finite((loss, grads, params, opt_state))
    params, opt_state = jax.tree.map(lambda new, old: jnp.where(finite, new, old), (params, opt_state),
                                     (state.params, state.opt_state))
    metrics = {"loss": loss, "mse": mses[-1], "psnr": -10.0 * jnp.log10(mses[-1]),
               "psnr_coarse": -10.0 * jnp.log10(mses[0]), "grad_norm": optax.tree.norm(grads),
               "skipped": 1 - finite.astype(jnp.int32), **extra}
    return TrainState(step=state.step + 1, params=params, opt_state=opt_state), metrics

  step = jax.shard_map(local_step, mesh=mesh, in_specs=(P(), P(distributed.DATA_AXIS), P()),
                       out_specs=(P(), P()))
  return jax.jit(step, donate_argnums=0, compiler_options=compiler_options)


class SkipCount:
  """Steps skipped for a non-finite loss or gradient: the total (logged as train/skipped) and the current run
  of them in a row, which stops training at `limit` with one sentence (the state, and so every checkpoint,
  holds the last good parameters)."""

  def __init__(self, limit: int):
    self.limit, self.total, self.in_row = limit, 0, 0

  def record(self, step: int, skipped, newest_checkpoint) -> None:
    """`newest_checkpoint()`: the newest saved step, named when training stops."""
    if not int(jax.device_get(skipped)):
      self.in_row = 0
      return
    self.total += 1
    self.in_row += 1
    if self.in_row == 1 and jax.process_index() == 0:
      print(f"nerfpod: warning: step {step} had a non-finite loss or gradient; skipped its update",
            file=sys.stderr, flush=True)
    if self.in_row >= self.limit:
      raise UserError(f"training diverged: the last {self.in_row} steps (to step {step}) all had a non-finite "
                      f"loss or gradient and were skipped (train.max_nonfinite_steps={self.limit}); no "
                      f"non-finite value was saved, the newest checkpoint is step {newest_checkpoint()}; train "
                      f"again in a new --workdir with a lower train.lr_init or a train.grad_clip > 0.")

  def with_total(self, metrics: dict) -> dict:
    """The fetched step metrics with 'skipped' (that step's flag) replaced by the total so far."""
    return dict(metrics, skipped=self.total)


def train_step(comps: components.Components, microbatches: int | None = None):
  """The jitted train step of a run's components (micro-batches: the config's unless given; 0: as few as
  fit the memory budget, see fit_microbatches)."""
  tc = comps.config.train
  microbatches = tc.microbatches if microbatches is None else microbatches
  if microbatches == 0:
    microbatches, _ = fit_microbatches(comps)
  return make_train_step(comps.model, comps.optimizer, comps.mesh, comps.near, comps.far,
                         comps.scene.background, tc.random_background, microbatches, comps.compiler_options,
                         tc.interlevel_weight, tc.distortion_weight, gradient_mean_is_ordered(comps.config))


def compiled_train_step(comps: components.Components):
  """The run's train step compiled ahead of time for its shapes (comps.state_shapes and batch_shapes): with
  train.microbatches=0, the fitted step is the very one compiled while fitting, not compiled a second time.
  Called with arguments of other shapes or placements it raises instead of recompiling."""
  if comps.config.train.microbatches == 0:
    return fit_microbatches(comps)[1]
  key = components.rays_key(comps.config.train.seed)
  return train_step(comps).lower(comps.state_shapes, comps.batch_shapes(), key).compile()


def start_compiling(comps: components.Components) -> concurrent.futures.Future:
  """compiled_train_step in a background thread, whose future is returned: XLA compiles without holding
  Python's lock, so the state's initialisation (itself a compilation) or restore overlaps the step's
  compilation, seconds off every start on a CPU. Tracing and lowering take the lock for a moment."""
  pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="nerfpod-compile")
  future = pool.submit(compiled_train_step, comps)
  pool.shutdown(wait=False)  # the thread ends with its one task
  return future


def gradient_mean_is_ordered(config, backend: str | None = None) -> bool:
  """compile.gradient_mean: 'ordered' (distributed.ordered_mean), 'pmean' (one all-reduce) or 'auto':
  ordered on a CPU, where simulated topologies are debugged and must agree bit for bit, one all-reduce on
  accelerators, where a pod's step must cost no more than the gradients' all-reduce (`backend`: JAX's
  default unless given; the pod compile tool asks for 'tpu')."""
  choice = config.compile.gradient_mean
  if choice == "auto":
    return (backend or jax.default_backend()) == "cpu"
  return choice == "ordered"


def fewest_microbatches(per_device: int, budget: int, step_bytes) -> tuple[int, int | None]:
  """The fewest micro-batches (a divisor of the `per_device` rays) whose step fits `budget` bytes per device,
  and that step's bytes; `step_bytes(count)` compiles the step with `count` micro-batches and returns XLA's
  memory analysis of it (step_memory_bytes). Each try is one compilation; the next count tried is scaled by
  how far the last one was over the budget. Where none fits, the most there can be."""
  divisors = [m for m in range(1, per_device + 1) if per_device % m == 0]
  count = 1
  while True:
    need = step_bytes(count)
    if need is None or need <= budget or count == divisors[-1]:
      return count, need
    wanted = count * need / max(budget, 1)  # activations dominate, and shrink with the slice
    count = next((m for m in divisors if m > count and m >= wanted), divisors[-1])


def step_memory_bytes(compiled) -> int | None:
  """What one device needs to run a compiled step, from XLA's own buffer assignment: its arguments, outputs
  and temporaries, less the outputs that reuse (donated) arguments' buffers. None where XLA reports none."""
  analysis = compiled.memory_analysis()
  if analysis is None:
    return None
  return int(analysis.argument_size_in_bytes + analysis.output_size_in_bytes + analysis.temp_size_in_bytes
             - analysis.alias_size_in_bytes)


def memory_budget_bytes(config) -> int:
  """The memory one device's train step may use: on accelerators 85% of what the device reports (the rest
  for the runtime, the renderer, fragmentation); on a CPU, compile.cpu_memory_gib shared by this process's
  simulated devices."""
  stats = jax.local_devices()[0].memory_stats() or {}
  if jax.default_backend() != "cpu" and stats.get("bytes_limit"):
    return int(0.85 * stats["bytes_limit"])
  return int(config.compile.cpu_memory_gib * 2**30 / jax.local_device_count())


def fit_microbatches(comps: components.Components) -> tuple[int, Any]:
  """train.microbatches=0: the fewest micro-batches (a divisor of the rays each device holds) whose compiled
  step fits memory_budget_bytes, by XLA's memory analysis of the step compiled for this run's shapes
  (fewest_microbatches); returns that count and that compiled step."""
  tc = comps.config.train
  per_device = tc.batch_size // jax.device_count()
  budget = memory_budget_bytes(comps.config)
  shapes, batch, key = comps.state_shapes, comps.batch_shapes(), components.rays_key(tc.seed)
  compiled = {}

  def step_bytes(count):
    compiled[count] = train_step(comps, count).lower(shapes, batch, key).compile()
    return step_memory_bytes(compiled[count])

  count, need = fewest_microbatches(per_device, budget, step_bytes)
  if jax.process_index() == 0:
    fits = "fits" if need is None or need <= budget else "is the most there can be; it does not fit"
    shown = "unknown" if need is None else f"{need / 2**20:,.1f} MiB"
    print(f"nerfpod: train.microbatches=0: {count} micro-batch(es) of {per_device // count} rays per device "
          f"({shown} per device by XLA's analysis) {fits} the budget of {budget / 2**20:,.1f} MiB per device",
          flush=True)
  return count, compiled[count]


def train(comps: components.Components, workdir: str, monitor) -> tuple[TrainState, int] | None:
  """Trains from workdir's newest checkpoint (or from scratch) to train.num_steps, checkpointing as it goes.

  Returns (state, step) at the end, or None when a SIGTERM (preemption) stopped training: the state was
  then saved at a step all processes agreed on. The workdir's config.json is written once the checkpoint,
  if any, has been restored: a refused resume leaves it as it was.
  """
  config = comps.config
  tc = config.train
  ckpt = checkpoints.Checkpoints(workdir, config.checkpoint.every_steps, config.checkpoint.max_to_keep)
  try:
    # The step compiles while the state is restored or initialised (not when training is already done).
    compiling = start_compiling(comps) if (ckpt.latest_step() or 0) < tc.num_steps else None
    start_step = 0
    if ckpt.latest_step() is not None:
      state, position = ckpt.restore(comps.state_shapes)
      start_step = int(position["next_step"])
      logging.info("resumed from step %d", start_step)
    else:
      state = comps.init_state()
    checkpoints.write_config(workdir, json.loads(config.to_json_best_effort()))
    checkpoints.write_scene(workdir, comps.scene.description())
    if jax.process_index() == 0:
      print(f"nerfpod: scene {comps.scene.name} ({len(comps.scene.split('train'))} training views), "
            f"{jax.process_count()} process(es), {jax.device_count()} device(s), "
            f"steps {start_step}..{tc.num_steps}, {tc.batch_size} rays/step", flush=True)

    schedule = components.learning_rate_schedule(tc)
    key = components.rays_key(tc.seed)
    batches = comps.batches(start_step)
    if start_step < tc.num_steps:  # (a damaged newest checkpoint may have put start_step back)
      step_fn = (compiling or start_compiling(comps)).result()
    if start_step < tc.num_steps and jax.process_count() > 1:
      # Every process has compiled before the first step: wait for all of them (see wait_for_all).
      distributed.wait_for_all(f"nerfpod_train_step_compiled_{start_step}")
    preview = comps.scene.split(config.eval.split)

    pending = None  # metrics of a log step, fetched only after the next step is dispatched
    skips = SkipCount(tc.max_nonfinite_steps)
    unchecked = None  # (step, whether it was skipped) of the previous step, read after this one is dispatched
    for step in range(start_step, tc.num_steps):
      local = next(batches)
      assert int(local.pop("step")) == step, "data pipeline out of step with training"
      state, metrics = step_fn(state, distributed.to_global(comps.mesh, local), key)
      if unchecked is not None:
        skips.record(*unchecked, ckpt.latest_step)
      unchecked = (step + 1, metrics["skipped"])
      if pending is not None:
        monitor.scalars(pending[0], skips.with_total(jax.device_get(pending[1])), float(schedule(pending[0] - 1)))
        pending = None
      done = step + 1
      if done % tc.log_every == 0 or done == tc.num_steps or step == start_step:
        pending = (done, metrics)
      ckpt.save(done, state, {"next_step": done})  # every checkpoint.every_steps, and when preempted
      if ckpt.reached_preemption(done):
        if pending is not None:
          monitor.scalars(pending[0], skips.with_total(jax.device_get(pending[1])),
                          float(schedule(pending[0] - 1)))
        ckpt.close()  # waits until the step is on disk
        if jax.process_index() == 0:
          print(f"nerfpod: preempted: saved step {done} in {checkpoints.checkpoint_dir(workdir)} and "
                f"stopped; the same command resumes from there.", flush=True)
        return None
      if tc.image_every and done % tc.image_every == 0:
        out = render.render_image(comps.renderer, state.params, comps.mesh, preview.poses[0],
                                  preview.cameras[0], config.data.pixel_center, config.eval.chunk)
        monitor.images(done, {"preview/rgb": out["rgb"],
                              "preview/depth": video.depth_image(out["depth"], comps.near, comps.far)[..., None]})
    if unchecked is not None:
      skips.record(*unchecked, ckpt.latest_step)
    if pending is not None:
      monitor.scalars(pending[0], skips.with_total(jax.device_get(pending[1])), float(schedule(pending[0] - 1)))
    final_step = int(jax.device_get(state.step))
    if ckpt.latest_step() != final_step:
      ckpt.save(final_step, state, {"next_step": final_step}, force=True)
  finally:
    ckpt.close()  # also on an exception: waits for a save under way, gives SIGTERM back
  return state, final_step
