"""Alpha compositing of colours and densities sampled along rays: NeRF's volume-rendering quadrature (eq. 3)."""
import jax.numpy as jnp

# What a rendered ray carries (compositing's per-ray outputs bar the weights): every renderer, archive,
# video and viewer channel, by these names and in this order.
OUTPUTS = ("rgb", "depth", "acc", "disparity")


def composite(rgb_RxSx3, sigma_RxS, t_RxS, directions_Rx3, *, last_delta: float, background=None):
  """Composites samples at ray parameters t into pixel values.

  The ray's length element is |d| dt, so densities are per unit of world distance whatever the length of
  `directions`. The last sample's interval is `last_delta` long (1e10: it absorbs everything left, as in the
  paper). Transmittance is computed in log space, T_i = exp(-sum_{j<i} sigma_j delta_j), which stays
  accurate where the product form of the original code loses precision.

  `background`: a colour (3,) or one per ray (R, 3), filling what the samples leave transparent; None: none.
  Returns a dict: rgb (R,3), depth (R,) (expected t, 0 where nothing was hit), acc (R,) accumulated opacity,
  disparity (R,) = acc / depth, and weights (R,S).
  """
  deltas = jnp.diff(t_RxS, axis=-1)
  deltas = jnp.concatenate([deltas, jnp.full_like(deltas[..., :1], last_delta)], axis=-1)
  return _composite(rgb_RxSx3, sigma_RxS, t_RxS, deltas, directions_Rx3, background)


def interval_weights(sigma_RxS, t_edges_RxS1, directions_Rx3):
  """Weights (R, S) of samples that each fill an interval [t_i, t_{i+1}] (proposal sampling): the same
  quadrature, with every interval's length known exactly (no open last interval)."""
  deltas = jnp.diff(t_edges_RxS1, axis=-1) * jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
  return _weights(sigma_RxS * deltas)


def composite_intervals(rgb_RxSx3, sigma_RxS, t_edges_RxS1, directions_Rx3, *, background=None):
  """`composite` for samples that each fill an interval [t_i, t_{i+1}] (proposal sampling): the colour
  and density at the interval's midpoint hold over its exact length. Depth is the expected midpoint."""
  mids = 0.5 * (t_edges_RxS1[..., 1:] + t_edges_RxS1[..., :-1])
  return _composite(rgb_RxSx3, sigma_RxS, mids, jnp.diff(t_edges_RxS1, axis=-1), directions_Rx3, background)


def _weights(optical_depth_RxS):
  """w_i = (1 - exp(-tau_i)) T_i with T_i = exp(-sum_{j<i} tau_j), in log space."""
  alpha = 1.0 - jnp.exp(-optical_depth_RxS)
  accumulated = jnp.concatenate(
      [jnp.zeros_like(optical_depth_RxS[..., :1]), jnp.cumsum(optical_depth_RxS[..., :-1], axis=-1)], axis=-1)
  return alpha * jnp.exp(-accumulated)


def _composite(rgb_RxSx3, sigma_RxS, t_RxS, deltas_RxS, directions_Rx3, background):
  """The quadrature shared by both: samples at t with intervals of (ray-parameter) length deltas."""
  deltas = deltas_RxS * jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
  weights = _weights(sigma_RxS * deltas)
  acc = jnp.sum(weights, axis=-1)
  rgb = jnp.sum(weights[..., None] * rgb_RxSx3, axis=-2)
  if background is not None:
    rgb = rgb + (1.0 - acc[..., None]) * jnp.asarray(background, rgb.dtype)
  depth = jnp.sum(weights * t_RxS, axis=-1)
  disparity = acc / jnp.maximum(depth, 1e-10)
  return {"rgb": rgb, "depth": depth, "acc": acc, "disparity": disparity, "weights": weights}
