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

evaluate.py renders and scores each; this module holds what they need: the aligned held-out poses and the
code fit, a compiled program over the run's mesh like the renderer (rays sharded over its batch axes, the
gradient averaged), so it spans the whole slice on a pod as every program does.
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


def make_code_fitter(model, mesh, near: float, far: float, background, lr: float, ordered: bool = True):
  """(init, step): `init(code)` the Adam state of a code (A,); `step(code, opt_state, params, origins,
  directions, rgb)` -> (code, opt_state, loss), one Adam step on the mean squared error of the rays' colours
  rendered with `code` (model.apply without frames, no jitter: evaluation's samples), rays sharded over the
  mesh's batch axes and the gradient averaged over them (`ordered`: by distributed.ordered_mean, as the train
  step's under compile.gradient_mean, so that 2 processes x 4 devices fit the bits of 1 x 8). Only the code
  moves: the field's parameters are an input, never an output."""
  optimizer = optax.adam(lr)
  axis = distributed.batch_axes(mesh)

  def loss(code, params, origins, directions, rgb):
    out = model.apply(with_code(params, code), origins, directions, near, far, jnp.asarray(background))[-1]
    return jnp.mean(jnp.square(out["rgb"] - rgb))

  def local(code, params, origins, directions, rgb):
    value, grad = jax.value_and_grad(loss)(code, params, origins, directions, rgb)
    if ordered:
      sizes = distributed.batch_axis_sizes(mesh)
      return distributed.ordered_mean((value, grad), axis, sizes if isinstance(axis, tuple) else sizes[0])
    return jax.lax.pmean(value, axis), jax.lax.pmean(grad, axis)

  grads = jax.shard_map(local, mesh=mesh, in_specs=(P(), P(), P(axis), P(axis), P(axis)), out_specs=(P(), P()))

  def step(code, opt_state, params, origins, directions, rgb):
    value, grad = grads(code, params, origins, directions, rgb)
    updates, opt_state = optimizer.update(grad, opt_state, code)
    return optax.apply_updates(code, updates), opt_state, value

  replicated = distributed.replicated(mesh)
  return jax.jit(optimizer.init, out_shardings=replicated), jax.jit(step)


def fit_code(fitter, params, mesh, c2w_4x4, intr: cameras.Intrinsics, image_HxWx3, pixel_center: float,
             steps: int, rays_per_step: int, seed: int) -> np.ndarray:
  """The appearance code (A,) fitted to the left half (columns < W // 2) of a held-out view: `steps` Adam
  steps from the mean code, each on `rays_per_step` of its pixels drawn at random (rounded up to a multiple
  of the mesh's devices; the same on every process, from `seed`)."""
  init, step = fitter
  height, width = image_HxWx3.shape[:2]
  half = width // 2
  rows, cols = np.meshgrid(np.arange(height), np.arange(half), indexing="ij")
  rows, cols = rows.ravel(), cols.ravel()
  origins, directions = cameras.rays_for_pixels(c2w_4x4, intr, rows, cols, pixel_center)
  colours = np.asarray(image_HxWx3, np.float32)[rows, cols]
  count = -(-rays_per_step // mesh.size) * mesh.size
  mine = distributed.local_slice(count, mesh)
  replicated = distributed.replicated(mesh)
  code = jax.device_put(jnp.asarray(mean_code(params), jnp.float32), replicated)
  opt_state = init(code)
  rng = np.random.default_rng(seed)
  for _ in range(steps):
    pick = rng.integers(0, len(rows), count)
    batch = (np.asarray(origins[pick], np.float32), np.asarray(directions[pick], np.float32), colours[pick])
    code, opt_state, _ = step(code, opt_state, params,
                              *distributed.to_global(mesh, tuple(x[mine] for x in batch)))
    # One step in flight at a time: with the steps queued back to back, XLA:CPU's in-process collectives
    # deadlocked on 8 simulated devices (the all-reduce's rendezvous timed out with 6 of 8 arrived).
    jax.block_until_ready(code)
  return np.asarray(distributed.to_host(code))
