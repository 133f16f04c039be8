"""The train step: step(state, batch, key) -> (state, metrics), sharded over the device mesh.

    make_train_step    the jitted step from its pieces (model, optimiser, mesh, ray bounds) and its Options
    field_loss, local_step, accumulate   its pieces: the one-field loss (_region_loss_fn: a region model's), one
                       device's share of the step, the micro-batches' gradient accumulation
    Options            the loss's settings, micro-batches and the backend's policy; Options.of(config, ...)
    measure_capacity, with_capacity, measure_for_tool   model.region_capacity=auto: the fraction measured on the
                       training rays (a run's, nerfpod train.train; a tool's, on a built-in scene)
    for_program        the step of a config's Components (runs and the pod tool)
    compile_fitted     compiled for Components' shapes, with train.microbatches=0 fitted to a memory budget
                       (fitted_capacity: a measured auto capacity's margin for the fitted micro-batch)
    start_compiling    a run's step compiled in a background thread while its state initialises
"""
import concurrent.futures
import copy
import dataclasses
import functools
import sys
import typing

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import PartitionSpec as P

from nerfpod import distributed, scenes, text
from nerfpod.run import compilation, components, train_state
from nerfpod.run.components import Components
from nerfpod.run.train_state import TrainState
from nerfpod.errors import UserError
from nerfpod.render.metrics import mse_to_psnr
from nerfpod.nerf import model as nerf_model
from nerfpod.nerf import encodings, regions, stepfun


def per_ray_uniforms(key, ray_ids, count: int):
  """(R, count) uniform numbers, ray i's drawn from fold_in(key, ray_ids[i]): the same for a ray whatever
  device or host renders it, so results do not depend on how the batch is split."""
  return jax.vmap(lambda i: jax.random.uniform(jax.random.fold_in(key, i), (count,)))(ray_ids)


def round_uniforms(key, ray_ids, count: int, single_jitter: bool = False):
  """A sampling round's numbers (R, count) (per_ray_uniforms); with `single_jitter` (train.single_jitter,
  nerfacto's) one number per ray in every column: each stratum offset alike, the round's samples evenly spaced
  in its CDF with one random shift."""
  if not single_jitter:
    return per_ray_uniforms(key, ray_ids, count)
  return jnp.broadcast_to(per_ray_uniforms(key, ray_ids, 1), (ray_ids.shape[0], count))


@dataclasses.dataclass(frozen=True)
class Options:
  """How the step trains, beyond its model and data: the loss's settings (train.random_background,
  train.interlevel_weight, train.distortion_weight), its micro-batches, and the backend's policy (the
  gradient mean's order, the update under a conditional, XLA's options). `of(comps, ...)` is the one
  mapping of a config's Components onto them; tests build their own."""
  random_background: bool = False
  microbatches: int = 1
  interlevel_weight: float = 1.0
  distortion_weight: float = 0.0
  ordered_mean: bool = True
  update_under_cond: bool | None = None  # None: compilation.update_under_cond() for JAX's backend
  compiler_options: dict | None = None
  grad_clip: float = 0.0  # model.regions > 1: the step clips the global gradient norm (make_optimizer(clip=False))
  # (start, end) steps of the hash grid's coarse-to-fine opening (train.coarse_to_fine as steps); (): off
  coarse_to_fine: tuple = ()
  # train.interlevel_blur: one box half-width per proposal round (Zip-NeRF's anti-aliased interlevel loss);
  # (): mip-NeRF 360's
  interlevel_blur: tuple = ()
  # train.proposal_anneal_steps: the proposal weights' exponent rises from 0 to 1 over these steps; 0: off
  proposal_anneal_steps: int = 0
  # train.single_jitter: one random offset per ray and round, shared by its strata (step.round_uniforms)
  single_jitter: bool = False
  # model.region_capacity (model.regions > 1): each region renders C = regions.capacity_rows(this, the device's
  # rays) rows, the rays whose segment meets it (a ray over capacity dropped whole); 0: every ray (dense). 'auto'
  # is resolved to a number before (with_capacity; Options.of measures it where the config still says 'auto')
  region_capacity: float = 0.0
  # model.region_split: J sample classes (regions.sample_classes), each with C_j rows from its fraction
  # (model.region_split_capacity, or region_capacity for every class); 0 or 1: one class, every sample
  region_split: int = 0
  region_split_capacity: tuple = ()

  def capacity_rows(self, rays: int):
    """The compacted step's rows per region for `rays` rays: C (an int), or with region_split a tuple of C_j, one
    per sample class; 0 dense."""
    if not self.region_capacity:
      return 0
    fractions = regions.class_capacities(self.region_capacity, self.region_split, self.region_split_capacity)
    if not fractions:
      return regions.capacity_rows(self.region_capacity, rays)
    return tuple(regions.capacity_rows(f, rays) for f in fractions)

  @classmethod
  def of(cls, comps: Components, microbatches: int, backend: str | None = None) -> "Options":
    """Those of `comps`' config (`backend`: what the gradient mean and the update are chosen for, default
    JAX's; the pod compile tool asks for 'tpu')."""
    config = comps.config
    tc = config.train
    capacity = config.model.region_capacity if config.model.regions > 1 else 0.0
    split_capacity = tuple(float(f) for f in config.model.region_split_capacity)
    if capacity == "auto":  # (a run resolves it first, and says so: nerfpod.run.train; so does nerfpod aot)
      if comps.scene is None:
        raise UserError(AUTO_WITHOUT_SCENE.format(kind=config.data.kind))
      measured = measure_capacity(config, comps.scene, comps.mesh, comps.model.partition, comps.near, comps.far)
      capacity, split_capacity = measured.fraction, measured.split_fractions
    return cls(tc.random_background, microbatches, tc.interlevel_weight, tc.distortion_weight,
               compilation.gradient_mean_is_ordered(config, backend), compilation.update_under_cond(backend),
               comps.compiler_options, grad_clip=tc.grad_clip if config.model.regions > 1 else 0.0,
               coarse_to_fine=tuple(round(f * tc.num_steps) for f in tc.coarse_to_fine),
               interlevel_blur=tuple(float(r) for r in tc.interlevel_blur),
               proposal_anneal_steps=int(tc.proposal_anneal_steps), single_jitter=bool(tc.single_jitter),
               region_capacity=float(capacity), region_split=int(config.model.region_split),
               region_split_capacity=split_capacity if int(config.model.region_split) > 1 else ())


# model.region_capacity=auto is measured on AUTO_RAYS training rays drawn with AUTO_SEED (regions.pixel_rays, as the
# batches are drawn): fixed, so that every process of a run, and every run of the same scene, measures the same.
AUTO_RAYS, AUTO_SEED = 65536, 0
AUTO_WITHOUT_SCENE = ("model.region_capacity=auto is measured on the scene's training rays, and this tool loads only "
                      "the built-in scenes (data.kind procedural or street), not data.kind={kind}; give a fraction "
                      "instead, e.g. the one a training run with auto measured (its first lines print it, its "
                      "workdir's config.json records it), or --config.model.region_capacity=0.75.")


def region_rows(config, mesh, microbatches: int | None = None) -> int:
  """R, the rays each region of a chip renders in one micro-batch: train.batch_size over the chips of the
  batch's axes, over `microbatches` (default train.microbatches; 0, fitted at start-up: taken as 1, the most rows
  there can be)."""
  count = config.train.microbatches if microbatches is None else microbatches
  return config.train.batch_size // distributed.batch_devices(mesh) // max(1, count)


@dataclasses.dataclass(frozen=True)
class MeasuredCapacity:
  """model.region_capacity=auto measured (measure_capacity): `counts` (K,) of the `rays` training rays drawn
  that meet each region, a chip's `rows` R, and the fraction F (regions.auto_fraction of the fullest share). With
  model.region_split=J, `class_counts` (K, J), the rays whose segment in each region is of each sample class,
  and `split_fractions`, F_j of each class's fullest share (F is then their largest)."""
  counts: tuple
  rays: int
  rows: int
  fraction: float
  class_counts: tuple = ()
  split_fractions: tuple = ()

  @property
  def capacity(self) -> int:
    return regions.capacity_rows(self.fraction, self.rows)

  def at_rows(self, rows: int) -> "MeasuredCapacity":
    """The same shares with the margin for a chip's `rows` rays (a fitted micro-batch's): F, and with classes
    F_j of each class's fullest share, F their largest (regions.auto_fraction)."""
    by_class = np.asarray(self.class_counts).reshape(len(self.counts), -1)  # (K, J), or (K, 0) without classes
    fractions = tuple(regions.auto_fraction(float(np.max(by_class[:, j])) / self.rays, rows)
                      for j in range(by_class.shape[1]))
    fraction = (max(fractions) if fractions else
                regions.auto_fraction(float(np.max(self.counts)) / self.rays, rows))
    return dataclasses.replace(self, rows=rows, fraction=fraction, split_fractions=fractions)

  def line(self) -> str:
    shares = np.asarray(self.counts) / self.rays
    fullest = int(np.argmax(shares))
    if self.split_fractions:
      classes = np.asarray(self.class_counts) / self.rays  # (K, J)
      parts = [f"class {j} (1/{2**j} of the samples): fullest share {classes[:, j].max():.3f}, F = {f:g}, "
               f"C = {regions.capacity_rows(f, self.rows)}" for j, f in enumerate(self.split_fractions)]
      return (f"model.region_capacity=auto: of {self.rays:,} training rays, the shares that meet regions 0 to "
              f"{len(shares) - 1} are {', '.join(f'{s:.3f}' for s in shares)}; split by their segments' sample "
              f"classes, each with a margin for a batch's spread over a chip's {self.rows} rays: "
              + "; ".join(parts) + " rows per region")
    margin = self.fraction - shares[fullest]
    return (f"model.region_capacity=auto: of {self.rays:,} training rays, the shares that meet regions 0 to "
            f"{len(shares) - 1} are {', '.join(f'{s:.3f}' for s in shares)}; the fullest (region {fullest}, "
            f"{shares[fullest]:.3f}) plus {margin:.3f} for a batch's spread over a chip's {self.rows} rays gives "
            f"F = {self.fraction:g}: C = {self.capacity} of {self.rows} rows per region")


def measure_capacity(config, scene, mesh, partition: regions.Partition, near: float, far: float) -> MeasuredCapacity:
  """model.region_capacity=auto on `scene`: AUTO_RAYS of its training rays (regions.pixel_rays: every host's frames,
  whatever data.shards holds), the share whose segment in each region of `partition` is not empty, cut as the step
  cuts them (regions.segment_counts: [near, far] clipped to the hash grid's box where the field is one), and F from
  the fullest share for a chip's R rays of `mesh` (region_rows, regions.auto_fraction); with model.region_split,
  per sample class."""
  split = scene.split("train")
  origins, directions = regions.pixel_rays(np.asarray(split.poses), split.cameras, AUTO_RAYS, AUTO_SEED,
                                           config.data.pixel_center)
  bound = config.model.hashgrid.bound if config.model.field == "hashgrid" else None
  classes = int(config.model.region_split)
  rows = region_rows(config, mesh)
  if classes <= 1:
    counts = regions.segment_counts(origins, directions, near, far, partition, bound)
    return MeasuredCapacity(tuple(int(c) for c in counts), AUTO_RAYS, 0, 0.0).at_rows(rows)
  by_class = regions.segment_counts(origins, directions, near, far, partition, bound, classes=classes,
                                    spacing=config.render.spacing)
  return MeasuredCapacity(tuple(int(c) for c in by_class.sum(axis=1)), AUTO_RAYS, 0, 0.0,
                          tuple(tuple(int(c) for c in row) for row in by_class)).at_rows(rows)


def with_capacity(config, fraction: float, split_fractions: tuple = ()):
  """A copy of `config` whose model.region_capacity is `fraction` (and model.region_split_capacity
  `split_fractions`, where given): config.json then records them."""
  out = copy.deepcopy(config)
  out.model.region_capacity = float(fraction)
  if split_fractions:
    out.model.region_split_capacity = tuple(float(f) for f in split_fractions)
  return out


def measure_for_tool(config, mesh) -> MeasuredCapacity | None:
  """model.region_capacity=auto measured (measure_capacity, its line on stderr) for a tool that has no run's
  scene (nerfpod aot): a built-in scene (no download) is made here; another is refused in one sentence asking
  for a fraction. None for any other config."""
  if config.model.regions == 1 or config.model.region_capacity != "auto":
    return None
  loader = scenes.LOADERS.get(config.data.kind)
  if loader is None or loader.needs_path:
    raise UserError(AUTO_WITHOUT_SCENE.format(kind=config.data.kind))
  scene = scenes.cameras_only(config.data)  # (the measurement reads the cameras only: no frame traced)
  near, far = components.ray_bounds(config, scene)
  measured = measure_capacity(config, scene, mesh, components.region_cut(config, scene), near, far)
  print(f"nerfpod: {measured.line()} (on data.kind={config.data.kind})", file=sys.stderr, flush=True)
  return measured


def make_train_step(model, optimizer, mesh, near: float, far: float, background, options: Options = Options()):
  """The jitted step(state, batch, key) -> (state, metrics); batch sharded over the mesh, state donated.

  Each device renders its rays and takes gradients of its mean squared error; gradients and losses are
  averaged across devices (every device holds the same number of rays, so that is the global mean) and every
  device applies the same Adam update to its replica of the parameters. With `ordered_mean` the mean is
  summed in an order that does not depend on the processes (distributed.ordered_mean: any topology of the
  same device count gives the same bits, at log2(N) exchanges of the gradients); without, it is one
  all-reduce (jax.lax.pmean), whose summation order is the collective's own
  (compilation.gradient_mean_is_ordered). A step whose loss or gradient is not finite leaves the state as it
  was: with `update_under_cond` (None: compilation.update_under_cond for JAX's backend) its update is not
  even computed, without it the old state is selected after the update.
  With `random_background` and batches that carry alpha, each ray's target is recomposited on a random
  colour (Instant-NGP's trick): empty space must then be transparent rather than painted the background
  colour, which gives clean depth, opacity and disparity.
  With `microbatches` > 1, each device's rays are processed in that many sequential slices whose gradients
  are averaged (gradient accumulation): the same result in a fraction of the activation memory.
  `compiler_options`: XLA options to compile the step with (compilation.compiler_options).
  With proposal sampling (model.proposal_samples), the loss adds `interlevel_weight` times mip-NeRF 360's
  interlevel loss of every proposal round (with `interlevel_blur`, one radius per round: Zip-NeRF's
  anti-aliased form, stepfun.blurred_interlevel_loss) and `distortion_weight` times the distortion loss of the
  NeRF's weights; both are also returned as metrics.
  With `proposal_anneal_steps`, the proposal weights are raised to stepfun.anneal_exponent of the state's step
  before each resampling (nerfacto's annealing); evaluation resamples them as they are.
  With proposals, the metrics also carry the diagnostics of proposal_diagnostics (a collapse of the NeRF's
  sampling window shows there before it costs a run: docs/training.md).
  With `coarse_to_fine` (start, end) steps, the NeRF field's hash-grid levels open one after another between
  them (encodings.coarse_to_fine_weights of the state's step; BARF's schedule); the held-out views, the orbit
  and the exports render every level whole, as the step does from `end` on.
  """
  background = jnp.asarray(background, jnp.float32)
  # The options as this step applies them: the backend's policy resolved, and the global norm clipped by the
  # step only where the optimiser does not (model.regions > 1: make_optimizer(clip=False)).
  options = dataclasses.replace(
      options, grad_clip=options.grad_clip if model.regions > 1 else 0.0,
      update_under_cond=(compilation.update_under_cond() if options.update_under_cond is None
                         else options.update_under_cond))
  if model.regions > 1:
    loss_fn = _region_loss_fn(model, mesh, near, far, background, options)
    reductions = _region_reductions(mesh, options.ordered_mean)
  else:
    loss_fn = functools.partial(field_loss, model, near, far, background, options)
    reductions = _data_reductions(mesh, options.ordered_mean)
  step = functools.partial(local_step, optimizer, options, jax.value_and_grad(loss_fn, has_aux=True), reductions)
  state_spec = train_state.state_specs(model, optimizer, mesh)  # P() but for a region model's region axis
  step = jax.shard_map(step, mesh=mesh, in_specs=(state_spec, distributed.batch_spec(mesh), P()),
                       out_specs=(state_spec, P()))
  return jax.jit(step, donate_argnums=0, compiler_options=options.compiler_options)


def field_loss(model, near: float, far: float, background, options: Options, params, batch, key, step):
  """(loss, (mses, extra)) of the one-field model (model.regions == 1) on this device's rays: the sum of its
  levels' mean squared errors (`mses`, one per level, coarse first) and, with proposal sampling, the weighted
  interlevel and distortion losses (`extra`, with proposal_diagnostics). `step`: the state's, for the
  coarse-to-fine opening and the proposal weights' annealing."""
  # Round i's numbers come from stream i (0: coarse/stratified, 1: fine), skipping 2 (the backgrounds).
  uniforms = [round_uniforms(jax.random.fold_in(key, i if i < 2 else i + 1), batch["ray_ids"], count,
                             options.single_jitter)
              for i, count in enumerate(model.sample_counts())]
  target, ray_background = _targets(batch, key, background, options)
  levels = model.apply(params, batch["origins"], batch["directions"], near, far, ray_background, *uniforms,
                       frames=batch.get("frame"),  # per-frame appearance and pose corrections, where on
                       opened=_opened(model, options, step), anneal=_anneal(options, step))
  mses = jnp.stack([jnp.mean((level["rgb"] - target)**2) for level in levels])
  loss = jnp.sum(mses)
  extra = {}
  final = levels[-1]
  if "proposals" in final:
    # The proposals learn to bound the NeRF's weights (a fixed target for them: no gradient into the NeRF
    # from this loss); the photometric loss reaches only the NeRF (sample positions carry no gradient).
    target_weights = jax.lax.stop_gradient(final["weights"])
    radii = options.interlevel_blur or (None,) * len(final["proposals"])  # None: mip-NeRF 360's loss
    extra["interlevel"] = sum(jnp.mean(stepfun.interlevel_loss(final["s_edges"], target_weights, p["s_edges"],
                                                               p["weights"], radius))
                              for radius, p in zip(radii, final["proposals"]))
    extra["distortion"] = jnp.mean(stepfun.distortion_loss(final["s_edges"], final["weights"]))
    loss = loss + options.interlevel_weight * extra["interlevel"] + options.distortion_weight * extra["distortion"]
    extra.update(proposal_diagnostics(final))
  return loss, (mses, extra)


def _targets(batch, key, background, options: Options):
  """(target colours, background colours) of the batch's rays: the batch's and the scene's background, or
  with `random_background` and a batch that carries alpha, each ray recomposited on a random colour (stream
  2 of `key`)."""
  target, ray_background = batch["rgb"], background
  if options.random_background and "alpha" in batch:
    ray_background = per_ray_uniforms(jax.random.fold_in(key, 2), batch["ray_ids"], 3)
    target = target + (1.0 - batch["alpha"][:, None]) * (ray_background - background)
  return target, ray_background


def _opened(model, options: Options, step):
  """The NeRF field's hash-grid level weights at `step` (options.coarse_to_fine), None where it is off."""
  if not options.coarse_to_fine:
    return None
  return encodings.coarse_to_fine_weights(step, *options.coarse_to_fine, model.model_config.hashgrid.num_levels)


class Reductions(typing.NamedTuple):
  """How the step's values cross devices: `vary` makes the replicated parameters device-varying (each device
  then differentiates its own rays' loss; differentiating the replicated value directly would make shard_map
  sum the cotangents across devices already, and the mean would then give N times the mean), `reduce` takes
  the mean of (grads, loss, mses, extra) over the devices, `norm` is the gradients' global norm."""
  vary: typing.Callable
  reduce: typing.Callable
  norm: typing.Callable


def _data_reductions(mesh, ordered_mean: bool) -> Reductions:
  """The one-field step's Reductions over every axis of the mesh: DATA_AXIS on one slice; (SLICE_AXIS,
  DATA_AXIS) on several, where the mean runs within each slice (ICI) and then across the slices (DCN): see
  distributed.ordered_mean, and for the all-reduce (not `ordered_mean`), docs/scale.md#multi-slice."""
  axes = distributed.batch_axes(mesh)
  axis_sizes = tuple(mesh.shape[name] for name in mesh.axis_names)

  def reduce(tree):
    if ordered_mean:
      return distributed.ordered_mean(tree, mesh.axis_names, axis_sizes)
    return jax.lax.pmean(tree, axes)

  return Reductions(lambda params: jax.lax.pcast(params, axes, to="varying"), reduce, optax.tree.norm)


def accumulate(value_and_grad, microbatches: int, params, batch, key, step):
  """((loss, aux), grads) of `value_and_grad` for the mean over this device's rays, in `microbatches`
  sequential slices whose values and gradients are averaged (one call where it is 1)."""
  if microbatches == 1:
    return value_and_grad(params, batch, key, step)
  slices = jax.tree.map(lambda x: x.reshape((microbatches, -1) + x.shape[1:]), batch)
  def body(total, micro):
    value, grads = value_and_grad(params, micro, key, step)
    return jax.tree.map(lambda a, b: a + b / microbatches, total, (value, grads)), None
  zeros = jax.tree.map(jnp.zeros_like, jax.eval_shape(value_and_grad, params,
                                                      jax.tree.map(lambda x: x[0], slices), key, step))
  return jax.lax.scan(body, zeros, slices)[0]


def local_step(optimizer, options: Options, value_and_grad, reductions: Reductions, state: TrainState, batch, key):
  """One device's share of the step (make_train_step's shard_map of it, whose `options` are resolved):
  gradients of its rays' loss (`value_and_grad`, of the device-varying parameters), their mean over the
  devices (`reductions`), and the update where the loss and gradients are finite."""
  key = jax.random.fold_in(key, state.step)
  params = reductions.vary(state.params)
  (loss, (mses, extra)), grads = accumulate(value_and_grad, options.microbatches, params, batch, key, state.step)
  grads, loss, mses, extra = reductions.reduce((grads, loss, mses, extra))
  # A non-finite loss or gradient never reaches the state: the step is skipped (the parameters and Adam's
  # moments and count stay as they were; the data moves on) and counted in metrics["skipped"]. The test is
  # read before the update, off the loss and the gradients' global norm (finite only where every gradient
  # and the sum of their squares are): the update then takes one pass over the parameters and moments
  # (under a conditional, or fused with the select), where a test of the new state would take three. A
  # finite gradient gives a finite update (Adam's eps > 0; the sum of squares bounds the second moment),
  # so the state stays finite; checkpoints.Checkpoints.save checks it again before any save.
  grad_norm = reductions.norm(grads)
  finite = jnp.isfinite(loss) & jnp.isfinite(grad_norm)
  if options.grad_clip > 0:  # optax.clip_by_global_norm's, on every region's norm
    grads = jax.tree.map(lambda g: jnp.where(grad_norm < options.grad_clip, g,
                                             g / grad_norm.astype(g.dtype) * options.grad_clip), grads)
  params, opt_state = _update_if(finite, optimizer, options.update_under_cond,
                                 (grads, state.params, state.opt_state))
  metrics = {"loss": loss, "mse": mses[-1], "psnr": mse_to_psnr(mses[-1]),
             "psnr_coarse": mse_to_psnr(mses[0]), "grad_norm": grad_norm,
             "skipped": 1 - finite.astype(jnp.int32), **extra}
  return TrainState(step=state.step + 1, params=params, opt_state=opt_state), metrics


def _update_if(finite, optimizer, under_cond: bool, operands):
  """(params, opt_state) after `optimizer`'s update of operands (grads, params, opt_state) where `finite`,
  else as they were: with `under_cond` the update is not even computed (jax.lax.cond), without it the old
  values are selected after the update."""
  update = functools.partial(_update, optimizer)
  if under_cond:
    return jax.lax.cond(finite, update, lambda operands: operands[1:], operands)
  return jax.tree.map(lambda new, old: jnp.where(finite, new, old), update(operands), operands[1:])


def _update(optimizer, operands):
  """(params, opt_state) after `optimizer`'s update of operands (grads, params, opt_state)."""
  grads, params, opt_state = operands
  updates, opt_state = optimizer.update(grads, opt_state, params)
  return optax.apply_updates(params, updates), opt_state


def _anneal(options: Options, step):
  """The proposal weights' exponent at `step` (train.proposal_anneal_steps), None where there is no annealing."""
  return stepfun.anneal_exponent(step, options.proposal_anneal_steps) if options.proposal_anneal_steps else None


# A proposal interval holding more than this share of its ray's proposal weight counts as heavy.
HEAVY_SHARE = 0.99


def proposal_diagnostics(final) -> dict:
  """What shows a proposal sampler collapsing, from a proposal rendering (NeRF.__call__'s last level), each a
  mean over the rays (metrics train/window, ...: docs/training.md):
  window, the span in normalised distance s of the NeRF's sampling window (its intervals' first to last edge:
  1 for the whole ray); heavy, the share of rays whose last proposal round puts more than HEAVY_SHARE of its
  weight in one interval; saturated and proposal_saturated, the share of the NeRF's and of the last proposal's
  samples whose density sits at the clamp (fields.DENSITY_CLAMP). A trapped sampler (stepfun.resampling_weights)
  has a window of a few hundredths, most rays heavy, and interlevel and distortion terms of about 0.
  The values are read through an optimisation barrier: without it XLA fuses these reductions with the
  rendering's own and the step's float bits change (the default job held out 28.76 dB instead of its 28.82)."""
  last = final["proposals"][-1]
  s_edges, weights, saturated, proposal_saturated = jax.lax.optimization_barrier(jax.lax.stop_gradient(
      (final["s_edges"], last["weights"], final["saturated"], last["saturated"])))
  total = jnp.sum(weights, axis=-1)
  heavy = jnp.max(weights, axis=-1) > HEAVY_SHARE * jnp.maximum(total, stepfun.EPS)
  return {"window": jnp.mean(s_edges[..., -1] - s_edges[..., 0]),
          "heavy": jnp.mean(heavy.astype(jnp.float32)),
          "saturated": jnp.mean(saturated), "proposal_saturated": jnp.mean(proposal_saturated)}


def _region_loss_fn(model, mesh, near: float, far: float, background, options: Options):
  """loss_fn(params, batch, key, step) of a model of K regions (model.regions > 1) on `mesh`, whose region axis
  (of size K / L, or none: L = K) gives each device L regions: it renders each ray through its own regions
  (NeRF.render_partials), gathers every region's partial sums of its rays over the region axis and composites
  them in ray order (regions.composite_regions): the loss is the whole ray's, the same on every device of the
  region axis.

  The gather is invariant (distributed.gather_regions): its result is formally the same on every device of
  the axis, and its transpose hands each device the cotangent of its own regions' sums only (a slice of the
  one invariant cotangent). jax.lax.all_gather's result would vary over the axis, its transpose
  (psum_scatter) would sum the K identical cotangents of the K devices' identical losses, and every gradient
  would come out K times too large. The interlevel loss is per segment (regions.interlevel_loss, each
  region's own histograms scaled by the NeRF's transmittance before its segment), its per-ray terms gathered
  the same way; the distortion loss is the whole ray's, from the gathered sums.

  With options.region_capacity (docs/scale.md, "Dispatch and capacity"), each region renders only its C rows
  (NeRF.render_partials' capacity: the rays whose segment meets it, in ray order, with the dense path's
  random numbers), put back into their rays as empty segments elsewhere, so the composite and the losses are
  the dense ones. A ray with a segment over capacity in any region is dropped whole: its flag rides the same
  gather, and it adds nothing to the mean squared error, interlevel and distortion losses (still the means over
  the whole batch, so that the loss does not depend on how the batch is split over devices).
  The metrics gain region_metrics' (for the dense path too)."""
  count = model.regions
  axis_size = distributed.num_regions(mesh)
  if count % axis_size:
    raise ValueError(f"model.regions={count} does not split over the mesh's region axis of {axis_size}")
  local = count // axis_size
  background = jnp.asarray(background, jnp.float32)
  # The losses' and metrics' means are taken over the micro-batches and the batch's devices: a count of the
  # whole step is reported as (count of these rays) x (how many such shares make the step).
  shares = options.microbatches * distributed.batch_devices(mesh)
  field_samples = sum(model.sample_counts())  # a ray's field evaluations in one region: proposals' and NeRF's
  split_by = model.model_config.region_split_by

  def gather(x):  # (L, R, ...) on each device -> (K, R, ...), the same on every device of the region axis
    return x if axis_size == 1 else distributed.gather_regions(x)

  def loss_fn(params, batch, key, step):  # (the schema refuses train.coarse_to_fine with regions)
    first = jax.lax.axis_index(distributed.REGION_AXIS) * local if axis_size > 1 else 0
    ids = first + jnp.arange(local)
    # Region r's numbers of round i: stream i (as the one-field model's), then r folded in.
    def region_uniforms(stream, n):
      stream_key = jax.random.fold_in(key, stream)
      return jax.vmap(lambda r: round_uniforms(jax.random.fold_in(stream_key, r), batch["ray_ids"], n,
                                               options.single_jitter))(ids)
    uniforms = [region_uniforms(i if i < 2 else i + 1, n) for i, n in enumerate(model.sample_counts())]
    target, ray_background = _targets(batch, key, background, options)
    rays = batch["origins"].shape[0]
    capacity = options.capacity_rows(rays)  # C, or per sample class (model.region_split); 0 dense
    partials, own = model.apply(params, batch["origins"], batch["directions"], near, far, ids, tuple(uniforms),
                                frames=batch.get("frame"), anneal=_anneal(options, step), capacity=capacity,
                                gather=gather, method="render_partials")
    # (Compacted) whether each ray's segment in each region found no row: riding the partial sums' gather, so
    # every device of the region axis knows every region's, and drops the ray whole.
    flags = {"dropped": jax.lax.stop_gradient(own["dropped"].astype(jnp.float32))} if capacity else {}
    gathered = gather(partials | flags)
    out = regions.composite_regions(gathered, ray_background)
    # Each region's rays with a segment in it (K,): the devices' own, summed over the region axis (K numbers,
    # apart from the gather, whose traffic stays the dense step's).
    counts = jax.lax.stop_gradient(jnp.sum(own["present"], axis=1, dtype=jnp.float32))
    # (Split) the same per sample class (K, J)
    class_counts = (jnp.stack([jnp.sum(d.present_LxR, axis=1, dtype=jnp.float32) for d in own["dispatches"]],
                              axis=1) if isinstance(capacity, tuple) else None)
    # (Split by weights) the segments a full class of the NeRF round handed down to fewer samples, all regions'
    downgraded = (jnp.sum(own["downgraded"], dtype=jnp.float32) if "downgraded" in own else None)
    if axis_size > 1:
      counts = jax.lax.psum(jax.lax.dynamic_update_slice_in_dim(jnp.zeros(count), counts, first, axis=0),
                            distributed.REGION_AXIS)
      if downgraded is not None:
        downgraded = jax.lax.psum(downgraded, distributed.REGION_AXIS)
      if class_counts is not None:
        class_counts = jax.lax.psum(jax.lax.dynamic_update_slice_in_dim(
            jnp.zeros((count,) + class_counts.shape[1:]), class_counts, first, axis=0), distributed.REGION_AXIS)
    class_counts = None if class_counts is None else jax.lax.stop_gradient(class_counts)
    mean = jnp.mean
    if capacity:  # a dropped ray adds 0 to the means over the batch (where none is dropped: the dense means' bits)
      kept = jnp.max(gathered["dropped"], axis=0) == 0.0
      mean = lambda x: jnp.mean(jnp.where(kept.reshape(kept.shape + (1,) * (x.ndim - 1)), x, 0.0))  # noqa: E731
    mse = mean((out["rgb"] - target)**2)
    mses, loss = mse[None], mse
    extra = region_metrics(counts, rays, gathered.get("dropped"), capacity, local, field_samples,
                           options.microbatches, shares, class_counts,
                           regions.split_evals(model.sample_counts(), capacity, split_by)
                           if isinstance(capacity, tuple) else None)
    if downgraded is not None:  # (a share of the step's segments: the mean over the shares is the step's)
      extra["regions/downgraded"] = jax.lax.stop_gradient(downgraded) / jnp.maximum(jnp.sum(counts), 1.0)
    if model.proposal_samples:
      prefix = jax.lax.stop_gradient(jax.lax.dynamic_slice_in_dim(out["prefix"], first, local, axis=0))
      radii = options.interlevel_blur or (None,) * len(model.proposal_samples)  # None: mip-NeRF 360's loss

      def segment_loss(rendered, prefix):  # (L, R), or (L, C) rows
        weights = jax.lax.stop_gradient(rendered["weights"])
        return sum(jax.vmap(functools.partial(regions.interlevel_loss, radius=radius))(
                       rendered["s_edges"], weights, p["s_edges"], p["weights"], prefix)
                   for radius, p in zip(radii, rendered["proposals"]))

      if not capacity:
        per_ray = segment_loss(own, prefix)
      else:  # per row (each row's own ray's prefix), back into the rays: an empty segment's term is 0
        dispatches = [r["dispatch"] for r in own["classes"]]
        per_ray = regions.scatter_classes(
            [segment_loss(r, regions.gather_rows(prefix, r["dispatch"], per_region=True)) for r in own["classes"]],
            dispatches, 0.0)
      extra["interlevel"] = mean(jnp.sum(gather(per_ray), axis=0))
      extra["distortion"] = mean(out["distortion"])
      loss = loss + options.interlevel_weight * extra["interlevel"] + options.distortion_weight * extra["distortion"]
    return loss, (mses, extra)

  return loss_fn


def region_metrics(counts_K, rays: int, dropped_KxR, capacity, local: int, field_samples,
                   microbatches: int, shares: int, class_counts_KxJ=None, evals: int | None = None) -> dict:
  """A region step's visibility (docs/scale.md, "Dispatch and capacity") of these `rays` rays (one device's,
  one micro-batch's): `counts` (K,), how many of them have a segment in each region; `dropped` (K, R) or None
  (dense), whether each ray's segment in each region found no row within `capacity` C (0: dense). The step's
  mean over its `shares` (micro-batches x the batch's devices) gives:
  regions/segments_per_ray      the mean count of non-empty segments per ray
  regions/fill                  the fullest region's rays with a segment in it / C (/ R when dense); over 1: overflow
  regions/dropped               the rays dropped in the step (each reported x shares, so the mean is the sum)
  regions/field_evals_per_chip  the rows a chip renders in the step x field samples per ray (`field_samples`)
  regions/capacity              C, rows per region (compacted only)
  With model.region_split, `capacity` is per sample class (C_j), `class_counts_KxJ` each region's rays per class
  and `evals` a region's rows' field evaluations (regions.split_evals; `field_samples` unused): fill is the
  fullest (region, class)'s count over its C_j, and capacity is the rows of every class.
  regions/downgraded (model.region_split_by=weights, added by the step) the share of the segments that a full
  class of the NeRF round handed down to fewer samples"""
  if isinstance(capacity, tuple):  # model.region_split: per sample class, its rows C_j
    fill = jnp.max(class_counts_KxJ / jnp.asarray(capacity, jnp.float32))
    capacity = sum(capacity)
  else:
    rows = capacity or rays
    fill, evals = jnp.max(counts_K) / rows, rows * field_samples
  out = {"regions/segments_per_ray": jnp.sum(counts_K) / rays,
         "regions/fill": fill,
         "regions/dropped": (jnp.zeros(()) if dropped_KxR is None else
                             jnp.sum(jnp.max(dropped_KxR, axis=0)) * float(shares)),
         "regions/field_evals_per_chip": jnp.float32(local * evals * microbatches)}
  if capacity:
    out["regions/capacity"] = jnp.float32(capacity)
  return out


def _region_reductions(mesh, ordered_mean: bool) -> Reductions:
  """The region step's Reductions: `vary` makes the parameters device-varying where the gradient
  of each device's own loss is wanted (a region's over the batch's axes: they already vary over the region
  axis; the replicated ones, per-frame tables, over the region axis too); `reduce` sums the replicated
  parameters' gradients over the region axis (each device's holds its own regions' part) and takes the mean
  of every gradient and metric over the batch's axes only (a region's gradients never leave its devices of
  the region axis); `norm`, the global norm of the gradients of every region."""
  axes = distributed.batch_axes(mesh)
  names = (axes,) if isinstance(axes, str) else tuple(axes)
  sizes = distributed.batch_axis_sizes(mesh)
  with_regions = distributed.num_regions(mesh) > 1
  region = (distributed.REGION_AXIS,) if with_regions else ()

  def vary(params):
    return jax.tree_util.tree_map_with_path(
        lambda path, x: jax.lax.pcast(x, names if nerf_model.in_region(path) or not with_regions
                                      else names + region, to="varying"), params)

  def mean(tree):
    if ordered_mean:
      return distributed.ordered_mean(tree, names, sizes)
    return jax.lax.pmean(tree, axes)

  def reduce(tree):
    grads, *rest = tree
    if not with_regions:
      return mean(tree)
    # Two means: ordered_mean packs a tree's leaves into one vector, which must not mix the region fields'
    # gradients (varying over the region axis) with values the same on all of it.
    paths, treedef = jax.tree_util.tree_flatten_with_path(grads)
    own = [nerf_model.in_region(path) for path, _ in paths]
    sharded = mean([g for (_, g), o in zip(paths, own) if o])
    shared, *rest = mean(([jax.lax.psum(g, distributed.REGION_AXIS) for (_, g), o in zip(paths, own) if not o],
                          *rest))
    sharded, shared = iter(sharded), iter(shared)
    return (jax.tree.unflatten(treedef, [next(sharded) if o else next(shared) for o in own]), *rest)

  def norm(grads):
    if not with_regions:
      return optax.tree.norm(grads)
    squares = jax.tree_util.tree_map_with_path(
        lambda path, g: (jnp.sum(jnp.square(g)), nerf_model.in_region(path)), grads,
        is_leaf=lambda x: isinstance(x, jax.Array))
    pairs = jax.tree.leaves(squares, is_leaf=lambda x: isinstance(x, tuple))
    sharded = sum((s for s, own in pairs if own), jnp.zeros(()))
    shared = sum((s for s, own in pairs if not own), jnp.zeros(()))
    return jnp.sqrt(jax.lax.psum(sharded, distributed.REGION_AXIS) + shared)

  return Reductions(vary, reduce, norm)


def for_program(comps: Components, microbatches: int, backend: str | None = None):
  """The jitted train step of `comps` with `microbatches` micro-batches (`backend`: Options.of's)."""
  return make_train_step(comps.model, comps.optimizer, comps.mesh, comps.near, comps.far, comps.background,
                         Options.of(comps, microbatches, backend))


def fitted_capacity(comps: Components, microbatches: int) -> Components:
  """`comps` for a step of `microbatches` micro-batches: where the run measured model.region_capacity=auto
  (comps.capacity_measured) for a chip's whole share of rays (train.microbatches=0), F (and F_j) with the margin
  for one micro-batch's rays (MeasuredCapacity.at_rows), which a smaller draw needs wider; else `comps` itself."""
  measured = comps.capacity_measured
  if measured is None or microbatches <= 1:
    return comps
  rows = region_rows(comps.config, comps.mesh, microbatches)
  if rows == measured.rows:
    return comps
  refit = measured.at_rows(rows)
  return dataclasses.replace(comps, config=with_capacity(comps.config, refit.fraction, refit.split_fractions),
                             capacity_measured=refit)


def compile_fitted(program: Components, key, budget_bytes: int, backend: str | None = None):
  """(micro-batches, compiled step, its bytes per device by XLA's analysis) for `program`'s state and batch
  shapes and `key` (a key, or its ShapeDtypeStruct). With train.microbatches=0: the fewest micro-batches
  whose step fits `budget_bytes` per device (compilation.fewest_microbatches), the compiled step being the
  very one compiled while fitting (for a measured auto capacity, with its margin for that count's micro-batch:
  fitted_capacity); a count XLA refuses to compile for lack of device memory counts as over the budget. Called
  with arguments of other shapes or placements, the compiled step raises instead of recompiling."""
  compiled, refused = {}, {}

  def compile_with(count):
    fitted = fitted_capacity(program, count)
    lowered = for_program(fitted, count, backend).lower(fitted.state_shapes, fitted.batch_shapes, key)
    try:
      compiled[count] = lowered.compile()
    except jax.errors.JaxRuntimeError as e:
      if tc.microbatches or "RESOURCE_EXHAUSTED" not in str(e):
        raise
      refused[count] = e  # too large for the device even to compile: over budget, try more micro-batches
      return 2 * budget_bytes + 1
    return compilation.step_memory_bytes(compiled[count])

  tc = program.config.train
  if tc.microbatches:
    need = compile_with(tc.microbatches)
    return tc.microbatches, compiled[tc.microbatches], need
  per_device = tc.batch_size // distributed.batch_devices(program.mesh)
  count, need = compilation.fewest_microbatches(per_device, budget_bytes, compile_with)
  if count in refused:  # even the most micro-batches there can be do not compile
    raise refused[count]
  return count, compiled[count], need


class ForRun(typing.NamedTuple):
  """compile_for_run's: the compiled step, and the components it was compiled for (a measured auto capacity
  fitted to its micro-batches: fitted_capacity; the config that config.json records and the drop watch reads)."""
  step: typing.Any
  comps: Components


def compile_for_run(comps: Components) -> ForRun:
  """A run's train step compiled ahead of time for its shapes, micro-batches fitted to this process's memory
  budget (compilation.memory_budget_bytes) where train.microbatches=0, which process 0 reports (and, where that
  changed a measured auto capacity, its fractions)."""
  budget = compilation.memory_budget_bytes(comps.config)
  count, compiled, need = compile_fitted(comps, train_state.rays_key(comps.config.train.seed, comps.mesh), budget)
  capacity = compilation.device_memory_bytes()
  if need is not None and need > capacity:  # not a budget: what the device has (fitted ones are said below)
    tc = comps.config.train
    per_device = tc.batch_size // distributed.batch_devices(comps.mesh)
    more = (f"set --config.train.microbatches=0 (the fewest that fit, found at start-up) or more than {count}, "
            f"or a smaller --config.train.batch_size" if tc.microbatches else
            "set a smaller --config.train.batch_size")
    raise UserError(f"the train step of train.batch_size={tc.batch_size} ({per_device} rays per device) in "
                    f"{count} micro-batch(es) needs {text.byte_size(need)} per device by XLA's analysis, "
                    f"more than the {text.byte_size(capacity)} a device has; {more}.")
  if comps.config.train.microbatches == 0 and jax.process_index() == 0:
    fits = "fits" if need is None or need <= budget else "is the most there can be; it does not fit"
    shown = "unknown" if need is None else f"{need / 2**20:,.1f} MiB"
    per_device = comps.config.train.batch_size // distributed.batch_devices(comps.mesh)
    print(f"nerfpod: train.microbatches=0: {count} micro-batch(es) of {per_device // count} rays per device "
          f"({shown} per device by XLA's analysis) {fits} the budget of {budget / 2**20:,.1f} MiB per device",
          flush=True)
  fitted = fitted_capacity(comps, count)
  if fitted is not comps and jax.process_index() == 0:
    print(f"nerfpod: {fitted.capacity_measured.line()} (its margin for one of the {count} micro-batches)",
          flush=True)
  return ForRun(compiled, fitted)


def start_compiling(comps: Components) -> concurrent.futures.Future:
  """compile_for_run in a background thread, whose future is returned: XLA compiles without holding
  Python's lock, so the state's initialisation (itself a compilation) or restore overlaps the step's
  compilation, seconds off every start on a CPU. Tracing and lowering take the lock for a moment."""
  pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="nerfpod-compile")
  future = pool.submit(compile_for_run, comps)
  pool.shutdown(wait=False)  # the thread ends with its one task
  return future
