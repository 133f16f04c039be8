"""Step functions of importance and proposal sampling (nerf/stepfun.py) against brute-force references."""
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nerfpod.nerf import stepfun

# The functions under test, each one jitted program (eagerly, each of their operations is compiled on its own:
# hundreds of compiles a test). Their numbers (interval counts, shapes, the blur's radius) are static.
J = types.SimpleNamespace(
    outer=jax.jit(stepfun.outer), interlevel_loss=jax.jit(stepfun.interlevel_loss, static_argnames=("radius",)),
    blurred_weights=jax.jit(stepfun.blurred_weights, static_argnums=3),
    blurred_interlevel_loss=jax.jit(stepfun.blurred_interlevel_loss, static_argnums=4),
    distortion_loss=jax.jit(stepfun.distortion_loss), inverse_cdf=jax.jit(stepfun.inverse_cdf),
    sample_intervals=jax.jit(stepfun.sample_intervals, static_argnums=2, static_argnames=("num", "domain")),
    stratified_uniforms=jax.jit(stepfun.stratified_uniforms, static_argnums=(0, 2),
                                static_argnames=("num", "shape")))


def _random_histograms(rng, rays: int, intervals: int, zero_share: float = 0.3):
  """Random step functions on [0, 1]: sorted edges (random interior, 0 and 1 at the ends) and weights, some
  of them zero, each ray's summing to at most 1 (as compositing weights do)."""
  interior = np.sort(rng.uniform(0.0, 1.0, (rays, intervals - 1)), axis=-1)
  edges = np.concatenate([np.zeros((rays, 1)), interior, np.ones((rays, 1))], axis=-1)
  weights = rng.uniform(0.0, 1.0, (rays, intervals)) * (rng.uniform(size=(rays, intervals)) > zero_share)
  weights = weights / np.maximum(weights.sum(-1, keepdims=True), 1e-9) * rng.uniform(0.2, 1.0, (rays, 1))
  return edges, weights


def _outer_brute_force(edges, env_edges, env_weights):
  """For each interval of `edges`, the sum of the envelope's weights on intervals that overlap it (with a
  positive-length overlap), by looping over every pair."""
  out = np.zeros((edges.shape[0], edges.shape[1] - 1))
  for r in range(edges.shape[0]):
    for i in range(edges.shape[1] - 1):
      for j in range(env_edges.shape[1] - 1):
        if min(edges[r, i + 1], env_edges[r, j + 1]) > max(edges[r, i], env_edges[r, j]):
          out[r, i] += env_weights[r, j]
  return out


def _interlevel_brute_force(edges, weights, env_edges, env_weights):
  bound = _outer_brute_force(edges, env_edges, env_weights)
  return np.sum(np.maximum(0.0, weights - bound)**2 / (weights + stepfun.EPS), axis=-1)


def test_outer_bound_matches_brute_force_on_random_step_functions():
  rng = np.random.default_rng(0)
  edges, _ = _random_histograms(rng, 40, 12)
  env_edges, env_weights = _random_histograms(rng, 40, 9)
  got = np.asarray(J.outer(jnp.asarray(edges), jnp.asarray(env_edges), jnp.asarray(env_weights)))
  np.testing.assert_allclose(got, _outer_brute_force(edges, env_edges, env_weights), rtol=1e-5, atol=1e-7)


def test_interlevel_loss_is_zero_exactly_when_the_proposal_bounds_the_nerf():
  rng = np.random.default_rng(1)
  edges, weights = _random_histograms(rng, 60, 16)
  env_edges, env_weights = _random_histograms(rng, 60, 10)
  loss = np.asarray(J.interlevel_loss(*map(jnp.asarray, (edges, weights, env_edges, env_weights))))
  np.testing.assert_allclose(loss, _interlevel_brute_force(edges, weights, env_edges, env_weights),
                             rtol=1e-4, atol=1e-7)
  bounded = np.all(weights <= _outer_brute_force(edges, env_edges, env_weights), axis=-1)
  assert 0 < bounded.sum() < len(bounded)  # both cases occur among these rays
  assert np.all(loss[bounded] == 0.0) and np.all(loss[~bounded] > 0.0)
  # A proposal whose histogram is the NeRF's own bounds it (up to the round-off of the prefix sums the bound
  # is read from: an excess of ~1e-8 squared); one with all its mass elsewhere does not.
  assert np.all(np.asarray(J.interlevel_loss(edges, weights, edges, weights)) < 1e-12)
  far_away = np.zeros_like(weights)
  far_away[:, -1] = 1.0
  nerf_weights = weights.copy()
  nerf_weights[:, -1] = 0.0
  nerf_weights[:, 0] = 0.5  # the first interval never overlaps the last
  assert np.all(np.asarray(J.interlevel_loss(edges, nerf_weights, edges, far_away)) > 0.0)


def test_interlevel_gradient_raises_the_proposal_where_it_falls_short():
  edges = jnp.array([[0.0, 0.25, 0.5, 0.75, 1.0]])
  nerf = jnp.array([[0.0, 0.8, 0.1, 0.0]])
  proposal = jnp.array([[0.1, 0.1, 0.0, 0.0]])
  grad = np.asarray(jax.jit(jax.grad(lambda w: jnp.sum(J.interlevel_loss(edges, nerf, edges, w))))(proposal))
  assert float(grad[0, 1]) < 0.0 and float(grad[0, 2]) < 0.0  # descent raises the mass near the NeRF's
  assert float(grad[0, 3]) == 0.0  # beyond every interval the NeRF weighs, no pressure at all


def _distortion_brute_force(edges, weights, n: int = 3000):
  """The double integral of w(u) w(v) |u - v| over [0, 1]^2 by the midpoint rule on an n x n grid, w(u)
  being the histogram's density (weight / interval length)."""
  u = (np.arange(n) + 0.5) / n
  out = []
  for e, w in zip(edges, weights):
    interval = np.clip(np.searchsorted(e, u, side="right") - 1, 0, len(w) - 1)
    density = w[interval] / np.diff(e)[interval]
    out.append(np.sum(density[:, None] * density[None, :] * np.abs(u[:, None] - u[None, :])) / n**2)
  return np.array(out)


def test_distortion_loss_equals_its_brute_force_double_integral():
  rng = np.random.default_rng(2)
  edges, weights = _random_histograms(rng, 6, 8, zero_share=0.2)
  # Intervals of at least 1/40 keep the grid's error at the edges small.
  edges = np.concatenate([np.zeros((6, 1)), np.cumsum(rng.uniform(1.0, 3.0, (6, 8)), -1)], -1)
  edges /= edges[:, -1:]
  got = np.asarray(J.distortion_loss(jnp.asarray(edges), jnp.asarray(weights)))
  np.testing.assert_allclose(got, _distortion_brute_force(edges, weights), rtol=2e-3)
  # One interval holding all the weight: w^2 * length / 3 (the integral of |u - v| over a square of side l
  # is l^3 / 3, and the density there is 1 / l).
  one = J.distortion_loss(jnp.array([[0.0, 0.2, 0.6, 1.0]]), jnp.array([[0.0, 1.0, 0.0]]))
  np.testing.assert_allclose(one, [0.4 / 3], rtol=1e-6)


def test_inverse_cdf_of_uniform_numbers_reproduces_the_weight_distribution():
  bins = np.asarray(jnp.linspace(0.0, 1.0, 11))[None]  # (NumPy: read on the host without a program each)
  weights = np.array([[0.0, 1, 4, 0, 0, 2, 8, 1, 0, 4]], np.float32)
  u = jax.random.uniform(jax.random.key(1), (1, 200_000))
  samples = np.asarray(J.inverse_cdf(bins, weights, u))[0]
  hist, _ = np.histogram(samples, bins=bins[0])
  expected = weights[0] / np.sum(weights)
  np.testing.assert_allclose(hist / len(samples), expected, atol=3e-3)
  # Within one interval the density is uniform: samples in [0.6, 0.7) spread evenly.
  inner = samples[(samples >= 0.6) & (samples < 0.7)]
  np.testing.assert_allclose(np.histogram(inner, bins=5, range=(0.6, 0.7))[0] / len(inner), 0.2, atol=0.01)


def test_inverse_cdf_at_quantiles_from_0_to_1_spans_the_edges():
  # The hierarchical sampler's evaluation: quantiles 0 and 1 inclusive, weights padded by 1e-5 (nerf/model.py).
  bins = np.asarray(jnp.linspace(0.0, 4.0, 5))[None]
  weights = np.array([[1.0, 1.0, 1.0, 1.0]], np.float32) + np.float32(1e-5)
  samples = np.asarray(J.inverse_cdf(bins, weights, np.asarray(jnp.linspace(0.0, 1.0, 9))[None]))[0]
  np.testing.assert_allclose(samples, np.linspace(0, 4, 9), atol=1e-3)
  assert samples[0] == 0.0 and samples[-1] == 4.0 and np.all(np.diff(samples) > 0)


def test_no_gradient_flows_through_inverse_cdf_positions():
  bins = np.asarray(jnp.linspace(0.0, 1.0, 9))[None]
  u = jax.random.uniform(jax.random.key(2), (1, 32))
  f = lambda w, b: jnp.sum(J.inverse_cdf(b, w, u))
  grad_w, grad_b = jax.jit(jax.grad(f, argnums=(0, 1)))(np.asarray(jnp.linspace(0.1, 1.0, 8))[None], bins)
  np.testing.assert_array_equal(grad_w, 0.0)
  np.testing.assert_array_equal(grad_b, 0.0)


def test_resampling_reproduces_a_known_histogram():
  edges = np.array([[0.0, 0.1, 0.3, 0.35, 0.6, 0.9, 1.0]], np.float32)
  weights = np.array([[0.0, 0.4, 0.05, 0.3, 0.0, 0.25]], np.float32)
  n = 100_000
  jitter = np.asarray(jax.random.uniform(jax.random.key(3), (1, n)))
  points = np.asarray(J.inverse_cdf(edges, weights, J.stratified_uniforms(n, jitter)))[0]
  assert np.all(np.diff(points) >= 0)  # stratified inverse CDF keeps the points sorted
  hist, _ = np.histogram(points, bins=edges[0])
  np.testing.assert_allclose(hist / n, weights[0] / 1.0, atol=2e-4)
  # Uniform inside an interval: [0.35, 0.6) splits evenly.
  inner = points[(points >= 0.35) & (points < 0.6)]
  np.testing.assert_allclose(np.histogram(inner, bins=5, range=(0.35, 0.6))[0] / len(inner), 0.2, atol=0.01)
  assert not np.any((points > 0.0) & (points < 0.1)) and not np.any((points > 0.6) & (points < 0.9))
  # The intervals drawn are short where the weight is dense; a region without weight is bridged by the two
  # intervals of the points on either side, each reaching half way across (their midpoints may lie there).
  intervals = np.asarray(J.sample_intervals(edges, weights, 64, jitter[:, :64]))[0]
  assert intervals.shape == (65,) and np.all(np.diff(intervals) >= 0)
  assert intervals[0] >= 0.0 and intervals[-1] <= 1.0
  mids = 0.5 * (intervals[1:] + intervals[:-1])
  assert np.sum((mids > 0.0) & (mids < 0.1)) <= 2 and np.sum((mids > 0.6) & (mids < 0.9)) <= 2
  lengths = np.diff(intervals)
  assert np.max(lengths[(mids > 0.1) & (mids < 0.3)]) < 0.3 / 64 * 4  # density 2: about 1/128 each


def test_deterministic_resampling_and_an_empty_ray():
  edges = jnp.array([[0.0, 0.5, 1.0], [0.0, 0.5, 1.0]])
  weights = jnp.array([[1.0, 1.0], [0.0, 0.0]])  # the second ray has no weight: uniform over its span
  for row in np.asarray(J.inverse_cdf(edges, weights, J.stratified_uniforms(4, shape=(2,)))):
    np.testing.assert_allclose(row, [0.125, 0.375, 0.625, 0.875], atol=1e-6)


def test_no_gradient_flows_through_sampled_positions():
  edges = np.asarray(jnp.linspace(0.0, 1.0, 9))[None]
  jitter = jax.random.uniform(jax.random.key(4), (1, 16))
  f = lambda w, e: jnp.sum(J.sample_intervals(e, w, 16, jitter))
  grad_w, grad_e = jax.jit(jax.grad(f, argnums=(0, 1)))(np.asarray(jnp.linspace(0.1, 1.0, 8))[None], edges)
  np.testing.assert_array_equal(grad_w, 0.0)
  np.testing.assert_array_equal(grad_e, 0.0)


@pytest.mark.parametrize("intervals", [1, 3])
def test_shapes_are_static(intervals):
  edges = np.asarray(jnp.linspace(0.0, 1.0, intervals + 1))[None].repeat(5, 0)
  weights = np.ones((5, intervals), np.float32)
  out = jax.eval_shape(lambda e, w: J.sample_intervals(e, w, 7), edges, weights)
  assert out.shape == (5, 8)


def _blurred_brute_force(edges, weights, query, radius, n: int = 200_000):
  """The histogram's density blurred by a box of half-width `radius` (the mean of the density over
  [x - radius, x + radius]: its exact CDF, piecewise linear, differenced), integrated over each query
  interval by the midpoint rule on n points, in float64; radius 0: the exact CDF differenced."""
  out = []
  for e, w, q in zip(edges, weights, query):
    cdf = lambda x: np.interp(x, e, np.concatenate([[0.0], np.cumsum(w)]))  # noqa: E731 (0 before, total after)
    if radius == 0:
      out.append(np.diff(cdf(q)))
      continue
    x = q[0] + (np.arange(n) + 0.5) / n * (q[-1] - q[0])
    density = (cdf(x + radius) - cdf(x - radius)) / (2 * radius)
    interval = np.clip(np.searchsorted(q, x, side="right") - 1, 0, len(q) - 2)
    out.append(np.bincount(interval, density, len(q) - 1) * (q[-1] - q[0]) / n)
  return np.array(out)


@pytest.mark.parametrize("radius", [0.0, 0.003, 0.03, 0.2])
def test_blurred_weights_match_a_brute_force_blur_and_resampling(radius):
  rng = np.random.default_rng(3)
  edges, weights = _random_histograms(rng, 12, 10)
  edges[:3, 4] = edges[:3, 5]  # zero-width intervals (weight on a point) occur too
  query, _ = _random_histograms(rng, 12, 7)
  got = np.asarray(J.blurred_weights(*map(jnp.asarray, (edges, weights, query)), radius))
  want = _blurred_brute_force(edges, weights, query, radius)
  assert got.shape == (12, 7)
  np.testing.assert_allclose(got, want, atol=2e-5)
  if radius > 0:  # the blur moves weight: resampling alone does not give the same numbers
    assert np.abs(want - _blurred_brute_force(edges, weights, query, 0.0)).max() > 1e-3


def test_blurred_weights_keep_the_mass_and_give_exact_zeros_away_from_it():
  edges = jnp.array([[0.0, 0.5, 0.6, 1.0]])
  weights = jnp.array([[0.0, 0.7, 0.0]])
  # Query edges wide enough to hold all of the blurred weight: its sum is the histogram's.
  wide = np.asarray(jnp.linspace(-0.5, 1.5, 21))[None]
  np.testing.assert_allclose(np.sum(J.blurred_weights(edges, weights, wide, 0.03)), 0.7, rtol=1e-6)
  # Weight only on [0.5, 0.6], blurred by 0.03, reaches [0.47, 0.63]: outside it, exactly nothing.
  query = jnp.array([[0.0, 0.2, 0.46, 0.47, 0.55, 0.63, 0.64, 1.0]])
  got = np.asarray(J.blurred_weights(edges, weights, query, 0.03))[0]
  assert got[0] == 0.0 and got[1] == 0.0 and got[-2] == 0.0 and got[-1] == 0.0
  # The trapezoid rises over [0.47, 0.53] and is flat (0.7 / 0.1) to 0.57: [0.47, 0.55] holds its rising
  # part and 0.02 of the flat one.
  ramp = 0.7 * (0.06 / 2) / 0.1  # the weight under one ramp of width 0.06, height 0.7 / 0.1
  np.testing.assert_allclose(got[3], ramp + 0.7 / 0.1 * 0.02, rtol=1e-5)
  np.testing.assert_allclose(got[2:6].sum(), 0.7, rtol=1e-6)


def test_blurred_interlevel_loss_is_zero_where_the_proposal_holds_the_blurred_weights_and_raises_it_where_short():
  rng = np.random.default_rng(4)
  edges, weights = _random_histograms(rng, 20, 16)
  env_edges, _ = _random_histograms(rng, 20, 10)
  target = np.asarray(J.blurred_weights(*map(jnp.asarray, (edges, weights, env_edges)), 0.03))
  loss = lambda p: J.blurred_interlevel_loss(edges, weights, env_edges, p, 0.03)  # noqa: E731
  # The target itself (up to its round-off when computed again inside the loss: an excess of ~1e-7 squared)
  # and more than it cost nothing.
  assert np.all(np.asarray(loss(jnp.asarray(target))) < 1e-11)
  assert np.all(np.asarray(loss(jnp.asarray(target * 1.5))) == 0.0)
  short = target * 0.5
  np.testing.assert_allclose(np.asarray(loss(jnp.asarray(short))),
                             np.sum((target - short)**2 / (short + stepfun.EPS), axis=-1), rtol=1e-4)
  grad = np.asarray(jax.jit(jax.grad(lambda p: jnp.sum(loss(p))))(jnp.asarray(short)))
  assert np.all(grad[target > 1e-6] < 0.0) and np.all(grad[target == 0.0] == 0.0)
