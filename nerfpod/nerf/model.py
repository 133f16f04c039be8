"""The NeRF renderer: sample along rays, query the field(s), composite; coarse-to-fine when configured."""
from typing import Any

import flax.linen as nn
import jax.numpy as jnp

from nerfpod.nerf import fields, rendering, sampling


class NeRF(nn.Module):
  """Renders a batch of rays.

  `num_samples` stratified samples go to the coarse field. With `num_importance` > 0 (the paper's
  hierarchical sampling), that many more are drawn from the coarse weights by inverse CDF and the fine field
  is queried at the union of both sets; each level returns its own rendering, coarse first. A bounded field
  (the hash grid) has each ray's [near, far] clipped to its box first.
  Randomness comes in as arrays of uniform numbers (None: deterministic evaluation), so the module is a
  pure function of its inputs.
  """
  model_config: Any
  num_samples: int
  num_importance: int
  last_delta: float = 1e10
  dtype: Any = jnp.float32

  def setup(self):
    self.coarse = fields.make_field(self.model_config, self.dtype)
    if self.num_importance > 0:
      self.fine = fields.make_field(self.model_config, self.dtype)

  def _render(self, field, origins, directions, viewdirs, t_RxS, background):
    points = origins[..., None, :] + t_RxS[..., None] * directions[..., None, :]
    dirs = jnp.broadcast_to(viewdirs[..., None, :], points.shape)
    rgb, sigma = field(points.reshape(-1, 3), dirs.reshape(-1, 3))
    rgb = rgb.reshape(points.shape)
    sigma = sigma.reshape(points.shape[:-1])
    out = rendering.volume_render(rgb, sigma, t_RxS, directions, last_delta=self.last_delta,
                                  background_3=background)
    out["t"] = t_RxS
    return out

  def __call__(self, origins_Rx3, directions_Rx3, near, far, background_3,
               uniform_coarse_RxS=None, uniform_fine_RxN=None):
    viewdirs = directions_Rx3 / jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
    if self.model_config.field == "hashgrid":  # bounded: sample only inside its box
      near, far = sampling.clip_to_box(origins_Rx3, directions_Rx3, near, far,
                                       self.model_config.hashgrid.bound)
    t = sampling.stratified(near, far, self.num_samples, uniform_coarse_RxS)
    t = jnp.broadcast_to(t, origins_Rx3.shape[:-1] + (self.num_samples,))
    coarse = self._render(self.coarse, origins_Rx3, directions_Rx3, viewdirs, t, background_3)
    if self.num_importance == 0:
      return [coarse]
    mids = 0.5 * (t[..., 1:] + t[..., :-1])
    t_fine = sampling.sample_pdf(mids, coarse["weights"][..., 1:-1], self.num_importance,
                                 uniform_fine_RxN)
    t_all = jnp.sort(jnp.concatenate([t, t_fine], axis=-1), axis=-1)
    fine = self._render(self.fine, origins_Rx3, directions_Rx3, viewdirs, t_all, background_3)
    return [coarse, fine]


def from_config(config) -> NeRF:
  """The NeRF renderer that `config.model` and `config.render` describe."""
  dtype = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}[config.model.compute_dtype]
  return NeRF(model_config=config.model, num_samples=config.render.num_samples,
              num_importance=config.render.num_importance, last_delta=config.render.last_delta,
              dtype=dtype)
