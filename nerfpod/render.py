"""Rendering whole images with a trained model, split in chunks over every device of every host."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P

from nerfpod import distributed
from nerfpod.nerf import cameras

OUTPUTS = ("rgb", "depth", "acc", "disparity")


def make_render_fn(model, mesh, near: float, far: float, background):
  """(params, origins, directions) -> final-level rgb/depth/acc/disparity; rays sharded over the mesh."""
  def local(params, origins, directions):
    out = model.apply(params, origins, directions, near, far, jnp.asarray(background))[-1]
    return {k: out[k] for k in OUTPUTS}
  axis = distributed.DATA_AXIS
  return jax.jit(jax.shard_map(local, mesh=mesh, in_specs=(P(), P(axis), P(axis)), out_specs=P(axis)))


def render_rays(render_fn, params, mesh, origins_Nx3, directions_Nx3, chunk: int) -> dict:
  """Renders N rays in global chunks of `chunk` rays; every process passes the same rays and gets all results.

  Each process feeds only its own share of every chunk; the last chunk is padded.
  """
  n = len(origins_Nx3)
  chunk = max(jax.device_count(), chunk - chunk % jax.device_count())
  padded = -(-n // chunk) * chunk
  pad = lambda x: np.concatenate([x, np.repeat(x[-1:], padded - n, axis=0)]) if padded > n else x
  origins, directions = pad(origins_Nx3), pad(directions_Nx3)
  rows = distributed.local_slice(chunk)
  pieces = []
  for start in range(0, padded, chunk):
    o = origins[start:start + chunk][rows]
    d = directions[start:start + chunk][rows]
    out = render_fn(params, *distributed.to_global(mesh, (o, d)))
    pieces.append(distributed.to_host(out))
  return {k: np.concatenate([p[k] for p in pieces])[:n] for k in OUTPUTS}


def render_image(render_fn, params, mesh, c2w, intr: cameras.Intrinsics, pixel_center: float,
                 chunk: int) -> dict:
  """One full image: rgb (H, W, 3), depth, acc and disparity (H, W), float32 NumPy."""
  origins, directions = cameras.image_rays(c2w, intr, pixel_center)
  out = render_rays(render_fn, params, mesh, origins.reshape(-1, 3), directions.reshape(-1, 3), chunk)
  return {k: v.reshape((intr.height, intr.width) + v.shape[1:]) for k, v in out.items()}
