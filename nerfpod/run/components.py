"""The shared set-up: what training, evaluation, orbit rendering and the tools build from a config.

`build(config)` loads the scene (a missing held-out split fails now, not after training), makes the device
mesh, the model, the optimiser, the ray bounds, the train state's and the batch's shapes and placement
(`jax.eval_shape` of the initialisation: nothing is computed until a run needs real parameters) and the
compiled renderer: one frozen Components. Every mode starts from these same pieces, so a checkpoint written
by one mode restores in any other. `make_model(config)` is the NeRF model the config describes for the backend
(nerfpod.nerf reads neither). `build_program(config, mesh, backend)` is the same without a scene: what
the pod compile tool compiles, on a TPU topology's devices. The train state, its optimiser and schedule are
nerfpod.run.train_state's.
"""
import dataclasses
import math
import sys
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh

from nerfpod import data, distributed, scenes
from nerfpod.render import camera_path, renderer
from nerfpod.run import compilation, train_state
from nerfpod.run.train_state import TrainState
from nerfpod.errors import UserError
from nerfpod.nerf import cameras as nerf_cameras, model as nerf_model, pose_correction, sampling
from nerfpod.nerf import regions as nerf_regions

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


@dataclasses.dataclass(frozen=True)
class Components:
  """The one set-up value: what compiling and running a config's train step and renderer needs, resolved
  once: the model formulated for a backend, the optimiser, the ray bounds and background, the train state's
  and the global batch's shapes laid over a mesh, the compiler options; and a run's scene with its renderer
  compiled on the run's mesh (build). The pod compile tool's have no scene (build_program): placeholders of
  the same shapes and cost stand in for what the scene would resolve."""
  config: Any
  mesh: Mesh
  model: nerf_model.NeRF
  optimizer: optax.GradientTransformation
  near: float
  far: float
  background: tuple
  state_shapes: TrainState  # jax.ShapeDtypeStruct leaves laid over `mesh` (train_state.state_shardings): what a
                            # restore fills
  batch_shapes: dict        # the global training batch as ShapeDtypeStructs, sharded over the batch's axes
  compiler_options: dict    # XLA options of the step and the renderer (compilation.compiler_options)
  scene: scenes.Scene | None = None  # None: the pod compile tool's, without a scene
  renderer: Any = None      # make_renderer() of the run's mesh, where there is a scene
  # step.MeasuredCapacity where this run measured model.region_capacity=auto (train.resolve_capacity): a fitted
  # train.microbatches=0 sizes the margin for its micro-batch's rays (step.fitted_capacity); None otherwise
  capacity_measured: Any = None

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
    (default the components')."""
    return renderer.make_renderer(self.render_model, self.mesh if mesh is None else mesh, self.near, self.far,
                                self.background, self.compiler_options)


  def init_state(self) -> TrainState:
    """The initial train state, created directly laid over the mesh (replicated, bar region fields)."""
    return train_state.initial_state(self.model, self.optimizer, self.config.train.seed, self.mesh)

  def batches(self, start_step: int):
    """This host's slices of the global training batches from `start_step` on."""
    tc = self.config.train
    dataset = data.ray_batches(self.scene.split("train"), tc.seed, tc.batch_size,
                               distributed.local_slice(tc.batch_size, self.mesh if self.config.model.regions > 1
                                                       else None), self.config.data.pixel_center,
                               max(tc.num_steps, 1), self.config.data.shards, uses_frames(self.config))
    # On a CPU the batches are made in the training loop's thread, between the dispatch of a step and the
    # next (the step runs meanwhile): a background thread would run on the cores that compute the step, and
    # its hand-offs cost more than the batch. On accelerators, a thread prepares them ahead.
    return data.iterator(dataset, start_step, background=jax.default_backend() != "cpu")


def batch_shapes(batch_size: int, mesh: Mesh, with_alpha: bool, with_frames: bool = False) -> dict:
  """The global batch of data.LocalRayBatch's fields (less its host-side step) as ShapeDtypeStructs laid
  over every device of `mesh` (its data axis, and its slice axis across slices): each host's rows on its own
  devices, as distributed.to_global makes them."""
  sharding = distributed.batch_sharding(mesh)
  wanted = {"alpha": with_alpha, "frame": with_frames}
  return {k: jax.ShapeDtypeStruct((batch_size, *shape), dtype, sharding=sharding)
          for k, (shape, dtype) in _RAY_FIELDS.items() if wanted.get(k, True)}


# A batch's fields, per ray: (shape, dtype); alpha where the scene has it, frame where per-frame parameters need it.
_RAY_FIELDS = {"origins": ((3,), jnp.float32), "directions": ((3,), jnp.float32), "rgb": ((3,), jnp.float32),
               "ray_ids": ((), jnp.int32), "alpha": ((), jnp.float32), "frame": ((), jnp.int32)}


# Ray bounds for a program compiled without its scene where the config leaves them to the scene: the values
# are constants of the program and change neither its shapes nor its cost.
_PLACEHOLDER_BOUNDS = (2.0, 6.0)
# Likewise the training frames (rows of the per-frame appearance codes and pose corrections).
_PLACEHOLDER_FRAMES = 100
# Likewise the NDC cube's camera (fx, fy, width, height) of a forward-facing scene: LLFF's at images_8.
_PLACEHOLDER_NDC_CAMERA = (421.0, 421.0, 504.0, 378.0)
# Likewise a pixel's angle (model.hashgrid.scale_aware): 1 / a focal length of 500 pixels.
_PLACEHOLDER_PIXEL_ANGLE = 1.0 / 500.0


def pixel_angle_of(scene: scenes.Scene) -> float:
  """A pixel's width at distance 1 (radians) of the scene's training cameras: 1 / their median focal length
  (pixels, at the loaded size; the mean of fx and fy). model.hashgrid.scale_aware's footprints use it for every
  ray, of any view (held-out, orbits, the viewer): one angle for the scene."""
  cams = scene.split("train").cameras
  return float(1.0 / np.median(0.5 * (np.asarray(cams.fx) + np.asarray(cams.fy))))


def pose_preconditioners(config, scene: scenes.Scene | None, num_frames: int) -> np.ndarray | None:
  """train.pose_precondition: CamP's matrices (N, 6, 6) of the training cameras over the scene's depths
  (pose_correction.preconditioners; NDC scenes: from their near plane at 1 to infinity, in the world);
  without a scene (the pod compile tool), identities of the same shape. None where it is off."""
  if not (config.train.pose_refine and config.train.pose_precondition):
    return None
  if scene is None:
    return np.tile(np.eye(6, dtype=np.float32), (num_frames, 1, 1))
  train = scene.split("train")
  near, far = (1.0, math.inf) if config.render.space == "ndc" else (scene.near, scene.far)
  return pose_correction.preconditioners(train.poses, train.cameras, near, far)


def grid_matmul_max_rows(config, backend: str) -> int:
  """How many rows a hash-grid level may have to be looked up by matmuls on `backend` (0: all gather).

  compile.hashgrid_lookup 'auto' takes matmuls on TPUs, where gathers and scatter-adds are slow
  (docs/pod-compile.md has the cost-model figures), and gathers elsewhere (a CPU or GPU gathers a row
  cheaply). The parameters are the same either way, so a checkpoint moves freely between backends.
  """
  lookup = config.compile.hashgrid_lookup
  if lookup == "auto":
    lookup = "matmul" if backend == "tpu" else "gather"
  return config.compile.matmul_max_rows if lookup == "matmul" else 0


# The balanced cut's sample cloud: rays drawn from the training frames with this seed (fixed: every process, and
# a resumed run, cuts the same planes), points stratified along each.
BALANCE_RAYS, BALANCE_SAMPLES_PER_RAY, BALANCE_SEED = 4096, 32, 0


def balance_samples(config, scene) -> np.ndarray:
  """(N, 3) float32: the points model.region_cut='balanced' splits evenly: BALANCE_RAYS pixels of the
  training frames (all of them, whatever data.shards holds: poses and cameras are every host's), drawn with
  BALANCE_SEED, each ray's [near, far] (ray_bounds) clipped to the hash grid's box where the field is one,
  BALANCE_SAMPLES_PER_RAY stratified points along it (nerf_regions.ray_samples)."""
  split = scene.split("train")
  near, far = ray_bounds(config, scene)
  bound = config.model.hashgrid.bound if config.model.field == "hashgrid" else None
  return nerf_regions.ray_samples(np.asarray(split.poses), split.cameras, near, far, bound, BALANCE_RAYS,
                                  BALANCE_SAMPLES_PER_RAY, BALANCE_SEED, config.data.pixel_center)


def region_partition(config, camera_positions_Nx3=None, samples_Nx3=None) -> nerf_regions.Partition:
  """The regions of `config.model.regions` cut as model.region_cut says: 'grid', cells of the ground plane
  over the hash grid's box [-bound, bound]^2 (model.hashgrid.bound); 'cameras', the Voronoi cells of the
  k-means centres of the training cameras' positions in the ground plane (`camera_positions_Nx3`; None, a
  placeholder ring of cameras of the same cost: the pod compile tool's); 'balanced', NeRF-XL's recursive
  median cut of the training rays' samples (`samples_Nx3`, balance_samples; None, the cut of a placeholder
  cloud over the box, of the same cost)."""
  count = config.model.regions
  if config.model.region_cut == "grid":
    return nerf_regions.grid(count, config.model.hashgrid.bound)
  if config.model.region_cut == "balanced":
    if samples_Nx3 is None:
      bound = config.model.hashgrid.bound
      samples_Nx3 = np.random.default_rng(BALANCE_SEED).uniform(-bound, bound, (max(64, 16 * count), 3))
    return nerf_regions.balanced(np.asarray(samples_Nx3)[:, :2], count)
  if camera_positions_Nx3 is None:
    angles = 2 * np.pi * np.arange(count) / count
    return nerf_regions.voronoi(np.stack([np.cos(angles), np.sin(angles)], -1))
  ground = np.asarray(camera_positions_Nx3, np.float64)[:, :2]
  return nerf_regions.voronoi(nerf_regions.kmeans(ground, count))


def region_inputs(config, scene) -> tuple:
  """(camera positions (N, 3), samples (N, 3) or None): what `scene`'s regions are cut from (region_partition):
  the training cameras' centres (model.region_cut=cameras cuts around them) and, for model.region_cut=balanced
  with model.regions > 1, the training rays' samples it splits evenly (balance_samples)."""
  cameras = np.asarray(scene.split("train").poses)[:, :3, 3]
  balanced = config.model.regions > 1 and config.model.region_cut == "balanced"
  return cameras, balance_samples(config, scene) if balanced else None


def region_cut(config, scene) -> nerf_regions.Partition:
  """The regions of `config` on `scene`, cut as build_program's model cuts them (region_inputs)."""
  return region_partition(config, *region_inputs(config, scene))


def _as_tuples(part: nerf_regions.Partition) -> tuple:
  """A partition as nested tuples (a flax module's attributes are hashed)."""
  nested = lambda x: tuple(map(nested, x)) if isinstance(x, list) else x  # noqa: E731
  return tuple(nested(np.asarray(a).tolist()) for a in part)


def make_model(config, ndc_camera=None, backend: str | None = None, num_frames: int = 0,
               camera_positions=None, pixel_angle: float = 0.0, region_samples=None) -> nerf_model.NeRF:
  """The NeRF model that `config.model` and `config.render` describe, formulated for `backend` (default:
  JAX's; the pod compile tool asks for 'tpu' on a CPU). `ndc_camera` (fx, fy, width, height): the camera
  whose frustum is the NDC cube, needed with render.space='ndc' (the scene's training camera).
  `num_frames`: the training frames, each with its own appearance code (model.appearance_dim > 0) and pose
  correction (train.pose_refine); at least 1 where either is on. `camera_positions` (N, 3): the training
  cameras' centres, where model.region_cut='cameras' cuts the regions around them; `region_samples` (N, 3):
  the training rays' samples that model.region_cut='balanced' splits evenly. `pixel_angle`: a pixel's
  width at distance 1 (radians: 1 / focal length in pixels), the footprints of model.hashgrid.scale_aware
  (needed there; unused elsewhere)."""
  if (config.model.appearance_dim or config.train.pose_refine) and num_frames < 1:
    raise ValueError("model.appearance_dim and train.pose_refine need the training frame count (num_frames)")
  scale_aware = config.model.field == "hashgrid" and config.model.hashgrid.scale_aware
  if scale_aware and not pixel_angle > 0:
    raise ValueError("model.hashgrid.scale_aware needs the scene's pixel angle (pixel_angle)")
  dtype = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}[config.model.compute_dtype]
  backend = backend or jax.default_backend()
  # compile.hashgrid_lookup=sparsecore: dense levels by matmuls (as 'auto' on a TPU), the others by Pallas
  # kernels on the SparseCores (nerf/sparsecore.py), refused in one sentence on a backend without them.
  sparsecore = config.compile.hashgrid_lookup == "sparsecore"
  matmul_max_rows = config.compile.matmul_max_rows if sparsecore else grid_matmul_max_rows(config, backend)
  if sparsecore:
    from nerfpod import schema  # the refusal in the schema's words
    refused = schema.backend_rules(schema.flatten(config), backend)
    if refused:
      raise schema.ConfigError(refused)
  render = config.render
  return nerf_model.NeRF(
      model_config=config.model, num_samples=render.num_samples, num_importance=render.num_importance,
      last_delta=render.last_delta, dtype=dtype, space=render.space, spacing=render.spacing,
      proposal_samples=tuple(render.proposal_samples), proposal_padding=float(render.proposal_padding),
      ndc_camera=None if ndc_camera is None else tuple(float(v) for v in ndc_camera),
      grid_matmul_max_rows=matmul_max_rows,
      grid_materialize=backend == "cpu", grid_layout=str(config.compile.hashgrid_layout),
      grid_lookup="sparsecore" if sparsecore else "gather",
      num_frames=int(num_frames),
      pose_refine=bool(config.train.pose_refine),
      near_gradient_distance=float(config.train.near_gradient_distance),
      pixel_angle=float(pixel_angle) if scale_aware else 0.0,
      **_region_attributes(config, camera_positions, region_samples))


def _region_attributes(config, camera_positions, region_samples=None) -> dict:
  """NeRF's region attributes: none where model.regions is 1 (the one-field model, as it always was)."""
  if config.model.regions == 1:
    return {}
  return {"regions": int(config.model.regions),
          "region_planes": _as_tuples(region_partition(config, camera_positions, region_samples))}


def build_program(config, mesh: Mesh, backend: str | None = None, scene: scenes.Scene | None = None) -> Components:
  """The step's and renderer's pieces for `config` on `mesh` (any devices: a TPU topology's too), the model
  formulated and compiled for `backend` (default JAX's). With `scene`, its ray bounds, NDC camera,
  background and alpha; without (the pod compile tool), placeholders of the same shapes and cost, the batch
  carrying alpha where the scene format has it (scenes.HAS_ALPHA), and _PLACEHOLDER_FRAMES training frames."""
  if scene is not None:
    ndc = ndc_camera(config, scene)
    near, far = ray_bounds(config, scene)
    background, with_alpha = tuple(scene.background), scene.split("train").alphas is not None
    num_frames = len(scene.split("train"))
    cameras, samples = region_inputs(config, scene)
    pixel_angle = pixel_angle_of(scene)
  else:
    cameras = samples = None
    num_frames = _PLACEHOLDER_FRAMES
    pixel_angle = _PLACEHOLDER_PIXEL_ANGLE
    ndc = _PLACEHOLDER_NDC_CAMERA if config.render.space == "ndc" else None
    near = config.render.near if config.render.near >= 0 else _PLACEHOLDER_BOUNDS[0]
    far = config.render.far if config.render.far >= 0 else max(_PLACEHOLDER_BOUNDS[1], near + 1.0)
    background, with_alpha = (1.0, 1.0, 1.0), scenes.HAS_ALPHA.get(config.data.kind, True)
  model = make_model(config, ndc, backend, num_frames, cameras, pixel_angle, samples)
  optimizer = train_state.make_optimizer(config.train, clip=config.model.regions == 1,  # regions: the step's
                                         pose_preconditioners=pose_preconditioners(config, scene, num_frames))
  return Components(config, mesh, model, optimizer, float(near), float(far), background,
                    train_state.state_shapes(model, optimizer, mesh),
                    batch_shapes(config.train.batch_size, mesh, with_alpha, uses_frames(config)),
                    compilation.compiler_options(config, backend), scene=scene)


def check_regions_seen(comps: Components, per_side: int = 8) -> None:
  """model.regions > 1: refuses, in one sentence, a partition with a region that no training ray crosses (a
  grid cell beyond every camera's view, a camera cut's centre that lost its cameras): its fields could learn
  nothing. The rays: a per_side x per_side grid of pixels of every training frame, corners included, over
  the run's [near, far], clipped to the hash grid's box as the model clips them."""
  config = comps.config
  if config.model.regions == 1 or comps.scene is None:
    return
  split = comps.scene.split("train")
  cams, frames = split.cameras, np.arange(len(split))
  grid = np.linspace(0.0, 1.0, per_side)
  fr, fc = (a.ravel() for a in np.meshgrid(grid, grid, indexing="ij"))
  frames_F = np.repeat(frames, fr.size)
  rows = np.minimum(np.tile(fr, len(frames)) * cams.height[frames_F], cams.height[frames_F] - 1)
  cols = np.minimum(np.tile(fc, len(frames)) * cams.width[frames_F], cams.width[frames_F] - 1)
  origins, directions = nerf_cameras.frame_rays(np.asarray(split.poses)[frames_F], cams, frames_F, rows, cols,
                                                config.data.pixel_center)
  near, far = comps.near, comps.far
  if config.model.field == "hashgrid":
    near, far = sampling.clip_to_box(origins, directions, near, far, config.model.hashgrid.bound)
  partition = comps.model.partition
  missing = nerf_regions.unseen(partition, origins, directions, near, far)
  if not missing:
    return
  bound = config.model.hashgrid.bound
  cells = nerf_regions.cells(partition, bound)
  outside = [k for k in missing if len(cells[k]) == 0]
  where = ([f"region{'s' if len(outside) > 1 else ''} {', '.join(map(str, outside))}: "
            f"{'their cells miss' if len(outside) > 1 else 'its cell misses'} the field's box (x and y within "
            f"+-{bound:.2f})"] if outside else [])
  for k in missing:
    if len(cells[k]):
      low, high = cells[k].min(0), cells[k].max(0)
      where.append(f"region {k}: x {low[0]:.2f}..{high[0]:.2f}, y {low[1]:.2f}..{high[1]:.2f}")
  other = "grid" if config.model.region_cut != "grid" else "cameras"
  raise UserError(f"model.regions={config.model.regions} ({config.model.region_cut} cut) makes "
                  f"{len(missing)} region(s) that no training camera sees ({'; '.join(where)}), whose fields could "
                  f"learn nothing; use fewer regions (--config.model.regions) or the other cut "
                  f"(--config.model.region_cut={other}).")


# The share of a host's physical memory its images may take where data.host_memory_gib is 0: the rest is for
# the runtime, the compiled programs, the pipeline's batches (and, on a CPU, the simulated devices).
HOST_MEMORY_SHARE = 0.5


def host_memory_budget_bytes(config) -> int:
  """The bytes this host's images (its training shards and the held-out splits) may take:
  data.host_memory_gib, or HOST_MEMORY_SHARE of the host's physical memory where that is 0."""
  if config.data.host_memory_gib > 0:
    return int(config.data.host_memory_gib * 2**30)
  return int(HOST_MEMORY_SHARE * compilation.physical_memory_bytes())


# The share of a host's physical memory its training batches may take (the host's share of each global batch,
# those prepared ahead and the copy on its devices): the half HOST_MEMORY_SHARE leaves is also the runtime's,
# the compiled programs' and, on a CPU, the simulated devices'.
BATCH_MEMORY_SHARE = 0.25
# Every field of a batch (_RAY_FIELDS, alpha and frame included): 48 bytes a ray.
BATCH_BYTES_PER_RAY = sum(int(np.prod(shape)) * np.dtype(dtype).itemsize for shape, dtype in _RAY_FIELDS.values())


def check_batches_fit_host(config) -> None:
  """Refuses, before any work, a train.batch_size whose batches this host could not hold: its share of each
  global batch, BATCH_BYTES_PER_RAY a ray, as many times as there are copies of it at once (the one in use,
  its copy on the devices, and on accelerators data.PREFETCH prepared ahead), must fit
  BATCH_MEMORY_SHARE of the host's physical memory."""
  tc = config.train
  copies = 2 + (data.PREFETCH if jax.default_backend() != "cpu" else 0)
  per_ray = BATCH_BYTES_PER_RAY * copies / jax.process_count()
  limit = BATCH_MEMORY_SHARE * compilation.physical_memory_bytes()
  need = tc.batch_size * per_ray
  if need <= limit:
    return
  fits = int(limit // per_ray) // jax.device_count() * jax.device_count()
  raise UserError(f"train.batch_size={tc.batch_size} rays would make this host hold {need / 2**30:,.1f} GiB of "
                  f"training batches at once ({copies} copies of its share), more than the "
                  f"{limit / 2**30:,.1f} GiB ({BATCH_MEMORY_SHARE:.0%} of its memory) they may take; set "
                  f"--config.train.batch_size to at most {max(fits, jax.device_count())} (a multiple of the "
                  f"{jax.device_count()} devices).")


def host_shards(config) -> scenes.Shards:
  """The training frames this host reads (data.shards over the hosts of the run) and its memory budget;
  a shard count the host count does not divide is refused."""
  held, host, hosts = distributed.local_shards(config.data.shards)
  return scenes.Shards(config.data.shards, held, host, hosts, host_memory_budget_bytes(config))


def build(config, mesh: Mesh | None = None) -> Components:
  """The pieces every mode needs (`mesh`: default, every device of every host in config.mesh.slices
  slices, distributed.make_mesh): the scene (a missing held-out split or a bad camera path file fails now,
  not after training; each host reads the training frames of its data.shards only, and says so in one
  line), its model, optimiser, shapes and renderer."""
  check_batches_fit_host(config)
  shards = host_shards(config)
  scene = scenes.load(config.data, shards)
  train = scene.split("train")
  print(f"host {shards.host} holds {len(train.held_frames)} of {len(train)} training images "
        f"({train.nbytes / 2**20:.1f} MiB)", file=sys.stderr, flush=True)  # stdout may be a tool's output
  scene.split(config.eval.split)
  if config.orbit.path == "file":
    camera_path.read(config.orbit.path_file)
  if mesh is None:
    mesh = distributed.make_mesh(num_slices=config.mesh.slices or None, regions=config.model.regions)
  comps = build_program(config, mesh, scene=scene)
  return dataclasses.replace(comps, renderer=comps.make_renderer())
