import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nerfpod.nerf.compositing import composite


# One program a test rather than one per operation; `last_delta` (a Python float) static, as it is eagerly.
@functools.partial(jax.jit, static_argnames="last_delta")
def _composite(*args, last_delta, background=None):
  return composite(*args, last_delta=last_delta, background=background)


def test_constant_density_transmittance_is_exponential():
  sigma, n = 0.7, 200
  t = np.asarray(jnp.linspace(2.0, 6.0, n))[None]
  directions = np.array([[0.0, 0.0, -2.0]], np.float32)  # |d| = 2: world distance is twice the t interval
  out = _composite(np.ones((1, n, 3), np.float32), np.full((1, n), sigma, np.float32), t, directions,
                   last_delta=1e10)
  weights = np.asarray(out["weights"])[0]
  transmittance = 1.0 - np.concatenate([[0.0], np.cumsum(weights)[:-1]])
  np.testing.assert_allclose(transmittance, np.exp(-sigma * 2.0 * (np.asarray(t[0]) - 2.0)), rtol=1e-4, atol=1e-6)


def test_weights_sum_to_accumulated_opacity_and_colour_is_weighted_mean():
  rng = np.random.default_rng(0)
  sigma = jnp.asarray(rng.uniform(0, 2, (5, 32)), jnp.float32)
  rgb = jnp.asarray(rng.uniform(0, 1, (5, 32, 3)), jnp.float32)
  t = jnp.asarray(np.sort(rng.uniform(2, 6, (5, 32)).astype(np.float32), -1))
  d = jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)
  background = jnp.array([0.2, 0.5, 1.0])

  @jax.jit  # one program rather than one per operation
  def run(rgb, sigma, t, d, background):
    out = composite(rgb, sigma, t, d, last_delta=0.3, background=background)
    expected = (out["weights"][..., None] * rgb).sum(1) + (1 - out["acc"][:, None]) * background
    return out, out["weights"].sum(-1), expected

  out, weights_sum, expected = run(rgb, sigma, t, d, background)
  np.testing.assert_allclose(weights_sum, out["acc"], rtol=1e-6)
  assert np.all((np.asarray(out["acc"]) >= 0) & (np.asarray(out["acc"]) <= 1))
  np.testing.assert_allclose(out["rgb"], expected, rtol=1e-6)
  np.testing.assert_allclose(out["disparity"], np.asarray(out["acc"]) / np.asarray(out["depth"]), rtol=1e-6)


def test_infinite_last_interval_makes_any_density_opaque():
  out = _composite(np.ones((1, 4, 3), np.float32), np.array([[0.0, 0.0, 0.0, 1e-3]], np.float32),
                   np.array([[2.0, 3, 4, 5]], np.float32), np.array([[0.0, 0, -1]], np.float32), last_delta=1e10)
  np.testing.assert_allclose(out["acc"], 1.0)
  np.testing.assert_allclose(out["depth"], 5.0)


@pytest.mark.parametrize("num_samples", [256])
def test_rendered_colour_matches_fine_riemann_sum_of_the_integral(num_samples):
  """C = int_n^f T(t) sigma(t) c(t) dt with T(t) = exp(-int_n^t sigma), against a 200k-step Riemann sum."""
  near, far = 2.0, 6.0
  sigma_fn = lambda t: 3.0 * np.exp(-((t - 4.0) / 0.4)**2) + 0.1
  colour_fn = lambda t: np.stack([np.sin(t)**2, t / 6.0, np.full_like(t, 0.3)], -1)
  fine = np.linspace(near, far, 200_001)
  dt = np.diff(fine)
  mid = 0.5 * (fine[1:] + fine[:-1])
  optical = np.concatenate([[0.0], np.cumsum(sigma_fn(mid) * dt)])[:-1]
  reference = np.sum((np.exp(-optical) * sigma_fn(mid) * dt)[:, None] * colour_fn(mid), 0)
  # NeRF's quadrature on stratified midpoints, the last interval closed at `far`.
  edges = np.linspace(near, far, num_samples + 1)
  t = 0.5 * (edges[1:] + edges[:-1])
  f32 = lambda a: np.asarray(a, np.float32)[None]  # noqa: E731  (as jnp.asarray made them: float32)
  out = _composite(f32(colour_fn(t)), f32(sigma_fn(t)), f32(t), np.array([[0.0, 0.0, -1.0]], np.float32),
                   last_delta=float(far - t[-1]))
  np.testing.assert_allclose(np.asarray(out["rgb"])[0], reference, atol=2e-3)
