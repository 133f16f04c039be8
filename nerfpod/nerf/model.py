"""The NeRF model: sample along rays, query the field(s), composite; coarse-to-fine when configured."""
from typing import Any

import flax.linen as nn
import jax.numpy as jnp

from nerfpod.nerf import compositing, coord, fields, sampling


class NeRF(nn.Module):
  """Renders a batch of rays.

  `num_samples` stratified samples go to the coarse field. With `num_importance` > 0 (the paper's
  hierarchical sampling), that many more are drawn from the coarse weights by inverse CDF and the fine field
  is queried at the union of both sets; each level returns its own rendering, coarse first. A bounded field
  (the hash grid) has each ray's [near, far] clipped to its box first.

  `space` says where the field lives (nerf/coord.py): 'euclidean', the world itself; 'ndc', a forward-facing
  scene's NDC cube (the rays are mapped there first, with the view directions taken from the world rays as
  the original does, and near/far are NDC parameters in [0, 1]); 'contract', mip-NeRF 360's contracted ball
  of radius 2 (sample points are contracted before the field; rays are not clipped, every point lands in
  the ball). `spacing` places the samples evenly in distance ('linear') or in inverse distance ('inverse',
  for unbounded scenes with a far bound of 1e6): samples are drawn in s in [0, 1] and mapped to t.
  Randomness comes in as arrays of uniform numbers (None: deterministic evaluation), so the module is a
  pure function of its inputs. Every attribute comes from the config (`from_config`).
  """
  model_config: Any
  num_samples: int
  num_importance: int
  last_delta: float
  dtype: Any
  space: str = "euclidean"
  spacing: str = "linear"
  ndc_camera: tuple[float, float, float, float] | None = None  # (fx, fy, width, height) defining the NDC cube

  def _render(self, field, origins, directions, viewdirs, t_RxS, background):
    points = origins[..., None, :] + t_RxS[..., None] * directions[..., None, :]
    if self.space == "contract":
      points = coord.contract(points)
    dirs = jnp.broadcast_to(viewdirs[..., None, :], points.shape)
    rgb, sigma = field(points.reshape(-1, 3), dirs.reshape(-1, 3))
    rgb = rgb.reshape(points.shape)
    sigma = sigma.reshape(points.shape[:-1])
    out = compositing.composite(rgb, sigma, t_RxS, directions, last_delta=self.last_delta,
                                background=background)
    if self.space == "ndc":  # depth along the NDC camera's axis, disparity its inverse (coord.ndc_to_disparity)
      out["disparity"] = jnp.sum(out["weights"] * coord.ndc_to_disparity(t_RxS), axis=-1)
      out["depth"] = out["acc"] / jnp.maximum(out["disparity"], 1e-10)
    out["t"] = t_RxS
    return out

  def _distances(self, near, far, num: int, uniform):
    """Stratified ray distances (R, num): even in t ('linear'), or even in s and warped to t."""
    if self.spacing == "linear":
      return sampling.stratified(near, far, num, uniform)
    return coord.s_to_t(sampling.stratified(0.0, 1.0, num, uniform), near, far, self.spacing)

  @nn.compact
  def __call__(self, origins_Rx3, directions_Rx3, near, far, background,
               uniform_coarse_RxS=None, uniform_fine_RxN=None):
    """A list of renderings (dicts of rgb, depth, acc, disparity, weights, t), coarse first.

    near, far: floats or (R, 1); background: (3,) or (R, 3) (nerf.compositing.composite).
    """
    viewdirs = directions_Rx3 / jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
    if self.space == "ndc":
      if self.ndc_camera is None:
        raise ValueError("render.space='ndc' needs the scene's camera (from_config(..., ndc_camera=...))")
      origins_Rx3, directions_Rx3 = coord.ndc_rays(origins_Rx3, directions_Rx3, *self.ndc_camera, near=1.0)
    if self.model_config.field == "hashgrid" and self.space != "contract":  # bounded: sample inside its box
      near, far = sampling.clip_to_box(origins_Rx3, directions_Rx3, near, far,
                                       self.model_config.hashgrid.bound)
    t = self._distances(near, far, self.num_samples, uniform_coarse_RxS)
    t = jnp.broadcast_to(t, origins_Rx3.shape[:-1] + (self.num_samples,))
    coarse_field = fields.make_field(self.model_config, self.dtype, name="coarse")
    coarse = self._render(coarse_field, origins_Rx3, directions_Rx3, viewdirs, t, background)
    if self.num_importance == 0:
      return [coarse]
    # Importance samples are drawn in s, where the coarse samples are evenly spread ('linear': s is t).
    s = t if self.spacing == "linear" else coord.t_to_s(t, near, far, self.spacing)
    mids = 0.5 * (s[..., 1:] + s[..., :-1])
    s_fine = sampling.sample_pdf(mids, coarse["weights"][..., 1:-1], self.num_importance, uniform_fine_RxN)
    t_fine = s_fine if self.spacing == "linear" else coord.s_to_t(s_fine, near, far, self.spacing)
    t_all = jnp.sort(jnp.concatenate([t, t_fine], axis=-1), axis=-1)
    fine_field = fields.make_field(self.model_config, self.dtype, name="fine")
    fine = self._render(fine_field, origins_Rx3, directions_Rx3, viewdirs, t_all, background)
    return [coarse, fine]


def from_config(config, ndc_camera=None) -> NeRF:
  """The NeRF model that `config.model` and `config.render` describe. `ndc_camera` (fx, fy, width, height):
  the camera whose frustum is the NDC cube, needed with render.space='ndc' (the scene's training camera)."""
  dtype = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}[config.model.compute_dtype]
  render = config.render
  return NeRF(model_config=config.model, num_samples=render.num_samples, num_importance=render.num_importance,
              last_delta=render.last_delta, dtype=dtype, space=render.space, spacing=render.spacing,
              ndc_camera=None if ndc_camera is None else tuple(float(v) for v in ndc_camera))
