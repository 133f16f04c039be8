"""The renderer: images of a trained model, its rays split in chunks over the devices of a mesh.

"Render" in nerfpod means this: pixels of the trained field (evaluation, previews, orbit frames, the
viewer). The volume-rendering arithmetic itself is nerf/compositing.py; config.render holds its settings.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P

from nerfpod import distributed
from nerfpod.nerf import cameras, compositing, regions
from nerfpod.nerf import model as nerf_model

def make_renderer(model, mesh, near: float, far: float, background, compiler_options: dict | None = None):
  """(params, origins, directions) -> final-level rgb/depth/acc/disparity; rays sharded over the mesh (a region
  model's over its batch axes, each device rendering its own regions: _region_renderer),
  compiled with XLA's `compiler_options` (compilation.compiler_options)."""
  def local(params, origins, directions):
    out = model.apply(params, origins, directions, near, far, jnp.asarray(background))[-1]
    return {k: out[k] for k in compositing.OUTPUTS}
  axis = distributed.batch_axes(mesh)  # every axis: DATA_AXIS, or (SLICE_AXIS, DATA_AXIS) across slices
  if model.regions > 1 and distributed.num_regions(mesh) > 1:
    return _region_renderer(model, mesh, near, far, background, compiler_options)
  return jax.jit(jax.shard_map(local, mesh=mesh, in_specs=(P(), P(axis), P(axis)), out_specs=P(axis)),
                 compiler_options=compiler_options)


def _region_renderer(model, mesh, near: float, far: float, background, compiler_options):
  """make_renderer's for a model of K regions on a mesh with a region axis: each device renders its rays
  through its own regions with its share of their parameters (as the train step does), the per-ray partial
  sums are gathered over the region axis and composited; no device holds another region's fields."""
  axis = distributed.batch_axes(mesh)
  local_count = model.regions // distributed.num_regions(mesh)

  def local(params, origins, directions):
    ids = jax.lax.axis_index(distributed.REGION_AXIS) * local_count + jnp.arange(local_count)
    partials, _ = model.apply(params, origins, directions, near, far, ids, method="render_partials")
    out = regions.composite_regions(distributed.gather_regions(partials), jnp.asarray(background))
    return {k: out[k] for k in compositing.OUTPUTS}

  def render(params, origins, directions):
    specs = jax.tree_util.tree_map_with_path(
        lambda path, _: P(distributed.REGION_AXIS) if nerf_model.in_region(path) else P(), params)
    return jax.shard_map(local, mesh=mesh, in_specs=(specs, P(axis), P(axis)), out_specs=P(axis))(
        params, origins, directions)

  return jax.jit(render, compiler_options=compiler_options)


def balanced_chunk(chunk: int, num_rays: int, devices: int) -> int:
  """Rays per call for `num_rays` rays in calls of at most `chunk` (at least `devices`), each a multiple of
  `devices`: as few calls as `chunk` allows, split evenly, so that the last call pads as few rays as it can
  (10,000 rays in chunks of 4,096: 3 calls of 3,334 on one device rather than 2 of 4,096 and one of 1,808 padded to
  4,096, a fifth less work)."""
  largest = max(devices, chunk - chunk % devices)
  calls = -(-num_rays // largest)
  per_call = -(-num_rays // calls)
  return -(-per_call // devices) * devices


def render_rays(renderer, params, mesh, origins_Nx3, directions_Nx3, chunk: int, cancelled=None,
                fixed_chunk: bool = False) -> dict | None:
  """Renders N rays in calls of at most `chunk` rays (a multiple of the mesh's device count) sharded over `mesh`.

  On a mesh over every host, every process passes the same rays, feeds only its own share of each chunk
  and gets all results back; a process of its own (the viewer) passes the mesh of every device it has. The
  rays are split into as few calls as `chunk` allows, of equal size (balanced_chunk), the last padded;
  `fixed_chunk`: every call has `chunk` rays instead (one compilation for inputs of any size, as the viewer
  wants).

  Without `cancelled`, every chunk is dispatched before any is fetched. With it (a function of no
  arguments), one chunk is in flight at a time and `cancelled()` is asked before each next one: True
  abandons the rendering and returns None (the viewer, whose camera moved).
  """
  n, devices = len(origins_Nx3), mesh.size
  chunk = max(devices, chunk - chunk % devices) if fixed_chunk else balanced_chunk(chunk, n, devices)
  padded = -(-n // chunk) * chunk
  pad = lambda x: np.concatenate([x, np.repeat(x[-1:], padded - n, axis=0)]) if padded > n else x
  origins, directions = pad(origins_Nx3), pad(directions_Nx3)
  rows = distributed.local_slice(chunk, mesh)
  pieces = []
  for start in range(0, padded, chunk):
    if cancelled is not None:
      if pieces:
        jax.block_until_ready(pieces[-1])
      if cancelled():
        return None
    pieces.append(renderer(params, *distributed.to_global(
        mesh, (origins[start:start + chunk][rows], directions[start:start + chunk][rows]))))
  pieces = distributed.to_host(pieces)
  return {k: np.concatenate([p[k] for p in pieces])[:n] for k in compositing.OUTPUTS}


def render_image(renderer, params, mesh, c2w_4x4, intr: cameras.Intrinsics, pixel_center: float,
                 chunk: int) -> dict:
  """One full image: rgb (H, W, 3), depth, acc and disparity (H, W), float32 NumPy."""
  origins, directions = cameras.image_rays(c2w_4x4, intr, pixel_center)
  out = render_rays(renderer, params, mesh, origins.reshape(-1, 3), directions.reshape(-1, 3), chunk)
  return {k: v.reshape((intr.height, intr.width) + v.shape[1:]) for k, v in out.items()}
