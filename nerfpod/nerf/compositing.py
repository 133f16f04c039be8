"""Alpha compositing of colours and densities sampled along rays: NeRF's volume-rendering quadrature (eq. 3)."""
import jax.numpy as jnp


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
  deltas = deltas * jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
  optical_depth = sigma_RxS * deltas
  alpha = 1.0 - jnp.exp(-optical_depth)
  accumulated = jnp.concatenate(
      [jnp.zeros_like(optical_depth[..., :1]), jnp.cumsum(optical_depth[..., :-1], axis=-1)], axis=-1)
  transmittance = jnp.exp(-accumulated)
  weights = alpha * transmittance
  acc = jnp.sum(weights, axis=-1)
  rgb = jnp.sum(weights[..., None] * rgb_RxSx3, axis=-2)
  if background is not None:
    rgb = rgb + (1.0 - acc[..., None]) * jnp.asarray(background, rgb.dtype)
  depth = jnp.sum(weights * t_RxS, axis=-1)
  disparity = acc / jnp.maximum(depth, 1e-10)
  return {"rgb": rgb, "depth": depth, "acc": acc, "disparity": disparity, "weights": weights}
