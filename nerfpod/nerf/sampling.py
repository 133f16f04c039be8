"""Where along each ray the field is queried: stratified samples, rays clipped to a box, the distance warp.

(Inverse-CDF sampling from a histogram along the ray, hierarchical and proposal alike, is nerf/stepfun.py.)
"""
import jax.numpy as jnp


def stratified(near, far, num_samples: int, uniform_RxS=None):
  """Ray parameters t of `num_samples` samples per ray between near and far, sorted, shape (R, S).

  With `uniform_RxS` (numbers in [0, 1)), one sample is drawn uniformly inside each of S equal bins whose
  edges are the midpoints of linspace(near, far, S) (the original NeRF code); without it, the bin centres
  linspace(near, far, S) themselves (deterministic, for evaluation). near/far broadcast against (R, 1).
  """
  s = jnp.linspace(0.0, 1.0, num_samples)
  t = near * (1.0 - s) + far * s  # (S,) or (R, S)
  if uniform_RxS is None:
    return jnp.broadcast_to(t, jnp.broadcast_shapes(jnp.shape(t), (1, num_samples)))
  mids = 0.5 * (t[..., 1:] + t[..., :-1])
  upper = jnp.concatenate([mids, t[..., -1:]], axis=-1)
  lower = jnp.concatenate([t[..., :1], mids], axis=-1)
  return lower + (upper - lower) * uniform_RxS


def clip_to_box(origins_Rx3, directions_Rx3, near, far, bound: float):
  """Per-ray [near, far] shrunk to where the ray crosses the box [-bound, bound]^3 (slab method).

  Bounded fields (the hash grid) are empty outside their box, so samples there are wasted. Rays that miss
  the box get an empty-but-valid interval at `near` (their samples see no density). Returns (R, 1) arrays.
  """
  safe = jnp.where(jnp.abs(directions_Rx3) < 1e-12, 1e-12, directions_Rx3)
  t0 = (-bound - origins_Rx3) / safe
  t1 = (bound - origins_Rx3) / safe
  enter = jnp.max(jnp.minimum(t0, t1), axis=-1, keepdims=True)
  leave = jnp.min(jnp.maximum(t0, t1), axis=-1, keepdims=True)
  lo = jnp.clip(enter, near, far)
  hi = jnp.clip(leave, near, far)
  hit = hi > lo
  return jnp.where(hit, lo, near), jnp.where(hit, hi, near + 1e-3)


def linear_warp(near, far):
  """s -> t: the normalised ray distance s in [0, 1] (where proposal sampling works) to the ray parameter t,
  linearly from near to far (object scenes). near/far broadcast against (R, 1). An unbounded scene swaps in
  another warp of the same form (e.g. samples spaced in inverse distance), and nothing else changes."""
  return lambda s: near + s * (far - near)
