"""The shared set-up: what training, evaluation, orbit rendering and the tools build from a config.

`build(config)` loads the scene (a missing held-out split fails now, not after training), makes the device
mesh, the model, the optimiser, the ray bounds, the train state's and the batch's shapes and placement
(`jax.eval_shape` of the initialisation: nothing is computed until a run needs real parameters) and the
compiled renderer. Every mode starts from these same pieces, so a checkpoint written by one mode restores in
any other. `build_program(config, mesh, backend)` is the same without a scene: what the pod compile tool
compiles, on a TPU topology's devices.

Randomness is a function of (seed, what): the parameters and the rays draw from their own streams, folded
into the seed; the train step folds in the step on top.
"""
import dataclasses
import os
import sys
from typing import Any

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh

from nerfpod import data, distributed, scenes
from nerfpod.render import camera_path, renderer
from nerfpod.run import compilation
from nerfpod.errors import UserError
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


def _pose_labels(params):
  """'pose' for the pose corrections, 'field' for every other parameter (appearance codes included)."""
  def label(path, _):
    return "pose" if any(getattr(k, "key", None) == pose_correction.PARAM for k in path) else "field"
  return jax.tree_util.tree_map_with_path(label, params)


def make_optimizer(train_config) -> optax.GradientTransformation:
  """Adam on the schedule above, after clipping the global gradient norm to train.grad_clip (if > 0). With
  train.pose_refine, the pose corrections have their own: AdamW on the same schedule's shape from
  train.pose_lr_init to train.pose_lr_final, with train.pose_weight_decay (nerfacto's camera optimiser)."""
  tc = train_config
  adam = optax.adam(learning_rate_schedule(tc), b1=tc.adam_b1, b2=tc.adam_b2, eps=tc.adam_eps)
  if tc.pose_refine:
    pose = optax.adamw(learning_rate_schedule(tc, tc.pose_lr_init, tc.pose_lr_final), eps=tc.adam_eps,
                       weight_decay=tc.pose_weight_decay)
    adam = optax.multi_transform({"field": adam, "pose": pose}, _pose_labels)
  return optax.chain(optax.clip_by_global_norm(tc.grad_clip), adam) if tc.grad_clip > 0 else adam


def uses_frames(config) -> bool:
  """Whether the training batches carry each ray's training-frame index (per-frame appearance or poses)."""
  return bool(config.model.appearance_dim) or bool(config.train.pose_refine)


def ray_bounds(config, scene) -> tuple[float, float]:
  """render.near/far where given (>= 0), else the scene's own (in NDC space: 0 and 1, the near plane and
  infinity)."""
  own_near, own_far = (0.0, 1.0) if config.render.space == "ndc" else (scene.near, scene.far)
  near = config.render.near if config.render.near >= 0 else own_near
  far = config.render.far if config.render.far >= 0 else own_far
  if not 0 <= near < far:
    raise UserError(f"the rays would run from near={near:g} to far={far:g} (render.near/far or the scene's "
                    f"bounds); set --config.render.near and --config.render.far with 0 <= near < far.")
  if config.render.spacing == "inverse" and near <= 0:
    raise UserError(f"render.spacing=inverse spaces samples evenly in 1 / distance, which needs a near bound "
                    f"above 0, but the rays start at {near:g}; set --config.render.near (e.g. 0.2).")
  return float(near), float(far)


def ndc_camera(config, scene) -> tuple[float, float, float, float] | None:
  """(fx, fy, width, height) of the camera whose frustum is the NDC cube (render.space='ndc'): the first
  training camera, in the scene's frame (a forward-facing capture, recentred so that its mean camera sits
  at the origin looking down -z, has one camera for all frames)."""
  if config.render.space != "ndc":
    return None
  train = scene.split("train")
  forward = -np.asarray(train.poses, np.float64)[:, :3, 2]
  if not (forward[:, 2].mean() < -0.9 and (train.poses[:, 2, 3] > -1.0).all()):
    raise UserError(f"render.space=ndc needs a forward-facing capture framed as LLFF's loader frames it "
                    f"(cameras looking down -z from in front of the near plane z = -1), but scene "
                    f"{scene.name!r} ({scene.space}) is not; load an LLFF capture with data.orient=auto, or use "
                    f"--config.render.space=euclidean (or contract for a 360-degree capture).")
  intr = train.intrinsics
  return float(intr.fx), float(intr.fy), float(intr.width), float(intr.height)


def rays_key(seed: int) -> jax.Array:
  """The key of the rays' randomness (stratified jitter, random backgrounds); the step folds in the step."""
  return jax.random.fold_in(jax.random.key(seed), _RAYS_STREAM)


def _initializer(model, optimizer):
  """key -> the initial TrainState (parameters from the key, optimiser state for them)."""
  def init(key):
    rays = jnp.zeros((2, 3), jnp.float32), jnp.ones((2, 3), jnp.float32)
    params = model.init(key, *rays, 2.0, 6.0, jnp.zeros(3))
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=optimizer.init(params))
  return init


@dataclasses.dataclass(frozen=True)
class Program:
  """What compiling a config's train step and renderer needs, with or without its scene: the model
  formulated for a backend, the optimiser, the ray bounds and background, and the train state's and the
  global batch's shapes laid over a mesh. The pod compile tool builds one without a scene; every run builds
  its Components, which are a Program with the scene it came from."""
  config: Any
  mesh: Mesh
  model: nerf_model.NeRF
  optimizer: optax.GradientTransformation
  near: float
  far: float
  background: tuple
  state_shapes: TrainState  # jax.ShapeDtypeStruct leaves, replicated over `mesh`: what a restore fills
  batch_shapes: dict        # the global training batch as ShapeDtypeStructs, sharded over every mesh axis
  compiler_options: dict    # XLA options of the step and the renderer (compilation.compiler_options)

  @property
  def render_model(self) -> nerf_model.NeRF:
    """The model of every rendering that trains nothing: render.eval_samples field samples per ray where
    set (the same parameters: only the quadrature is finer), else the training model itself."""
    samples = self.config.render.eval_samples
    if not samples or samples == self.model.num_samples:
      return self.model
    return self.model.clone(num_samples=samples)

  def make_renderer(self, mesh: Mesh | None = None):
    """(params, origins, directions) -> rgb/depth/acc/disparity of `render_model`, compiled on `mesh`
    (default the program's)."""
    return renderer.make_renderer(self.render_model, self.mesh if mesh is None else mesh, self.near, self.far,
                                self.background, self.compiler_options)


@dataclasses.dataclass(frozen=True)
class Components(Program):
  """A run's Program with its scene and its renderer compiled on the run's mesh."""
  scene: scenes.Scene = None
  renderer: Any = None  # make_renderer() of the run's mesh

  def init_state(self) -> TrainState:
    """The initial train state, created directly replicated on every device of the mesh."""
    return initial_state(self.model, self.optimizer, self.config.train.seed, self.mesh)

  def batches(self, start_step: int):
    """This host's slices of the global training batches from `start_step` on."""
    tc = self.config.train
    dataset = data.ray_batches(self.scene.split("train"), tc.seed, tc.batch_size,
                               distributed.local_slice(tc.batch_size), self.config.data.pixel_center,
                               max(tc.num_steps, 1), self.config.data.shards, uses_frames(self.config))
    # On a CPU the batches are made in the training loop's thread, between the dispatch of a step and the
    # next (the step runs meanwhile): a background thread would run on the cores that compute the step, and
    # its hand-offs cost more than the batch. On accelerators, a thread prepares them ahead.
    return data.iterator(dataset, start_step, background=jax.default_backend() != "cpu")


def initial_state(model, optimizer, seed: int, mesh: Mesh) -> TrainState:
  """The initial train state of `model` and `optimizer` from `seed`, created replicated over `mesh`."""
  key = jax.random.fold_in(jax.random.key(seed), _PARAMS_STREAM)
  return jax.jit(_initializer(model, optimizer), out_shardings=distributed.replicated(mesh))(key)


def state_shapes(model, optimizer, mesh: Mesh) -> TrainState:
  """The train state's leaves as ShapeDtypeStructs replicated over `mesh`, without computing anything."""
  shapes = jax.eval_shape(_initializer(model, optimizer), jax.random.key(0))
  sharding = distributed.replicated(mesh)
  return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sharding), shapes)


def batch_shapes(batch_size: int, mesh: Mesh, with_alpha: bool, with_frames: bool = False) -> dict:
  """The global batch of data.LocalRayBatch's fields (less its host-side step) as ShapeDtypeStructs laid
  over every device of `mesh` (its data axis, and its slice axis across slices): each host's rows on its own
  devices, as distributed.to_global makes them."""
  sharding = distributed.batch_sharding(mesh)
  shapes = {"origins": ((batch_size, 3), jnp.float32), "directions": ((batch_size, 3), jnp.float32),
            "rgb": ((batch_size, 3), jnp.float32), "ray_ids": ((batch_size,), jnp.int32)}
  if with_alpha:
    shapes["alpha"] = ((batch_size,), jnp.float32)
  if with_frames:
    shapes["frame"] = ((batch_size,), jnp.int32)
  return {k: jax.ShapeDtypeStruct(shape, dtype, sharding=sharding) for k, (shape, dtype) in shapes.items()}


# Ray bounds for a program compiled without its scene where the config leaves them to the scene: the values
# are constants of the program and change neither its shapes nor its cost.
_PLACEHOLDER_BOUNDS = (2.0, 6.0)
# Likewise the training frames (rows of the per-frame appearance codes and pose corrections).
_PLACEHOLDER_FRAMES = 100
# Likewise the NDC cube's camera (fx, fy, width, height) of a forward-facing scene: LLFF's at images_8.
_PLACEHOLDER_NDC_CAMERA = (421.0, 421.0, 504.0, 378.0)


def build_program(config, mesh: Mesh, backend: str | None = None, scene: scenes.Scene | None = None) -> Program:
  """The step's and renderer's pieces for `config` on `mesh` (any devices: a TPU topology's too), the model
  formulated and compiled for `backend` (default JAX's). With `scene`, its ray bounds, NDC camera,
  background and alpha; without (the pod compile tool), placeholders of the same shapes and cost, the batch
  carrying alpha where the scene format has it (scenes.HAS_ALPHA), and _PLACEHOLDER_FRAMES training frames."""
  if scene is not None:
    ndc = ndc_camera(config, scene)
    near, far = ray_bounds(config, scene)
    background, with_alpha = tuple(scene.background), scene.split("train").alphas is not None
    num_frames = len(scene.split("train"))
  else:
    num_frames = _PLACEHOLDER_FRAMES
    ndc = _PLACEHOLDER_NDC_CAMERA if config.render.space == "ndc" else None
    near = config.render.near if config.render.near >= 0 else _PLACEHOLDER_BOUNDS[0]
    far = config.render.far if config.render.far >= 0 else max(_PLACEHOLDER_BOUNDS[1], near + 1.0)
    background, with_alpha = (1.0, 1.0, 1.0), scenes.HAS_ALPHA.get(config.data.kind, True)
  model = nerf_model.from_config(config, ndc, backend, num_frames)
  optimizer = make_optimizer(config.train)
  return Program(config, mesh, model, optimizer, float(near), float(far), background,
                 state_shapes(model, optimizer, mesh),
                 batch_shapes(config.train.batch_size, mesh, with_alpha, uses_frames(config)),
                 compilation.compiler_options(config, backend))


# The share of a host's physical memory its images may take where data.host_memory_gib is 0: the rest is for
# the runtime, the compiled programs, the pipeline's batches (and, on a CPU, the simulated devices).
HOST_MEMORY_SHARE = 0.5


def host_memory_budget_bytes(config) -> int:
  """The bytes this host's images (its training shards and the held-out splits) may take:
  data.host_memory_gib, or HOST_MEMORY_SHARE of the host's physical memory where that is 0."""
  if config.data.host_memory_gib > 0:
    return int(config.data.host_memory_gib * 2**30)
  return int(HOST_MEMORY_SHARE * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def host_shards(config) -> scenes.Shards:
  """The training frames this host reads (data.shards over the hosts of the run) and its memory budget;
  a shard count the host count does not divide is refused."""
  held, host, hosts = distributed.local_shards(config.data.shards)
  return scenes.Shards(config.data.shards, held, host, hosts, host_memory_budget_bytes(config))


def build(config, mesh: Mesh | None = None) -> Components:
  """The pieces every mode needs (`mesh`: default, every device of every host in config.mesh.slices
  slices, distributed.make_mesh): the scene (a missing held-out split or a bad camera path file fails now,
  not after training; each host reads the training frames of its data.shards only, and says so in one
  line), its Program and renderer."""
  shards = host_shards(config)
  scene = scenes.load(config.data, shards)
  train = scene.split("train")
  print(f"host {shards.host} holds {len(train.held_frames)} of {len(train)} training images "
        f"({train.nbytes / 2**20:.1f} MiB)", file=sys.stderr, flush=True)  # stdout may be a tool's output
  scene.split(config.eval.split)
  if config.orbit.path == "file":
    camera_path.read(config.orbit.path_file)
  if mesh is None:
    mesh = distributed.make_mesh(num_slices=config.mesh.slices or None)
  program = build_program(config, mesh, scene=scene)
  fields = {f.name: getattr(program, f.name) for f in dataclasses.fields(Program)}
  return Components(**fields, scene=scene, renderer=program.make_renderer())
