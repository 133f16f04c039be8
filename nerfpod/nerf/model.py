"""The NeRF model: sample along rays, query the field(s), composite; coarse-to-fine or proposal sampling."""
from typing import Any

import flax.linen as nn
import jax.numpy as jnp

from nerfpod.nerf import compositing, fields, sampling, stepfun


class NeRF(nn.Module):
  """Renders a batch of rays, in one of three ways.

  - Stratified: `num_samples` stratified samples go to the field.
  - Hierarchical (`num_importance` > 0, the paper's): that many more are drawn from the coarse weights by
    inverse CDF and a fine field is queried at the union of both sets; each level returns its rendering.
  - Proposal (`proposal_samples`, mip-NeRF 360 / nerfacto): each round draws that many intervals from the
    previous round's histogram (the first from the whole ray) and a small density-only proposal field
    weighs them; the NeRF field is then queried at `num_samples` intervals drawn from the last proposal.
    Rounds work in the normalised distance s in [0, 1] (`sampling.linear_warp` maps it to t), and no
    gradient reaches the sample positions. The rendering carries `s_edges` and, per proposal round, its
    (s_edges, weights): train.py supervises the proposals with the interlevel loss.

  A bounded field (the hash grid) has each ray's [near, far] clipped to its box first.
  Randomness comes in as arrays of uniform numbers, one (R, n) array per round of `sample_counts()` (none:
  deterministic evaluation), so the module is a pure function of its inputs. Every attribute comes from
  the config (`from_config`).
  """
  model_config: Any
  num_samples: int
  num_importance: int
  last_delta: float
  dtype: Any
  proposal_samples: tuple = ()

  def sample_counts(self) -> tuple:
    """How many uniform numbers per ray each sampling round takes, in the order __call__ takes them."""
    if self.proposal_samples:
      return tuple(self.proposal_samples) + (self.num_samples,)
    return (self.num_samples,) + ((self.num_importance,) if self.num_importance else ())

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
  def __call__(self, origins_Rx3, directions_Rx3, near, far, background, *uniforms):
    """A list of renderings (dicts of rgb, depth, acc, disparity, weights, t), coarse first.

    near, far: floats or (R, 1); background: (3,) or (R, 3) (nerf.compositing.composite); uniforms: one
    (R, n) array of numbers in [0, 1) per entry of `sample_counts()`, or none at all (evaluation).
    """
    uniforms = uniforms or (None,) * len(self.sample_counts())
    viewdirs = directions_Rx3 / jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
    if self.model_config.field == "hashgrid":  # bounded: sample only inside its box
      near, far = sampling.clip_to_box(origins_Rx3, directions_Rx3, near, far,
                                       self.model_config.hashgrid.bound)
    if self.proposal_samples:
      return [self._proposal_render(origins_Rx3, directions_Rx3, viewdirs, near, far, background, uniforms)]
    t = sampling.stratified(near, far, self.num_samples, uniforms[0])
    t = jnp.broadcast_to(t, origins_Rx3.shape[:-1] + (self.num_samples,))
    coarse_field = fields.make_field(self.model_config, self.dtype, name="coarse")
    coarse = self._render(coarse_field, origins_Rx3, directions_Rx3, viewdirs, t, background)
    if self.num_importance == 0:
      return [coarse]
    mids = 0.5 * (t[..., 1:] + t[..., :-1])
    t_fine = sampling.sample_pdf(mids, coarse["weights"][..., 1:-1], self.num_importance, uniforms[1])
    t_all = jnp.sort(jnp.concatenate([t, t_fine], axis=-1), axis=-1)
    fine_field = fields.make_field(self.model_config, self.dtype, name="fine")
    fine = self._render(fine_field, origins_Rx3, directions_Rx3, viewdirs, t_all, background)
    return [coarse, fine]

  def _proposal_render(self, origins, directions, viewdirs, near, far, background, uniforms):
    warp = sampling.linear_warp(near, far)  # s -> t; the one line an unbounded scene's warp replaces
    rays = origins.shape[:-1]
    s_edges = jnp.broadcast_to(jnp.array([0.0, 1.0]), rays + (2,))  # round 0 draws from the whole ray
    weights = jnp.ones(rays + (1,))
    proposals = []
    for i, count in enumerate(self.proposal_samples):
      s_edges = stepfun.sample_intervals(s_edges, weights, count, uniforms[i])
      t_edges = warp(s_edges)
      t_mids = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
      points = origins[..., None, :] + t_mids[..., None] * directions[..., None, :]
      field = fields.make_proposal_field(self.model_config, self.dtype, name=f"proposal_{i}")
      sigma = field(points.reshape(-1, 3)).reshape(t_mids.shape)
      weights = compositing.interval_weights(sigma, t_edges, directions)
      proposals.append({"s_edges": s_edges, "weights": weights})
    s_edges = stepfun.sample_intervals(s_edges, weights, self.num_samples, uniforms[-1])
    t_edges = warp(s_edges)
    t_mids = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
    points = origins[..., None, :] + t_mids[..., None] * directions[..., None, :]
    dirs = jnp.broadcast_to(viewdirs[..., None, :], points.shape)
    field = fields.make_field(self.model_config, self.dtype, name="coarse")
    rgb, sigma = field(points.reshape(-1, 3), dirs.reshape(-1, 3))
    out = compositing.composite_intervals(rgb.reshape(points.shape), sigma.reshape(t_mids.shape), t_edges,
                                          directions, background=background)
    out.update(t=t_mids, s_edges=s_edges, proposals=proposals)
    return out


def from_config(config) -> NeRF:
  """The NeRF model that `config.model` and `config.render` describe."""
  dtype = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}[config.model.compute_dtype]
  return NeRF(model_config=config.model, num_samples=config.render.num_samples,
              num_importance=config.render.num_importance, last_delta=config.render.last_delta,
              dtype=dtype, proposal_samples=tuple(config.render.proposal_samples))
