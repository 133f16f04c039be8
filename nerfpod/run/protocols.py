"""Evaluation protocols for per-frame parameters: what a held-out view is rendered with where training
learned something per training frame that a held-out frame has no value of.

    plain            the whole image, the held-out camera at its given pose, the mean appearance code
    aligned          (train.pose_refine) the held-out camera mapped into the refined cameras' frame by the
                     similarity that best carries the given training cameras onto their refined ones
                     (nerf/alignment.py): the common drift of the refined cameras, which no training pixel
                     sees, no longer counts against the field
    appearance_half  (model.appearance_dim > 0) NeRF-W's: the view's own code fitted on the left half of its
                     image (the field frozen; eval.appearance_* steps of Adam from the mean code), metrics on
                     the right half only
    poses_optimised  (eval.pose_fit: runs with pose refinement by default) BARF's test-time pose
                     optimisation: each held-out camera's 6-vector correction fitted to its image (the field
                     frozen; eval.pose_* steps of Adam from the aligned pose, or the given one where there is
                     no gauge), metrics on the whole image from the fitted pose. Six numbers cannot paint an
                     image, so what it removes is registration: a field that holds the scene, seen from a
                     camera a little off the one its frame would put there

evaluate.py renders and scores each, one object per protocol in a list (evaluate.PROTOCOLS: its set-up,
a view added, its result, its summary line); this module holds what they need: the aligned held-out poses and the
code and pose fits, compiled programs over the run's mesh like the renderer (rays sharded over its batch axes,
the gradient averaged), so they span the whole slice on a pod as every program does.
"""
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import PartitionSpec as P

from nerfpod import distributed
from nerfpod.nerf import alignment, cameras, pose_correction

PLAIN = "plain: whole image, the held-out camera at its given pose, the mean appearance code"
ALIGNED = ("aligned: whole image, the held-out camera mapped into the refined cameras' frame by the similarity "
           "(Umeyama) of the given training camera centres onto the refined ones, the mean appearance code")
APPEARANCE_HALF = "NeRF-W: code fit on the left half, metrics on the right half"
POSES_OPTIMISED = ("BARF: each held-out camera's pose correction fitted to its whole image (the field frozen), "
                   "metrics on the whole image from the fitted pose, the mean appearance code")

# The appearance codes' parameter (nerf/model.py's NeRF._per_frame).
APPEARANCE = "appearance"


def has_codes(params) -> bool:
  return APPEARANCE in params["params"]


def gauge(params, train_poses_Nx4x4) -> tuple[float, np.ndarray, np.ndarray] | None:
  """(s, R, t): the similarity carrying the given training camera centres onto the refined ones (their
  poses with the learned corrections), or None where the run has no pose corrections."""
  corrections = pose_correction.of_params(params)
  if corrections is None:
    return None
  given = np.asarray(train_poses_Nx4x4, np.float64)
  refined = pose_correction.corrected_poses(given, corrections)
  return alignment.umeyama(given[:, :3, 3], refined[:, :3, 3])


def describe_gauge(similarity) -> dict:
  """The similarity as metrics.json reports it: scale, rotation angle (degrees) and translation."""
  scale, rotation, translation = similarity
  return {"scale": float(scale), "rotation_deg": alignment.rotation_angle_deg(rotation),
          "translation": [float(v) for v in translation]}


def with_code(params, code_A):
  """`params` with every row of the appearance table set to `code_A`: a rendering without frames (held-out
  views, which get the table's mean) then uses that code. The field's parameters are the same arrays."""
  table = params["params"][APPEARANCE]
  return {**params, "params": {**params["params"], APPEARANCE: jnp.broadcast_to(
      jnp.asarray(code_A, table.dtype), table.shape)}}


def mean_code(params) -> np.ndarray:
  """The mean of the training frames' codes (A,): what a held-out view is rendered with, and where the fit
  starts."""
  table = params["params"][APPEARANCE]
  return np.asarray(table.addressable_data(0) if hasattr(table, "addressable_data") else table).mean(0)


def _make_fitter(loss, mesh, optimizer, ordered: bool):
  """(init, step) of an Adam-like fit of a small replicated x (a code, a pose correction) to rays of one view:
  `loss(x, params, origins, directions, rgb)` its objective on the rays given; `step(x, opt_state, params,
  origins, directions, rgb)` -> (x, opt_state, loss), the rays sharded over the mesh's batch axes and the
  gradient averaged over them (`ordered`: by distributed.ordered_mean, as the train step's under
  compile.gradient_mean, so that 2 processes x 4 devices fit the bits of 1 x 8). Only x moves: the field's
  parameters are an input, never an output."""
  axis = distributed.batch_axes(mesh)

  def local(x, params, origins, directions, rgb):
    value, grad = jax.value_and_grad(loss)(x, params, origins, directions, rgb)
    if ordered:
      sizes = distributed.batch_axis_sizes(mesh)
      return distributed.ordered_mean((value, grad), axis, sizes if isinstance(axis, tuple) else sizes[0])
    return jax.lax.pmean(value, axis), jax.lax.pmean(grad, axis)

  grads = jax.shard_map(local, mesh=mesh, in_specs=(P(), P(), P(axis), P(axis), P(axis)), out_specs=(P(), P()))

  def step(x, opt_state, params, origins, directions, rgb):
    value, grad = grads(x, params, origins, directions, rgb)
    updates, opt_state = optimizer.update(grad, opt_state, x)
    return optax.apply_updates(x, updates), opt_state, value

  replicated = distributed.replicated(mesh)
  return jax.jit(optimizer.init, out_shardings=replicated), jax.jit(step)


def _fit(fitter, x0, params, mesh, origins_Nx3, directions_Nx3, colours_Nx3, steps: int, rays_per_step: int,
         seed: int) -> np.ndarray:
  """x fitted from `x0` by `steps` steps of `fitter`, each on `rays_per_step` of the rays given drawn at random
  (rounded up to a multiple of the mesh's devices; the same on every process, from `seed`)."""
  init, step = fitter
  count = -(-rays_per_step // mesh.size) * mesh.size
  mine = distributed.local_slice(count, mesh)
  x = jax.device_put(jnp.asarray(x0, jnp.float32), distributed.replicated(mesh))
  opt_state = init(x)
  rng = np.random.default_rng(seed)
  for _ in range(steps):
    pick = rng.integers(0, len(origins_Nx3), count)
    batch = (np.asarray(origins_Nx3[pick], np.float32), np.asarray(directions_Nx3[pick], np.float32),
             np.asarray(colours_Nx3[pick], np.float32))
    x, opt_state, _ = step(x, opt_state, params, *distributed.to_global(mesh, tuple(b[mine] for b in batch)))
    # One step in flight at a time: with the steps queued back to back, XLA:CPU's in-process collectives
    # deadlocked on 8 simulated devices (the all-reduce's rendezvous timed out with 6 of 8 arrived).
    jax.block_until_ready(x)
  return np.asarray(distributed.to_host(x))


def make_code_fitter(model, mesh, near: float, far: float, background, lr: float, ordered: bool = True):
  """(init, step): `init(code)` the Adam state of a code (A,); `step(code, opt_state, params, origins,
  directions, rgb)` -> (code, opt_state, loss), one Adam step on the mean squared error of the rays' colours
  rendered with `code` (model.apply without frames, no jitter: evaluation's samples); see _make_fitter."""
  def loss(code, params, origins, directions, rgb):
    out = model.apply(with_code(params, code), origins, directions, near, far, jnp.asarray(background))[-1]
    return jnp.mean(jnp.square(out["rgb"] - rgb))

  return _make_fitter(loss, mesh, optax.adam(lr), ordered)


def fit_code(fitter, params, mesh, c2w_4x4, intr: cameras.Intrinsics, image_HxWx3, pixel_center: float,
             steps: int, rays_per_step: int, seed: int) -> np.ndarray:
  """The appearance code (A,) fitted to the left half (columns < W // 2) of a held-out view: `steps` Adam
  steps from the mean code, each on `rays_per_step` of its pixels drawn at random (rounded up to a multiple
  of the mesh's devices; the same on every process, from `seed`)."""
  height, width = image_HxWx3.shape[:2]
  rows, cols = np.meshgrid(np.arange(height), np.arange(width // 2), indexing="ij")
  rows, cols = rows.ravel(), cols.ravel()
  origins, directions = cameras.rays_for_pixels(c2w_4x4, intr, rows, cols, pixel_center)
  colours = np.asarray(image_HxWx3, np.float32)[rows, cols]
  return _fit(fitter, mean_code(params), params, mesh, origins, directions, colours, steps, rays_per_step, seed)


def make_pose_fitter(model, mesh, near: float, far: float, background, lr: float, steps: int,
                     ordered: bool = True):
  """(init, step) of one held-out camera's correction (6,) [t, w] (nerf/pose_correction.py's form: the camera
  shifted by t and turned by exp(w) about its centre): Adam on the mean squared error of the rays' colours
  rendered through the corrected rays (model.apply without frames: the mean appearance code, evaluation's
  samples), its rate decayed log-linearly from `lr` to a tenth of it over `steps` (a fit that settles rather
  than jitters by `lr` about its optimum); see _make_fitter."""
  def loss(correction, params, origins, directions, rgb):
    origins, directions = pose_correction.correct_rays(origins, directions, correction)
    out = model.apply(params, origins, directions, near, far, jnp.asarray(background))[-1]
    return jnp.mean(jnp.square(out["rgb"] - rgb))

  schedule = optax.exponential_decay(lr, max(1, steps), 0.1)
  return _make_fitter(loss, mesh, optax.adam(schedule), ordered)


def fit_pose(fitter, params, mesh, c2w_4x4, intr: cameras.Intrinsics, image_HxWx3, pixel_center: float,
             steps: int, rays_per_step: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
  """(pose, correction): a held-out camera's pose fitted to its whole image from `c2w_4x4` (the aligned or
  given pose), `steps` Adam steps each on `rays_per_step` of its pixels drawn at random (as fit_code), and
  the correction (6,) [t, w] that carries `c2w_4x4` there ([exp(w) R | o + t], float64)."""
  origins, directions = cameras.image_rays(c2w_4x4, intr, pixel_center)
  colours = np.asarray(image_HxWx3, np.float32).reshape(-1, 3)
  correction = _fit(fitter, np.zeros(6), params, mesh, origins.reshape(-1, 3), directions.reshape(-1, 3), colours,
                    steps, rays_per_step, seed)
  return pose_correction.corrected_poses(np.asarray(c2w_4x4)[None], correction[None])[0], correction


def describe_correction(correction_6) -> dict:
  """A fitted camera correction as metrics.json reports it: its turn (degrees) and shift (scene units)."""
  correction = np.asarray(correction_6, np.float64)
  return {"rotation_deg": float(np.degrees(np.linalg.norm(correction[3:]))),
          "translation": float(np.linalg.norm(correction[:3]))}
