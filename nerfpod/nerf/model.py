"""The NeRF model: sample along rays, query the field(s), composite; coarse-to-fine when configured."""
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from nerfpod.nerf import compositing, fields, sampling


class NeRF(nn.Module):
  """Renders a batch of rays.

  `num_samples` stratified samples go to the coarse field. With `num_importance` > 0 (the paper's
  hierarchical sampling), that many more are drawn from the coarse weights by inverse CDF and the fine field
  is queried at the union of both sets; each level returns its own rendering, coarse first. A bounded field
  (the hash grid) has each ray's [near, far] clipped to its box first.
  Randomness comes in as arrays of uniform numbers (None: deterministic evaluation), so the module is a
  pure function of its inputs. Every attribute comes from the config (`from_config`).
  """
  model_config: Any
  num_samples: int
  num_importance: int
  last_delta: float
  dtype: Any
  grid_matmul_max_rows: int = 0  # hash grid: dense levels up to this many rows looked up by matmuls

  def _render(self, field, origins, directions, viewdirs, t_RxS, background):
    points = origins[..., None, :] + t_RxS[..., None] * directions[..., None, :]
    dirs = jnp.broadcast_to(viewdirs[..., None, :], points.shape)
    rgb, sigma = field(points.reshape(-1, 3), dirs.reshape(-1, 3))
    rgb = rgb.reshape(points.shape)
    sigma = sigma.reshape(points.shape[:-1])
    out = compositing.composite(rgb, sigma, t_RxS, directions, last_delta=self.last_delta,
                                background=background)
    out["t"] = t_RxS
    return out

  @nn.compact
  def __call__(self, origins_Rx3, directions_Rx3, near, far, background,
               uniform_coarse_RxS=None, uniform_fine_RxN=None):
    """A list of renderings (dicts of rgb, depth, acc, disparity, weights, t), coarse first.

    near, far: floats or (R, 1); background: (3,) or (R, 3) (nerf.compositing.composite).
    """
    viewdirs = directions_Rx3 / jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
    if self.model_config.field == "hashgrid":  # bounded: sample only inside its box
      near, far = sampling.clip_to_box(origins_Rx3, directions_Rx3, near, far,
                                       self.model_config.hashgrid.bound)
    t = sampling.stratified(near, far, self.num_samples, uniform_coarse_RxS)
    t = jnp.broadcast_to(t, origins_Rx3.shape[:-1] + (self.num_samples,))
    coarse_field = fields.make_field(self.model_config, self.dtype, "coarse", self.grid_matmul_max_rows)
    coarse = self._render(coarse_field, origins_Rx3, directions_Rx3, viewdirs, t, background)
    if self.num_importance == 0:
      return [coarse]
    mids = 0.5 * (t[..., 1:] + t[..., :-1])
    t_fine = sampling.sample_pdf(mids, coarse["weights"][..., 1:-1], self.num_importance,
                                 uniform_fine_RxN)
    t_all = jnp.sort(jnp.concatenate([t, t_fine], axis=-1), axis=-1)
    fine_field = fields.make_field(self.model_config, self.dtype, "fine", self.grid_matmul_max_rows)
    fine = self._render(fine_field, origins_Rx3, directions_Rx3, viewdirs, t_all, background)
    return [coarse, fine]


def grid_matmul_max_rows(config, backend: str) -> int:
  """How many rows a hash-grid level may have to be looked up by matmuls on `backend` (0: all gather).

  compile.hashgrid_lookup 'auto' takes matmuls on TPUs, where gathers and scatter-adds are slow (the README's
  pod section has the cost-model figures), and gathers elsewhere (a CPU or GPU gathers a row cheaply). The
  parameters are the same either way, so a checkpoint moves freely between backends.
  """
  lookup = config.compile.get("hashgrid_lookup", "gather")
  if lookup == "auto":
    lookup = "matmul" if backend == "tpu" else "gather"
  return int(config.compile.get("matmul_max_rows", 0)) if lookup == "matmul" else 0


def from_config(config, backend: str | None = None) -> NeRF:
  """The NeRF model that `config.model` and `config.render` describe, formulated for `backend` (default:
  JAX's; the pod compile tool asks for 'tpu' on a CPU)."""
  dtype = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}[config.model.compute_dtype]
  backend = backend or jax.default_backend()
  return NeRF(model_config=config.model, num_samples=config.render.num_samples,
              num_importance=config.render.num_importance, last_delta=config.render.last_delta,
              dtype=dtype, grid_matmul_max_rows=grid_matmul_max_rows(config, backend))
