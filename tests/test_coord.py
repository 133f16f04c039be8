"""Coordinate spaces (nerf/coord.py): NDC rays against the original code and a brute-force projection,
the contraction's continuity, range and inverse, and the ray-distance warps."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nerfpod.nerf import cameras, coord

# One program each rather than one per operation; the cameras' numbers (Python floats) static, as they are to an
# eager call.
_ndc_rays = jax.jit(coord.ndc_rays, static_argnums=(2, 3, 4, 5, 6))
_ndc_to_disparity = jax.jit(coord.ndc_to_disparity, static_argnums=1)
_contract = jax.jit(coord.contract)

def _reference_ndc_rays(H, W, focal, near, rays_o, rays_d):
  """bmild/nerf run_nerf_helpers.ndc_rays, verbatim but for tf -> np."""
  t = -(near + rays_o[..., 2]) / rays_d[..., 2]
  rays_o = rays_o + t[..., None] * rays_d
  o0 = -1. / (W / (2. * focal)) * rays_o[..., 0] / rays_o[..., 2]
  o1 = -1. / (H / (2. * focal)) * rays_o[..., 1] / rays_o[..., 2]
  o2 = 1. + 2. * near / rays_o[..., 2]
  d0 = -1. / (W / (2. * focal)) * (rays_d[..., 0] / rays_d[..., 2] - rays_o[..., 0] / rays_o[..., 2])
  d1 = -1. / (H / (2. * focal)) * (rays_d[..., 1] / rays_d[..., 2] - rays_o[..., 1] / rays_o[..., 2])
  d2 = -2. * near / rays_o[..., 2]
  return np.stack([o0, o1, o2], -1), np.stack([d0, d1, d2], -1)


def _camera_rays(n=200, seed=0):
  """Rays of a camera near the origin looking down -z (an LLFF-like scene frame), through random pixels."""
  rng = np.random.default_rng(seed)
  intr = cameras.Intrinsics.from_focal(64, 48, 55.0)
  pose = np.eye(4)
  pose[:3, 3] = rng.uniform(-0.1, 0.1, 3)
  rows, cols = rng.uniform(0, 47, n), rng.uniform(0, 63, n)  # + 0.5: pixel centres inside the image
  origins, directions = cameras.rays_for_pixels(pose, intr, rows, cols)
  return intr, origins.astype(np.float64), directions.astype(np.float64)


def test_ndc_rays_equal_the_original_code():
  intr, origins, directions = _camera_rays()
  got_o, got_d = _ndc_rays(jnp.asarray(origins), jnp.asarray(directions), intr.fx, intr.fy, intr.width,
                           intr.height, 1.0)
  want_o, want_d = _reference_ndc_rays(intr.height, intr.width, intr.fx, 1.0, origins, directions)
  np.testing.assert_allclose(got_o, want_o, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(got_d, want_d, rtol=1e-5, atol=1e-6)


def test_ndc_rays_pass_through_the_projections_of_their_world_points():
  """Brute force: project world points on each ray with the pinhole camera; the NDC ray must pass through
  every projection, at a t' that grows with distance, starts at 0 on the near plane and nears 1 far away."""
  intr, origins, directions = _camera_rays()
  near = 1.0
  o_ndc, d_ndc = (np.asarray(a, np.float64) for a in _ndc_rays(
      jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32), intr.fx, intr.fy, intr.width,
      intr.height, near))
  start = -(near + origins[:, 2]) / directions[:, 2]  # where each ray crosses z = -near
  previous = np.full(len(origins), -1.0)
  for extra in (0.0, 0.5, 3.0, 40.0, 1e4):
    points = origins + (start + extra)[:, None] * directions
    pixels, depth = cameras.project(points, np.eye(4), intr)
    ndc = np.stack([2.0 * (pixels[:, 0] - intr.cx) / intr.width, -2.0 * (pixels[:, 1] - intr.cy) / intr.height,
                    1.0 - 2.0 * near / depth], axis=-1)
    t_ndc = (ndc[:, 2] - o_ndc[:, 2]) / d_ndc[:, 2]
    np.testing.assert_allclose(o_ndc + t_ndc[:, None] * d_ndc, ndc, atol=2e-4)
    assert (t_ndc > previous - 1e-6).all() and (t_ndc < 1.0).all()
    np.testing.assert_allclose(_ndc_to_disparity(t_ndc, near), 1.0 / depth, rtol=1e-4, atol=1e-6)
    if extra == 0.0:
      np.testing.assert_allclose(t_ndc, 0.0, atol=1e-5)
    previous = t_ndc
  assert (previous > 0.999).all()
  # Infinitely far, a ray through a pixel of the camera lands where the pixel is: in the cube [-1, 1]^2.
  assert (np.abs((o_ndc + d_ndc)[:, :2]) <= 1.0 + 1e-5).all()


def _points(n=2000, seed=1):
  rng = np.random.default_rng(seed)
  directions = rng.normal(size=(n, 3))
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  radii = np.exp(rng.uniform(np.log(0.01), np.log(1e5), n))
  return jnp.asarray(directions * radii[:, None], jnp.float32)


def test_contraction_is_identity_inside_the_unit_ball_and_maps_everything_into_radius_2():
  points = _points()
  contracted = np.asarray(_contract(points))
  radius = np.linalg.norm(np.asarray(points), axis=-1)
  inside = radius <= 1.0
  np.testing.assert_array_equal(contracted[inside], np.asarray(points)[inside])
  r_out = np.linalg.norm(contracted, axis=-1)
  assert (r_out < 2.0).all() and (r_out[~inside] > 1.0).all()
  # Outside, the direction is kept and the radius is 2 - 1/r (the paper's formula).
  np.testing.assert_allclose(r_out[~inside], 2.0 - 1.0 / radius[~inside], rtol=1e-5)
  np.testing.assert_allclose(contracted[~inside] / r_out[~inside, None],
                             np.asarray(points)[~inside] / radius[~inside, None], atol=1e-5)
  # Radially monotone: farther points land farther out.
  ordered = np.argsort(radius)
  assert (np.diff(r_out[ordered]) >= -1e-6).all()


def test_contraction_and_its_derivative_are_continuous_at_the_unit_sphere():
  direction = np.asarray([0.48, -0.6, 0.64], np.float32)  # unit length
  jacobian = jax.jit(jax.jacfwd(lambda x: coord.contract(x[None])[0]))
  for eps in (1e-3, 1e-4):
    below, above = (jnp.asarray(direction * scale, jnp.float32) for scale in (1.0 - eps, 1.0 + eps))
    np.testing.assert_allclose(_contract(below[None]), _contract(above[None]), atol=3 * eps)
    np.testing.assert_allclose(jacobian(below), jacobian(above), atol=10 * eps)
  np.testing.assert_allclose(jacobian(jnp.asarray(direction * 1.0001, jnp.float32)), np.eye(3), atol=1e-3)
  grads = jax.jit(jax.grad(lambda x: coord.contract(x).sum()))(jnp.zeros((1, 3)))  # finite at the origin too
  assert np.isfinite(np.asarray(grads)).all()


def _uncontract(contracted_Nx3):
  """The inverse of coord.contract on the open ball of radius 2: y where |y| <= 1, else y / (|y| (2 - |y|))."""
  norm_sq = jnp.maximum(jnp.sum(contracted_Nx3 ** 2, axis=-1, keepdims=True), 1e-20)
  norm = jnp.sqrt(norm_sq)
  return jnp.where(norm <= 1.0, contracted_Nx3, contracted_Nx3 / (norm * jnp.maximum(2.0 - norm, 1e-20)))


def test_inverse_contraction_undoes_the_contraction():
  points = _points()
  # In float32, 2 - |contract(x)| = 1 / |x| keeps ~7 digits less the log10 of |x|: test up to |x| = 1e3.
  points = points[np.linalg.norm(np.asarray(points), axis=-1) < 1e3]
  # One program each rather than one per operation.
  np.testing.assert_allclose(jax.jit(lambda p: _uncontract(coord.contract(p)))(points), points, rtol=2e-3)
  rng = np.random.default_rng(2)
  ball = rng.normal(size=(1000, 3))
  ball = ball / np.linalg.norm(ball, axis=-1, keepdims=True) * rng.uniform(0, 1.99, (1000, 1))
  ball = jnp.asarray(ball, jnp.float32)
  np.testing.assert_allclose(jax.jit(lambda b: coord.contract(_uncontract(b)))(ball), ball, atol=1e-5)


@pytest.mark.parametrize("spacing", ["linear", "inverse", "piecewise"])
def test_warps_are_inverse_pairs_that_map_the_bounds_to_0_and_1(spacing):
  near, far = (2.0, 6.0) if spacing == "linear" else (0.2, 1e6)
  # Per-ray bounds broadcast: (R, 1) near/far against (S,) s.
  nears, fars = jnp.asarray([[near], [near * 2]]), jnp.asarray([[far], [far * 2]])

  @jax.jit  # one program rather than one per operation (the float bounds stay Python floats, as eagerly)
  def warps(s, nears, fars):
    t, t2 = coord.s_to_t(s, near, far, spacing), coord.s_to_t(s, nears, fars, spacing)
    return t, coord.t_to_s(t, near, far, spacing), t2, coord.t_to_s(t2, nears, fars, spacing)

  s = jnp.linspace(0.0, 1.0, 101)
  t, s_again, t2, s2_again = warps(s, nears, fars)
  t = np.asarray(t)
  np.testing.assert_allclose([t[0], t[-1]], [near, far], rtol=1e-5)
  assert (np.diff(t) > 0).all()
  np.testing.assert_allclose(s_again, s, atol=1e-5)
  assert t2.shape == (2, 101)
  np.testing.assert_allclose(s2_again, np.broadcast_to(s, (2, 101)), atol=1e-5)


def test_linear_warp_is_even_in_distance_and_inverse_warp_even_in_disparity():
  warps = jax.jit(lambda s: (coord.s_to_t(s, 2.0, 6.0, "linear"), coord.s_to_t(s, 0.2, 1e6, "inverse")))
  linear, inverse = warps(jnp.linspace(0.0, 1.0, 9))  # one program rather than one per operation
  t = np.asarray(linear)
  np.testing.assert_allclose(t, np.linspace(2.0, 6.0, 9), rtol=1e-6)
  t = np.asarray(inverse, np.float64)
  np.testing.assert_allclose(np.diff(1.0 / t), np.full(8, (1e-6 - 5.0) / 8), rtol=1e-4)
  # Half the samples lie within twice the near bound: the foreground gets them.
  assert t[4] < 0.41


def test_piecewise_warp_is_linear_to_distance_1_and_even_in_disparity_beyond():
  """nerfacto's UniformLinDispPiecewiseSampler, from its spacing function g(t) = t / 2 (t < 1), 1 - 1 / (2 t)
  (t >= 1), written here in float64 numpy as the reference: the samples even in g between near and far."""
  def reference(s, near, far):
    g = lambda t: np.where(t < 1, t / 2, 1 - 1 / (2 * np.maximum(t, 1)))  # noqa: E731
    y = g(near) + s * (g(far) - g(near))
    return np.where(y < 0.5, 2 * y, 1 / (2 * (1 - np.minimum(y, 1 - 1e-12))))
  s = np.linspace(0.0, 1.0, 201)
  bounds = ((0.2, 1e6), (0.05, 1000.0), (0.0, 5.0))
  pairs = ((0.1, 0.9, "piecewise"), (0.1, 0.9, "linear"), (1.0, 1e6, "piecewise"), (1.0, 1e6, "inverse"))

  @jax.jit  # one program rather than one per operation (the bounds stay Python floats, as eagerly)
  def warps(s):
    return ([coord.s_to_t(s, near, far, "piecewise") for near, far in bounds],
            [coord.s_to_t(s, near, far, spacing) for near, far, spacing in pairs])

  piecewise, (inside_piecewise, inside_linear, beyond_piecewise, beyond_inverse) = warps(jnp.asarray(s, jnp.float32))
  for (near, far), t in zip(bounds, piecewise):
    t = np.asarray(t, np.float64)
    np.testing.assert_allclose(t, reference(s, near, far), rtol=2e-5, atol=1e-6)
  t = np.asarray(piecewise[0], np.float64)
  inside = t < 1.0
  np.testing.assert_allclose(np.diff(t[inside]), np.diff(t[inside])[0], rtol=1e-3)  # even in distance
  beyond = t >= 1.0
  np.testing.assert_allclose(np.diff(1.0 / t[beyond]), np.diff(1.0 / t[beyond])[1], rtol=1e-3)
  assert 0.43 < inside.mean() < 0.46  # (g(1) - g(0.2)) / (g(1e6) - g(0.2)) = 0.4 / 0.9 of the samples
  # Inside distance 1 it is the linear warp, beyond it the inverse one.
  np.testing.assert_allclose(inside_piecewise, inside_linear, rtol=1e-5)
  np.testing.assert_allclose(beyond_piecewise, beyond_inverse, rtol=1e-4)
