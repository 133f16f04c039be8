"""Training: the train state, the sharded step, the loop, checkpoints and logging."""
import json
import time
from typing import Any, NamedTuple

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax
from absl import logging
from jax.sharding import PartitionSpec as P

from nerfpod import checkpoints, data, distributed, evaluate, orbit, render, scenes, xla_options
from nerfpod.errors import UserError
from nerfpod.nerf import model as nerf_model

# Tags folded into the seed so that each use of randomness has its own stream.
_PARAMS, _RAYS = 0, 1


@flax.struct.dataclass
class TrainState:
  step: jax.Array  # scalar int32: optimiser steps taken
  params: Any
  opt_state: Any


def learning_rate_schedule(tc) -> optax.Schedule:
  """Linear warm-up to lr_init, then log-linear decay to lr_final at the last step (the original NeRF's)."""
  decay_steps = max(1, tc.num_steps - tc.lr_warmup_steps)
  decay = optax.exponential_decay(tc.lr_init, decay_steps, tc.lr_final / tc.lr_init)
  if tc.lr_warmup_steps <= 0:
    return decay
  warmup = optax.linear_schedule(0.0, tc.lr_init, tc.lr_warmup_steps)
  return optax.join_schedules([warmup, decay], [tc.lr_warmup_steps])


def make_optimizer(tc) -> optax.GradientTransformation:
  adam = optax.adam(learning_rate_schedule(tc), eps=tc.adam_eps)
  return optax.chain(optax.clip_by_global_norm(tc.grad_clip), adam) if tc.grad_clip > 0 else adam


def ray_bounds(config, scene) -> tuple[float, float]:
  near = config.render.near if config.render.near >= 0 else scene.near
  far = config.render.far if config.render.far >= 0 else scene.far
  if not 0 <= near < far:
    raise UserError(f"render.near={near} and render.far={far} must satisfy 0 <= near < far.")
  return float(near), float(far)


def init_state(model, optimizer, seed: int, mesh) -> TrainState:
  """Parameters and optimiser state, created directly replicated on every device."""
  def init(key):
    rays = jnp.zeros((2, 3), jnp.float32), jnp.ones((2, 3), jnp.float32)
    params = model.init(key, *rays, 2.0, 6.0, jnp.zeros(3))
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=optimizer.init(params))
  key = jax.random.fold_in(jax.random.key(seed), _PARAMS)
  return jax.jit(init, out_shardings=distributed.replicated(mesh))(key)


def per_ray_uniforms(key, ray_ids, count: int):
  """(R, count) uniform numbers, ray i's drawn from fold_in(key, ray_ids[i]): the same for a ray whatever
  device or host renders it, so results do not depend on how the batch is split."""
  return jax.vmap(lambda i: jax.random.uniform(jax.random.fold_in(key, i), (count,)))(ray_ids)


def make_train_step(model, optimizer, mesh, near: float, far: float, background,
                    random_background: bool = False, microbatches: int = 1,
                    compiler_options: dict | None = None):
  """The jitted step(state, batch, key) -> (state, metrics); batch sharded over the mesh, state donated.

  Each device renders its rays and takes gradients of its mean squared error; gradients and losses are
  averaged across devices with pmean (every device holds the same number of rays, so that is the global
  mean) and every device applies the same Adam update to its replica of the parameters.
  With `random_background` and batches that carry alpha, each ray's target is recomposited on a random
  colour (Instant-NGP's trick): empty space must then be transparent rather than painted the background
  colour, which gives clean depth, opacity and disparity.
  With `microbatches` > 1, each device's rays are processed in that many sequential slices whose gradients
  are averaged (gradient accumulation): the same result in a fraction of the activation memory.
  `compiler_options`: XLA options to compile the step with (xla_options.compiler_options).
  """
  background = jnp.asarray(background, jnp.float32)

  def loss_fn(params, batch, key):
    u_coarse = per_ray_uniforms(jax.random.fold_in(key, 0), batch["ray_ids"], model.num_samples)
    u_fine = (per_ray_uniforms(jax.random.fold_in(key, 1), batch["ray_ids"], model.num_importance)
              if model.num_importance else None)
    target, ray_background = batch["rgb"], background
    if random_background and "alpha" in batch:
      ray_background = per_ray_uniforms(jax.random.fold_in(key, 2), batch["ray_ids"], 3)
      target = target + (1.0 - batch["alpha"][:, None]) * (ray_background - background)
    levels = model.apply(params, batch["origins"], batch["directions"], near, far, ray_background,
                         u_coarse, u_fine)
    mses = jnp.stack([jnp.mean((level["rgb"] - target)**2) for level in levels])
    return jnp.sum(mses), mses

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
    (loss, mses), grads = accumulate(params, batch, key)
    grads, loss, mses = jax.lax.pmean((grads, loss, mses), distributed.DATA_AXIS)
    updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    metrics = {"loss": loss, "mse": mses[-1], "psnr": -10.0 * jnp.log10(mses[-1]),
               "psnr_coarse": -10.0 * jnp.log10(mses[0]), "grad_norm": optax.tree.norm(grads)}
    return TrainState(step=state.step + 1, params=params, opt_state=opt_state), metrics

  step = jax.shard_map(local_step, mesh=mesh, in_specs=(P(), P(distributed.DATA_AXIS), P()),
                       out_specs=(P(), P()))
  return jax.jit(step, donate_argnums=0, compiler_options=compiler_options)


class Setup(NamedTuple):
  """What training, evaluation, rendering and the benchmark all build from a config, on the global mesh."""
  scene: Any
  mesh: Any
  model: Any
  optimizer: Any
  near: float
  far: float
  state: TrainState  # freshly initialised: restore a checkpoint into it
  render_fn: Any     # the compiled renderer (previews, evaluation)

  def train_step(self, config, microbatches: int | None = None):
    """The jitted train step of this set-up (micro-batches: config.train's unless given)."""
    tc = config.train
    return make_train_step(self.model, self.optimizer, self.mesh, self.near, self.far, self.scene.background,
                           tc.random_background, tc.microbatches if microbatches is None else microbatches,
                           xla_options.compiler_options(config))

  def batches(self, config, start_step: int):
    """This host's slices of the global training batches from `start_step` on."""
    tc = config.train
    dataset = data.ray_batches(self.scene.split("train"), tc.seed, tc.batch_size,
                               distributed.local_slice(tc.batch_size), config.data.pixel_center,
                               max(tc.num_steps, 1))
    return data.iterator(dataset, start_step)


def setup(config) -> Setup:
  """Loads the scene (a missing held-out split fails now, not after training), makes the mesh, the model,
  the optimiser, the initial state and the renderer."""
  scene = scenes.load(config.data)
  scene.split(config.eval.split)
  mesh = distributed.make_mesh()
  model = nerf_model.from_config(config)
  near, far = ray_bounds(config, scene)
  optimizer = make_optimizer(config.train)
  state = init_state(model, optimizer, config.train.seed, mesh)
  render_fn = render.make_render_fn(model, mesh, near, far, scene.background,
                                    xla_options.compiler_options(config))
  return Setup(scene, mesh, model, optimizer, near, far, state, render_fn)


def rays_key(seed: int):
  """The key of the rays' randomness (stratified jitter, random backgrounds); the step folds in the step."""
  return jax.random.fold_in(jax.random.key(seed), _RAYS)


def _check_config(config) -> None:
  tc = config.train
  if tc.num_steps < 0 or tc.batch_size <= 0:
    raise UserError("train.num_steps must be >= 0 and train.batch_size > 0.")
  if tc.batch_size % jax.device_count():
    raise UserError(f"train.batch_size={tc.batch_size} does not split over {jax.device_count()} devices; "
                    f"make it a multiple of {jax.device_count()}.")
  if tc.microbatches < 1 or tc.batch_size % (jax.device_count() * tc.microbatches):
    raise UserError(f"train.batch_size={tc.batch_size} does not split into train.microbatches="
                    f"{tc.microbatches} equal slices on each of {jax.device_count()} devices.")
  evaluate.check_config(config)
  if config.checkpoint.every_steps <= 0:
    raise UserError("checkpoint.every_steps must be a positive number of steps.")


class _Monitor:
  """TensorBoard events and console lines, written by process 0 only."""

  def __init__(self, workdir: str, num_steps: int, batch_size: int):
    self.enabled = jax.process_index() == 0
    self.num_steps, self.batch_size = num_steps, batch_size
    self.writer = distributed.summary_writer(workdir, flush_secs=10)
    self._last = None  # (step, time) of the last console line

  def scalars(self, step: int, metrics: dict, lr: float) -> None:
    now = time.perf_counter()
    if self._last is None or step <= self._last[0]:
      self._last = (step, now)
      rays_per_s = None
    else:
      rays_per_s = (step - self._last[0]) * self.batch_size / (now - self._last[1])
      eta = (self.num_steps - step) * (now - self._last[1]) / (step - self._last[0])
      self._last = (step, now)
    if not self.enabled:
      return
    for name, value in metrics.items():
      self.writer.add_scalar(f"train/{name}", float(value), step)
    self.writer.add_scalar("train/learning_rate", lr, step)
    line = (f"step {step:>6d}/{self.num_steps} | loss {float(metrics['loss']):.5f} | "
            f"psnr {float(metrics['psnr']):6.2f} dB | lr {lr:.2e}")
    if rays_per_s is not None:
      self.writer.add_scalar("train/rays_per_sec", rays_per_s, step)
      line += f" | {rays_per_s:,.0f} rays/s | ETA {_duration(eta)}"
    print(line, flush=True)

  def images(self, step: int, images: dict) -> None:
    if self.enabled:
      for name, image in images.items():
        self.writer.add_image(name, np.clip(image, 0.0, 1.0), step, dataformats="HWC")

  def close(self) -> None:
    if self.writer is not None:
      self.writer.close()


def _duration(seconds: float) -> str:
  seconds = int(round(seconds))
  if seconds >= 3600:
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m"
  return f"{seconds // 60}m{seconds % 60:02d}s"


def write_config(config, workdir: str) -> dict:
  """Checks a resumed workdir's config, then saves this run's resolved config as workdir/config.json."""
  resolved = json.loads(config.to_json_best_effort())
  checkpoints.check_compatible(workdir, resolved)
  checkpoints.write_config(workdir, resolved)  # process 0; local paths or gs://
  return resolved


def train_and_evaluate(config, workdir: str) -> dict:
  """Trains (resuming from workdir's newest checkpoint), evaluates the held-out views, renders the orbit.

  Returns the metrics written to workdir/eval/metrics.json, or None when a SIGTERM (preemption) stopped
  training: the state was then saved at a step all processes agreed on, and nothing else is done.
  """
  _check_config(config)
  s = setup(config)
  scene, mesh, model, near, far, state = s.scene, s.mesh, s.model, s.near, s.far, s.state
  write_config(config, workdir)
  tc = config.train

  ckpt = checkpoints.Checkpoints(workdir, config.checkpoint.every_steps, config.checkpoint.max_to_keep)
  try:
    start_step = 0
    if ckpt.latest_step() is not None:
      state, position = ckpt.restore(checkpoints.abstract_like(state))
      start_step = int(position["next_step"])
      logging.info("resumed from step %d", start_step)
    if jax.process_index() == 0:
      print(f"nerfpod: scene {scene.name} ({len(scene.splits['train'])} training views), "
            f"{jax.process_count()} process(es), {jax.device_count()} device(s), "
            f"steps {start_step}..{tc.num_steps}, {tc.batch_size} rays/step", flush=True)

    batches = s.batches(config, start_step)
    step_fn = s.train_step(config)
    schedule = learning_rate_schedule(tc)
    monitor = _Monitor(workdir, tc.num_steps, tc.batch_size)
    key = rays_key(tc.seed)
    preview = scene.split(config.eval.split)

    pending = None  # metrics of a log step, fetched only after the next step is dispatched
    preempted_at = None
    for step in range(start_step, tc.num_steps):
      local = next(batches)
      assert int(local.pop("step")) == step, "data pipeline out of step with training"
      state, metrics = step_fn(state, distributed.to_global(mesh, local), key)
      if pending is not None:
        monitor.scalars(pending[0], jax.device_get(pending[1]), float(schedule(pending[0] - 1)))
        pending = None
      done = step + 1
      if done % tc.log_every == 0 or done == tc.num_steps or step == start_step:
        pending = (done, metrics)
      ckpt.save(done, state, {"next_step": done})  # every checkpoint.every_steps, and when preempted
      if ckpt.reached_preemption(done):
        preempted_at = done
        break
      if tc.image_every and done % tc.image_every == 0:
        out = render.render_image(s.render_fn, state.params, mesh, preview.poses[0], preview.intrinsics,
                                  config.data.pixel_center, config.eval.chunk)
        monitor.images(done, {"preview/rgb": out["rgb"],
                              "preview/depth": evaluate.depth_image(out["depth"], near, far)[..., None]})
    if pending is not None:
      monitor.scalars(pending[0], jax.device_get(pending[1]), float(schedule(pending[0] - 1)))
    if preempted_at is not None:
      ckpt.close()  # waits until the step is on disk
      monitor.close()
      if jax.process_index() == 0:
        print(f"nerfpod: preempted: saved step {preempted_at} in {checkpoints.checkpoint_dir(workdir)} and "
              f"stopped; the same command resumes from there.", flush=True)
      return None
    final_step = int(jax.device_get(state.step))
    if ckpt.latest_step() != final_step:
      ckpt.save(final_step, state, {"next_step": final_step}, force=True)
  finally:
    ckpt.close()  # also on an exception: waits for a save under way, gives SIGTERM back

  result = evaluate.evaluate(config, scene, model, state.params, mesh, workdir, final_step,
                             writer=monitor.writer, render_fn=s.render_fn)
  if config.orbit.render_after_training:
    orbit.render_orbit(config, scene, model, state.params, workdir, final_step, writer=monitor.writer)
  monitor.close()
  return result


class Trained(NamedTuple):
  """A workdir's newest checkpoint restored onto this run's mesh: what evaluation and rendering start from."""
  scene: Any
  mesh: Any
  model: Any
  state: TrainState
  step: int


def load_trained(config, workdir: str) -> Trained:
  """The scene, mesh, model and newest checkpointed state of workdir, for --mode=eval and --mode=render."""
  if checkpoints.latest_step(workdir) is None:
    raise UserError(f"workdir {workdir} holds no checkpoint to evaluate or render; train first (--mode=train, "
                    f"the default) or pass the --workdir of a trained run.")
  checkpoints.check_compatible(workdir, json.loads(config.to_json_best_effort()))
  evaluate.check_config(config)
  s = setup(config)
  with checkpoints.Checkpoints(workdir, config.checkpoint.every_steps, config.checkpoint.max_to_keep,
                               read_only=True) as ckpt:
    state, _ = ckpt.restore(checkpoints.abstract_like(s.state))
  step = int(jax.device_get(state.step))
  if jax.process_index() == 0:
    print(f"nerfpod: restored step {step} of {workdir}", flush=True)
  return Trained(s.scene, s.mesh, s.model, state, step)
