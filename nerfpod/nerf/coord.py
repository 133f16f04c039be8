"""Coordinate spaces for real scenes: NDC rays (forward-facing), scene contraction (unbounded) and the warps
of ray distance that decide how samples are spaced.

- NDC (the original NeRF, appendix C; its `ndc_rays`): a forward-facing scene's frustum, from the near plane
  z = -near out to infinity, maps to the cube [-1, 1]^3; straight rays stay straight, and the NDC ray
  parameter t' in [0, 1] runs linearly in *disparity* (1 / depth), so evenly spaced samples in t' put most
  samples near the camera and still reach infinity.
- Contraction (mip-NeRF 360, eq. 10; multinerf coord.contract): points inside the unit ball stay where they
  are, points outside are pulled into the shell 1 < |x| < 2, so all of unbounded space fits in the ball of
  radius 2 and a bounded field (the hash grid on [-2, 2]^3) can model the background.
- Ray-distance warps: samples are placed evenly in a normalised s in [0, 1] and mapped to distances t by
  s_to_t. 'linear' is t = near + s (far - near); 'inverse' (mip-NeRF 360's spacing) is even in 1 / t,
  s = (1/t - 1/near) / (1/far - 1/near), which spends samples on the foreground and still reaches a far
  bound of 1e6; 'piecewise' (nerfacto's UniformLinDispPiecewiseSampler) is even in t up to t = 1 and even
  in 1 / t beyond, through g(t) = t / 2 (t < 1), 1 - 1 / (2 t) (t >= 1): s = (g(t) - g(near)) /
  (g(far) - g(near)), so a capture scaled to distance 1 (its cameras within 1 of the centre) gets evenly
  spread samples where its object is and inverse-distance ones in the background. Each warp is a
  (t_to_s, s_to_t) pair of pure functions, so any sampler (stratified, the fine network's inverse CDF, a
  proposal sampler) can work in s and hand back t.

All functions are pure jnp and differentiable, and work on any leading shape.
"""
import jax.numpy as jnp


def ndc_rays(origins_Rx3, directions_Rx3, focal_x: float, focal_y: float, width: float, height: float,
             near: float = 1.0):
  """The original NeRF's `ndc_rays(H, W, focal, near, rays_o, rays_d)`, with a focal length per axis.

  Each ray is first moved along itself to the plane z = -near, then projected: with (ox, oy, oz) that
  shifted origin and (dx, dy, dz) the direction (camera space of the scene's frame: looking down -z),
      o' = (-(2 fx / W) ox / oz, -(2 fy / H) oy / oz, 1 + 2 near / oz)
      d' = (-(2 fx / W) (dx / dz - ox / oz), -(2 fy / H) (dy / dz - oy / oz), -2 near / oz)
  so that o' + t' d' for t' in [0, 1) is the NDC image of the ray from the near plane to infinity. Returns
  (origins', directions'), not normalised: t' = 1 is infinitely far away.
  """
  ox, oy, oz = (origins_Rx3[..., i] for i in range(3))
  dx, dy, dz = (directions_Rx3[..., i] for i in range(3))
  t = -(near + oz) / dz
  ox, oy, oz = ox + t * dx, oy + t * dy, oz + t * dz
  ax, ay = -2.0 * focal_x / width, -2.0 * focal_y / height
  origins = jnp.stack([ax * ox / oz, ay * oy / oz, 1.0 + 2.0 * near / oz], axis=-1)
  directions = jnp.stack([ax * (dx / dz - ox / oz), ay * (dy / dz - oy / oz), -2.0 * near / oz], axis=-1)
  return origins, directions


def ndc_to_disparity(t_ndc, near: float = 1.0):
  """Inverse depth (1 / distance in front of the NDC camera, along its -z axis) of the point at NDC ray
  parameter t': its NDC z is 2 t' - 1 = 1 + 2 near / z, so 1 / depth = 1 / -z = (1 - t') / near. Linear in
  t', so the expected disparity of a ray is this of its expected t' (with the weights' sum for 1)."""
  return (1.0 - t_ndc) / near


def contract(points_Nx3):
  """mip-NeRF 360's contraction: x where |x| <= 1, else (2 - 1 / |x|) x / |x| (L2 norm). Continuous, with
  a continuous first derivative; maps R^3 onto the open ball of radius 2."""
  norm_sq = jnp.maximum(jnp.sum(points_Nx3 ** 2, axis=-1, keepdims=True), 1e-20)
  norm = jnp.sqrt(norm_sq)
  # Written with the safe norm in both branches so the gradient is finite everywhere.
  return jnp.where(norm <= 1.0, points_Nx3, (2.0 - 1.0 / norm) * points_Nx3 / norm)


def contraction_scale(points_Nx3):
  """How much `contract` shrinks a small ball about each point (N, 1): the cube root of its Jacobian's
  determinant (mip-NeRF 360 and Zip-NeRF's isotropic approximation). 1 inside the unit ball; outside, radially
  1 / |x|^2 and tangentially (2 - 1 / |x|) / |x|, so (2 |x| - 1)^(2/3) / |x|^2."""
  norm = jnp.sqrt(jnp.maximum(jnp.sum(points_Nx3 ** 2, axis=-1, keepdims=True), 1e-20))
  safe = jnp.maximum(norm, 1.0)
  return jnp.where(norm <= 1.0, 1.0, (2.0 * safe - 1.0) ** (2.0 / 3.0) / safe ** 2)


def _piecewise_rest(t):
  """1 - g(t) of nerfacto's lin-disp map g (t / 2 below 1, 1 - 1 / (2 t) from 1 on): 1 - t / 2, then 1 / (2 t).
  Kept as what remains to 1, so that far bounds of 1e6 keep their digits (1 - g would round them away)."""
  return jnp.where(t < 1.0, 1.0 - 0.5 * t, 0.5 / jnp.maximum(t, 1.0))


def _piecewise_rest_inverse(h):
  """The t whose _piecewise_rest is h in (0, 1]."""
  return jnp.where(h > 0.5, 2.0 * (1.0 - h), 0.5 / jnp.clip(h, 1e-30, 0.5))


def t_to_s(t, near, far, spacing: str):
  """Ray distance t in [near, far] -> normalised s in [0, 1] under `spacing` ('linear', 'inverse' or
  'piecewise')."""
  if spacing == "linear":
    return (t - near) / (far - near)
  if spacing == "inverse":
    return (1.0 / t - 1.0 / near) / (1.0 / far - 1.0 / near)
  if spacing == "piecewise":
    h_near = _piecewise_rest(near)
    return (h_near - _piecewise_rest(t)) / (h_near - _piecewise_rest(far))
  raise ValueError(f"unknown spacing {spacing!r}")  # nerfpod.schema refuses it first


def s_to_t(s, near, far, spacing: str):
  """Normalised s in [0, 1] -> ray distance t in [near, far]: the inverse of `t_to_s`. 'inverse' needs
  near > 0 (schema rule)."""
  if spacing == "linear":
    return near * (1.0 - s) + far * s
  if spacing == "inverse":
    return 1.0 / (s / far + (1.0 - s) / near)
  if spacing == "piecewise":
    return _piecewise_rest_inverse((1.0 - s) * _piecewise_rest(near) + s * _piecewise_rest(far))
  raise ValueError(f"unknown spacing {spacing!r}")
