"""The train state and what makes it: the optimiser and its learning-rate schedule, the initial parameters,
the shapes a restore fills, and the streams of randomness.

    TrainState              step, params, opt_state (a flax struct: what checkpoints hold)
    learning_rate_schedule  warm-up, then log-linear decay (the original NeRF's)
    make_optimizer          Adam (and AdamW for pose corrections), after gradient clipping
    scale_by_sparse_adam    Adam that skips hash-table entries without a gradient (train.sparse_table_updates)
    scale_by_gated_adam     Adam whose steps wait for a gradient's mean to stand out of noise (train.pose_gate)
    initial_state           the state from the seed, laid over the mesh (state_shardings)
    state_shapes            its ShapeDtypeStructs, without computing anything
    state_specs             where each leaf lives: a region's fields on the region axis, the rest replicated
    rays_key                the rays' key, replicated over the mesh

Randomness is a function of (seed, what): the parameters and the rays draw from their own streams, folded
into the seed; the train step folds in the step on top.
"""
from typing import Any, NamedTuple

import flax
import jax
import jax.numpy as jnp
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from nerfpod import distributed
from nerfpod.nerf import model as nerf_model
from nerfpod.nerf import pose_correction

# Tags folded into the seed so that each use of randomness has its own stream.
_PARAMS_STREAM, _RAYS_STREAM = 0, 1


@flax.struct.dataclass
class TrainState:
  step: jax.Array  # scalar int32: optimiser steps taken
  params: Any
  opt_state: Any


def learning_rate_schedule(train_config, lr_init: float | None = None,
                           lr_final: float | None = None) -> optax.Schedule:
  """Linear warm-up to lr_init, then log-linear decay to lr_final at the last step (the original NeRF's);
  train.lr_init and train.lr_final unless given."""
  tc = train_config
  lr_init = tc.lr_init if lr_init is None else lr_init
  lr_final = tc.lr_final if lr_final is None else lr_final
  decay_steps = max(1, tc.num_steps - tc.lr_warmup_steps)
  decay = optax.exponential_decay(lr_init, decay_steps, lr_final / lr_init)
  if tc.lr_warmup_steps <= 0:
    return decay
  warmup = optax.linear_schedule(0.0, lr_init, tc.lr_warmup_steps)
  return optax.join_schedules([warmup, decay], [tc.lr_warmup_steps])


def _labels(tables: bool):
  """The parameters' labels for make_optimizer's multi_transform: 'pose' for the pose corrections, with `tables`
  'table' for the hash grids' level tables (nerf.encodings.HashGridEncoding's 'level_<l>' parameters), 'field'
  for every other parameter (appearance codes included)."""
  def label(path, _):
    keys = [getattr(k, "key", None) for k in path]
    if pose_correction.PARAM in keys:
      return "pose"
    if tables and len(keys) >= 2 and keys[-2] == "grid" and str(keys[-1]).startswith("level_"):
      return "table"
    return "field"
  return lambda params: jax.tree_util.tree_map_with_path(label, params)


class SparseAdamState(NamedTuple):
  count: jax.Array  # scalar int32: steps taken, for the bias correction (as optax's Adam)
  mu: Any
  nu: Any


def scale_by_sparse_adam(b1: float, b2: float, eps: float) -> optax.GradientTransformation:
  """Adam that skips hash-table entries without a gradient (Instant-NGP, whose tiny-cuda-nn Adam skips
  non-matrix parameters whose gradient is exactly zero; TensorFlow's LazyAdam): where no sample of the batch
  touched a row, its entries' moments and values stay as they were. Dense Adam would keep moving an entry seen
  once along its decaying momentum for tens of steps (about ten times the one step this gives it, at b1 =
  0.9): in rarely seen space, where floaters form. The bias correction is the global step's, as optax's
  Adam, without state per entry (tiny-cuda-nn counts each entry's own steps: at b2 = 0.99 an entry first
  touched late takes the same first step either way, and the cup and the fox measured alike with both); on
  entries with a gradient at every step it is optax.scale_by_adam's update."""
  def init(params):
    zeros = lambda: jax.tree.map(lambda p: jnp.zeros(p.shape, jnp.float32), params)  # noqa: E731
    return SparseAdamState(count=jnp.zeros((), jnp.int32), mu=zeros(), nu=zeros())

  def update(updates, state, params=None):
    del params
    count = optax.safe_int32_increment(state.count)
    t = count.astype(jnp.float32)
    correct1, correct2 = 1 - jnp.power(jnp.float32(b1), t), 1 - jnp.power(jnp.float32(b2), t)

    def entry(g, mu, nu):
      hit = g != 0
      mu = jnp.where(hit, b1 * mu + (1 - b1) * g, mu)
      nu = jnp.where(hit, b2 * nu + (1 - b2) * g * g, nu)
      step = (mu / correct1) / (jnp.sqrt(nu / correct2) + eps)
      return jnp.where(hit, step, 0.0).astype(g.dtype), mu, nu

    out = jax.tree.map(entry, updates, state.mu, state.nu)
    pick = lambda i: jax.tree.map(lambda _, o: o[i], updates, out)  # noqa: E731
    return pick(0), SparseAdamState(count=count, mu=pick(1), nu=pick(2))

  return optax.GradientTransformation(init, update)


def noise_variance(b1: float, t):
  """The variance of Adam's bias-corrected first moment after t steps of independent gradients of unit
  variance and zero mean: m_t = (1 - b1) sum_i b1^(t-i) g_i over (1 - b1^t) has variance
  (1 - b1) (1 + b1^t) / ((1 + b1) (1 - b1^t)); 1 at t = 1, (1 - b1) / (1 + b1) in the limit."""
  power = jnp.power(jnp.float32(b1), t)
  return (1 - b1) * (1 + power) / ((1 + b1) * (1 - power))


class GatedAdamState(NamedTuple):
  count: jax.Array  # scalar int32: steps taken, for the bias corrections
  mu: Any  # the first moment (decay b1)
  nu: Any  # the second moment of Adam's step (decay b2)
  sq: Any  # the second moment over the first moment's window (decay b1), for the gate


def scale_by_gated_adam(b1: float, b2: float, eps: float, threshold: float) -> optax.GradientTransformation:
  """Adam whose step of each entry is kept only as far as its gradient's mean stands out of noise
  (train.pose_gate). Over the first moment's window (decay b1, about 1 / (1 - b1) steps) m and s are the
  bias-corrected means of g and g^2, and z = m / sqrt(s c_t), c_t the variance of m for gradients of zero mean
  and unit variance (noise_variance). Where the gradient is noise of any size, z is about a standard normal
  (s estimates its variance); where it has a mean mu beside noise sigma, z is about mu / sqrt((mu^2 +
  sigma^2) c_t), never more than 1 / sqrt(c_t) (sqrt((1 + b1) / (1 - b1)) in the limit: 14.1 at b1 = 0.99,
  4.4 at 0.9, so a gate of 5 needs b1 > 0.92; at the first steps c_t is near 1 and the gate stays shut until
  the window holds enough gradients to tell). Adam's step m / (sqrt(v) + eps), v at decay b2, is scaled by
  max(0, 1 - threshold / |z|): 0 inside the threshold, continuous, up to 1 - threshold sqrt(c_t) for a
  gradient without noise (0.65 at b1 = 0.99 and 5). s is measured over m's own window, not Adam's longer
  one, so a gradient that keeps its sign while it shrinks (a correction nearing its answer) keeps its z.

  What it is for: Adam's normalised step moves an entry whose gradient is pure noise by about the learning
  rate times sqrt((1 - b1) / (1 + b1)) at every step, a random walk that nothing pulls back (the pose
  corrections of exact cameras, docs/results.md); gated at 5, such an entry almost never moves, while a
  correction that its pixels keep pushing one way still takes most of Adam's step. threshold = 0 is Adam's
  step (the factor is 1)."""
  def init(params):
    zeros = lambda: jax.tree.map(lambda p: jnp.zeros(p.shape, jnp.float32), params)  # noqa: E731
    return GatedAdamState(count=jnp.zeros((), jnp.int32), mu=zeros(), nu=zeros(), sq=zeros())

  def update(updates, state, params=None):
    del params
    count = optax.safe_int32_increment(state.count)
    t = count.astype(jnp.float32)
    correct1, correct2 = 1 - jnp.power(jnp.float32(b1), t), 1 - jnp.power(jnp.float32(b2), t)
    spread = jnp.sqrt(noise_variance(b1, t))

    def entry(g, mu, nu, sq):
      mu = b1 * mu + (1 - b1) * g
      nu = b2 * nu + (1 - b2) * g * g
      sq = b1 * sq + (1 - b1) * g * g
      mean = mu / correct1
      z = jnp.abs(mean) / (jnp.sqrt(sq / correct1) * spread + 1e-30)
      gate = jnp.maximum(0.0, 1.0 - threshold / jnp.maximum(z, 1e-30))
      return (gate * mean / (jnp.sqrt(nu / correct2) + eps)).astype(g.dtype), mu, nu, sq

    out = jax.tree.map(entry, updates, state.mu, state.nu, state.sq)
    pick = lambda i: jax.tree.map(lambda _, o: o[i], updates, out)  # noqa: E731
    return pick(0), GatedAdamState(count=count, mu=pick(1), nu=pick(2), sq=pick(3))

  return optax.GradientTransformation(init, update)


def pinned_mean() -> optax.GradientTransformation:
  """Updates of the pose corrections (N frames, 6) less their mean over the frames: corrections that start
  at zero keep a zero mean, so the cameras cannot drift together by a common shift or turn (a motion of
  every camera with the scene that no training pixel sees, but that held-out cameras, at their given poses,
  pay for). What each camera moves relative to the others is left as the optimiser made it."""
  return optax.stateless(lambda updates, params=None: jax.tree.map(
      lambda u: u - jnp.mean(u, axis=0, keepdims=True), updates))


def preconditioned(inner: optax.GradientTransformation, matrices_Nx6x6) -> optax.GradientTransformation:
  """`inner` run on v, where the corrections (N, 6) are M v with each frame's symmetric M (CamP's
  preconditioning, pose_correction.preconditioners): the gradient it sees is M g (d loss / dv = M^T g), its
  update u of v is applied as M u, and its parameters (weight decay) are M^-1 x. The corrections stay the
  parameters (and start at zero, as v does), so checkpoints, exports and evaluation read them as before."""
  matrices = jnp.asarray(matrices_Nx6x6, jnp.float32)
  inverses = jnp.linalg.inv(matrices)
  apply = lambda m: (lambda x: jnp.einsum("nij,nj->ni", m, x))  # noqa: E731

  def update(updates, state, params=None):
    latent = None if params is None else jax.tree.map(apply(inverses), params)
    steps, state = inner.update(jax.tree.map(apply(matrices), updates), state, latent)
    return jax.tree.map(apply(matrices), steps), state

  return optax.GradientTransformation(inner.init, update)


def make_optimizer(train_config, clip: bool = True, pose_preconditioners=None) -> optax.GradientTransformation:
  """Adam on the schedule above, after clipping the global gradient norm to train.grad_clip (if > 0 and
  `clip`: a model of several regions clips in its step instead, where the norm of every region's gradients is
  known; each device's optimiser sees its own regions' only). With train.sparse_table_updates, the hash grids'
  tables have an Adam that skips entries without a gradient (scale_by_sparse_adam, the same schedule and
  decays). With train.pose_refine, the pose corrections have their own: AdamW on the same schedule's shape
  from train.pose_lr_init to train.pose_lr_final, with train.pose_weight_decay (nerfacto's camera optimiser),
  its first-moment decay train.pose_b1 and, where train.pose_gate > 0, each step gated by how far its
  gradient's mean stands out of noise (scale_by_gated_adam);
  with train.pose_pin_mean, each of its updates less its mean over the frames (pinned_mean); with
  `pose_preconditioners` (N, 6, 6: train.pose_precondition), AdamW steps the preconditioned corrections
  (preconditioned)."""
  tc = train_config
  schedule = learning_rate_schedule(tc)
  adam = optax.adam(schedule, b1=tc.adam_b1, b2=tc.adam_b2, eps=tc.adam_eps)
  transforms = {}
  if tc.sparse_table_updates:
    transforms["table"] = optax.chain(scale_by_sparse_adam(tc.adam_b1, tc.adam_b2, tc.adam_eps),
                                      optax.scale_by_learning_rate(schedule))
  if tc.pose_refine:
    pose_schedule = learning_rate_schedule(tc, tc.pose_lr_init, tc.pose_lr_final)
    if tc.pose_gate > 0:
      pose = optax.chain(scale_by_gated_adam(tc.pose_b1, 0.999, tc.adam_eps, tc.pose_gate),
                         optax.add_decayed_weights(tc.pose_weight_decay),
                         optax.scale_by_learning_rate(pose_schedule))
    else:
      pose = optax.adamw(pose_schedule, b1=tc.pose_b1, eps=tc.adam_eps, weight_decay=tc.pose_weight_decay)
    if pose_preconditioners is not None:
      pose = preconditioned(pose, pose_preconditioners)
    if tc.pose_pin_mean:
      pose = optax.chain(pose, pinned_mean())
    transforms["pose"] = pose
  if transforms:
    adam = optax.multi_transform({"field": adam, **transforms}, _labels(tables=tc.sparse_table_updates))
  return optax.chain(optax.clip_by_global_norm(tc.grad_clip), adam) if clip and tc.grad_clip > 0 else adam


def rays_key(seed: int, mesh: Mesh) -> jax.Array:
  """The key of the rays' randomness (stratified jitter, random backgrounds), made replicated on `mesh`
  (where the step takes it: a key on one device would be copied to every device at every step); the step
  folds in the step."""
  make = lambda: jax.random.fold_in(jax.random.key(seed), _RAYS_STREAM)
  return jax.jit(make, out_shardings=distributed.replicated(mesh))()


# The initializers of the last few (model, optimizer) pairs, by identity (a flax module with a ConfigDict is not
# hashable): a run asks for its state's shapes, its leaves' specs and the state itself, and JAX traces a function
# it has traced before for the same argument types from its cache, so one function object is traced once (the
# model's whole forward pass, 0.1 to 0.3 s) rather than two to five times.
_INITIALIZERS: list = []


def _initializer(model, optimizer):
  """key -> the initial TrainState (parameters from the key, optimiser state for them); the same function for
  the same model and optimizer objects."""
  for known_model, known_optimizer, init in _INITIALIZERS:
    if known_model is model and known_optimizer is optimizer:
      return init

  def init(key):
    rays = jnp.zeros((2, 3), jnp.float32), jnp.ones((2, 3), jnp.float32)
    params = model.init(key, *rays, 2.0, 6.0, jnp.zeros(3))
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=optimizer.init(params))
  _INITIALIZERS[:] = [(model, optimizer, init)] + _INITIALIZERS[:3]
  return init


def state_specs(model, optimizer, mesh: Mesh):
  """The train state's PartitionSpecs on `mesh`: with model.regions > 1 and a region axis, the region fields'
  parameters and their optimiser state split over it, P(REGION_AXIS) (each device holds its regions' only),
  and every other leaf (the step, per-frame tables, the optimiser's count) replicated; else P() for the whole
  state (a prefix of every leaf)."""
  if model.regions == 1 or distributed.num_regions(mesh) == 1:
    return P()
  shapes = jax.eval_shape(_initializer(model, optimizer), jax.random.key(0))
  return jax.tree_util.tree_map_with_path(
      lambda path, _: P(distributed.REGION_AXIS) if nerf_model.in_region(path) else P(), shapes)


def state_shardings(model, optimizer, mesh: Mesh):
  """state_specs as NamedShardings on `mesh` (one replicated sharding where the whole state is)."""
  specs = state_specs(model, optimizer, mesh)
  if specs == P():
    return distributed.replicated(mesh)
  return jax.tree.map(lambda spec: NamedSharding(mesh, spec), specs, is_leaf=lambda x: isinstance(x, P))


def initial_state(model, optimizer, seed: int, mesh: Mesh) -> TrainState:
  """The initial train state of `model` and `optimizer` from `seed`, created laid over `mesh`
  (state_shardings: replicated, bar a region model's region fields)."""
  key = jax.random.fold_in(jax.random.key(seed), _PARAMS_STREAM)
  return jax.jit(_initializer(model, optimizer), out_shardings=state_shardings(model, optimizer, mesh))(key)


def state_shapes(model, optimizer, mesh: Mesh) -> TrainState:
  """The train state's leaves as ShapeDtypeStructs laid over `mesh` (state_shardings), without computing
  anything."""
  shapes = jax.eval_shape(_initializer(model, optimizer), jax.random.key(0))
  sharding = state_shardings(model, optimizer, mesh)
  if isinstance(sharding, NamedSharding):
    return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sharding), shapes)
  return jax.tree.map(lambda s, sh: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sh), shapes, sharding)
