"""The proposal sampler's absorbing state (the trap), and what keeps a sampler out of it.

Once a proposal puts nearly all its weight in one interval, the raw histogram sends every NeRF sample into that
interval: every NeRF interval overlaps it, `outer` is about 1 everywhere, and the interlevel loss is 0 with no
gradient whatever the NeRF's weights are, so the proposal never learns again (the collapse an H200 showed on the
cup, docs/results.md). Padding the histogram (render.proposal_padding, nerfacto's) keeps the previous round's
intervals reachable; annealing (train.proposal_anneal_steps) flattens it early; trunc_exp (model.trunc_exp) keeps
a saturated density's gradient. Each test checks both sides: the trap as it is without the fix, and its end with.
"""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import procs
from conftest import smoke_config
from nerfpod.nerf import fields, model as nerf_model, stepfun
from nerfpod.run import components, step as train_step

INTERVALS, SAMPLES, HEAVY = 96, 48, 40  # the proposal's intervals, the NeRF's samples, the heavy interval


def _one_hot_proposal(mass: float = 0.999):
  """A proposal histogram on 96 random intervals of [0, 1] with `mass` of its weight in interval 40 (1, 96 + 1)
  edges and (1, 96) weights, and the rest spread evenly over the others; NumPy float32 arrays (read on the host
  without a program per indexing)."""
  rng = np.random.default_rng(0)
  edges = np.concatenate([[0.0], np.sort(rng.uniform(0.0, 1.0, INTERVALS - 1)), [1.0]])
  weights = np.full(INTERVALS, (1.0 - mass) / (INTERVALS - 1))
  weights[HEAVY] = mass
  return edges[None].astype(np.float32), weights[None].astype(np.float32)


def _nerf_intervals(env_edges, env_weights, padding: float, seed: int = 1):
  """The NeRF's 48 intervals drawn from the proposal as the model draws them (stratified, jittered): (1, 49)
  edges, a NumPy array."""
  jitter = jax.random.uniform(jax.random.PRNGKey(seed), (1, SAMPLES))
  draw = jax.jit(lambda e, w, u: stepfun.sample_intervals(e, stepfun.resampling_weights(w, padding), SAMPLES, u))
  return np.asarray(draw(env_edges, env_weights, jitter))


def _random_histograms(count: int, seed: int = 2):
  """`count` random NeRF histograms on 48 intervals, each summing to at most 1, no interval over 0.9."""
  rng = np.random.default_rng(seed)
  w = rng.dirichlet(np.full(SAMPLES, 0.5), count) * rng.uniform(0.2, 1.0, (count, 1))
  return jnp.asarray(np.minimum(w, 0.9), jnp.float32)


def _loss_and_gradient(edges, nerf_weights, env_edges, env_weights):
  """Per histogram: the interlevel loss and the norm of its gradient with respect to the proposal's weights."""
  def loss(env_w, w):
    return stepfun.interlevel_loss(edges, w[None], env_edges, env_w)[0]

  @jax.jit  # one program, the norms too
  def values_and_norms(env_w, ws):
    values, grads = jax.vmap(jax.value_and_grad(loss), in_axes=(None, 0))(env_w, ws)
    return values, jnp.linalg.norm(grads.reshape(len(ws), -1), axis=-1)
  values, norms = values_and_norms(env_weights, nerf_weights)
  return np.asarray(values), np.asarray(norms)


def test_without_padding_the_interlevel_loss_and_its_gradient_are_zero_whatever_the_nerf_does():
  env_edges, env_weights = _one_hot_proposal()
  edges = _nerf_intervals(env_edges, env_weights, padding=0.0)
  heavy_lo, heavy_hi = float(env_edges[0, HEAVY]), float(env_edges[0, HEAVY + 1])
  # Every NeRF sample lies inside the heavy interval (the outermost edges are mirrored a little beyond it):
  # the NeRF's window is about that interval's width.
  mids = 0.5 * (edges[0, 1:] + edges[0, :-1])
  assert np.all((heavy_lo <= mids) & (mids <= heavy_hi))
  assert float(edges[0, -1] - edges[0, 0]) <= 1.1 * (heavy_hi - heavy_lo) < 0.05
  np.testing.assert_allclose(np.asarray(jax.jit(stepfun.outer)(edges, env_edges, env_weights)), 0.999, atol=1e-3)
  values, gradient_norms = _loss_and_gradient(edges, _random_histograms(200), env_edges, env_weights)
  assert np.all(values == 0.0) and np.all(gradient_norms == 0.0)


def test_with_padding_the_nerfs_samples_spread_and_the_loss_pulls_the_proposal():
  env_edges, env_weights = _one_hot_proposal()
  edges = _nerf_intervals(env_edges, env_weights, padding=0.01)
  assert float(edges[0, -1] - edges[0, 0]) > 0.9  # the window spans nearly the whole ray
  heavy_lo, heavy_hi = float(env_edges[0, HEAVY]), float(env_edges[0, HEAVY + 1])
  mids = 0.5 * (edges[0, 1:] + edges[0, :-1])
  outside = (mids < heavy_lo) | (mids > heavy_hi)
  assert 10 <= outside.sum() < SAMPLES  # about half the samples follow the padding, the rest the heavy interval
  # A NeRF histogram with weight outside the heavy interval: loss > 0, and its gradient raises the proposal's
  # weights there (negative), never the heavy interval's.
  nerf_weights = jnp.asarray(np.where(outside, 0.5 / outside.sum(), 0.0)[None], jnp.float32)
  values, gradient_norms = _loss_and_gradient(edges, nerf_weights, env_edges, env_weights)
  assert values[0] > 0.1 and gradient_norms[0] > 0.1
  grad = np.asarray(jax.jit(jax.grad(lambda w: stepfun.interlevel_loss(edges, nerf_weights, env_edges, w)[0]))(
      env_weights))
  assert grad[0, HEAVY] == 0.0 and (grad[0] < 0).sum() >= 5
  # 200 random histograms: every one now costs something and moves the proposal.
  values, gradient_norms = _loss_and_gradient(edges, _random_histograms(200), env_edges, env_weights)
  assert np.all(values > 0.0) and np.all(gradient_norms > 0.0)


def test_a_transparent_window_is_a_trap_too_and_padding_finds_the_surface():
  """The NeRF transparent inside its window (w = 0) and a surface outside it: without padding no sample reaches
  the surface, the NeRF's weights are 0 and so are the loss and its gradient; with it, samples reach it."""
  env_edges, env_weights = _one_hot_proposal()
  surface = float(env_edges[0, HEAVY + 1]) + 0.5 * (1.0 - float(env_edges[0, HEAVY + 1]))  # beyond the heavy one

  def nerf_weights(edges):  # opaque from `surface` on, empty before: weight 1 in the interval that holds it
    hit = (edges[0, :-1] <= surface) & (surface < edges[0, 1:])
    return hit.astype(np.float32)[None]

  trapped = _nerf_intervals(env_edges, env_weights, padding=0.0)
  assert float(np.sum(nerf_weights(trapped))) == 0.0
  values, norms = _loss_and_gradient(trapped, nerf_weights(trapped), env_edges, env_weights)
  assert values[0] == 0.0 and norms[0] == 0.0
  padded = _nerf_intervals(env_edges, env_weights, padding=0.01)
  assert float(np.sum(nerf_weights(padded))) == 1.0
  values, norms = _loss_and_gradient(padded, nerf_weights(padded), env_edges, env_weights)
  assert values[0] > 0.5 and norms[0] > 0.5


def test_annealing_flattens_the_histogram_early_and_leaves_it_at_the_end():
  # One program each rather than one per operation; the numbers that shape them static.
  anneal_exponent = jax.jit(stepfun.anneal_exponent, static_argnums=1)
  resampling_weights = jax.jit(stepfun.resampling_weights, static_argnums=1)
  steps = 1000
  exponents = np.asarray([anneal_exponent(s, steps) for s in (0, 100, 1000 / 11, 500, 1000, 5000)])
  x = np.array([0.0, 0.1, 1 / 11, 0.5, 1.0, 1.0])
  np.testing.assert_allclose(exponents, 10 * x / (9 * x + 1), rtol=1e-6)  # nerfacto's, slope 10
  np.testing.assert_allclose(exponents[2], 0.5, rtol=1e-6)
  assert float(anneal_exponent(7, 0)) == 1.0
  env_edges, env_weights = _one_hot_proposal()
  env_weights[0, 3] = 0.0  # an empty interval: 0^0 = 1, every interval alike
  flat = np.asarray(resampling_weights(env_weights, 0.0, jnp.float32(0.0)))
  np.testing.assert_array_equal(flat, np.ones((1, INTERVALS), np.float32))
  np.testing.assert_array_equal(np.asarray(resampling_weights(env_weights, 0.0, jnp.float32(1.0))), env_weights)
  np.testing.assert_array_equal(np.asarray(resampling_weights(env_weights, 0.0, None)), env_weights)
  # At the start every NeRF interval has the same share of the proposal's intervals: the window is the ray.
  edges = np.asarray(jax.jit(stepfun.sample_intervals, static_argnums=2)(
      env_edges, flat, SAMPLES, jax.random.uniform(jax.random.PRNGKey(3), (1, SAMPLES))))
  assert float(edges[0, -1] - edges[0, 0]) > 0.95


def test_trunc_exp_keeps_the_densitys_gradient_above_the_clamp_and_its_forward_bits():
  h = jnp.array([-3.0, 0.0, 9.5, 14.9, 15.0, 16.0, 40.0], jnp.float32)

  # One program rather than one per operation, its bits from optimised kernels (procs.OPTIMIZED_KERNELS), as in
  # every claim that two computations give the same bits.
  @functools.partial(jax.jit, compiler_options=procs.OPTIMIZED_KERNELS)
  def run(h):
    return (fields.trunc_exp(h), jnp.exp(jnp.minimum(h, 15.0)), jax.vmap(jax.grad(fields.clamped_exp))(h),
            jax.vmap(jax.grad(fields.trunc_exp))(h))
  forward, reference, clamped, truncated = (np.asarray(a) for a in run(h))
  np.testing.assert_array_equal(forward, reference)
  np.testing.assert_allclose(truncated, np.exp(np.minimum(np.asarray(h), 15.0)), rtol=1e-6)
  np.testing.assert_array_equal(truncated[:4], clamped[:4])  # below the clamp: the same gradient
  assert np.all(clamped[5:] == 0.0) and np.all(truncated[5:] > 3e6)  # above it: 0 before, exp(15) now


@pytest.mark.parametrize("truncated", [False, True])
def test_a_saturated_hash_grid_field_gets_a_gradient_only_with_trunc_exp(truncated):
  field = fields.HashGridField(bound=1.0, num_levels=2, features_per_level=2, log2_table_size=8, base_resolution=4,
                               max_resolution=8, hidden_width=8, geo_features=3, use_viewdirs=False,
                               dtype=jnp.float32, trunc_exp=truncated)
  points = jax.random.uniform(jax.random.PRNGKey(0), (64, 3), minval=-0.5, maxval=0.5)
  params = jax.jit(field.init)(jax.random.PRNGKey(1), points)
  bias = np.array(params["params"]["density_out"]["bias"])  # (edited in NumPy: no program per edit)
  bias[0] = 30.0
  params["params"]["density_out"]["bias"] = bias
  sigma_sum = lambda p: jnp.sum(field.apply(p, points)[1])  # noqa: E731
  assert np.min(np.asarray(jax.jit(field.apply)(params, points)[1])) >= nerf_model.SATURATED_DENSITY  # all clamped
  bias_gradient = float(jax.jit(jax.grad(sigma_sum))(params)["params"]["density_out"]["bias"][0])
  assert (bias_gradient > 1e8) if truncated else (bias_gradient == 0.0)


def _spiked_model(padding: float):
  """The default config's smoke model (one proposal round of 16, 16 NeRF samples) with its proposal field's
  density raised by e^8 everywhere (a spike): the proposal's weight piles into the ray's first intervals."""
  config = smoke_config(**{"render.proposal_padding": padding})
  model = components.make_model(config, backend="cpu")
  rays = 64
  key = jax.random.PRNGKey(0)
  # (Built and edited in NumPy, float32: no program per operation.)
  origins = np.tile(np.array([[0.0, 0.0, 4.0]], np.float32), (rays, 1))
  directions = np.concatenate([0.2 * np.asarray(jax.random.normal(key, (rays, 2))), -np.ones((rays, 1), np.float32)],
                              -1)
  background = np.zeros(3, np.float32)
  params = jax.jit(model.init)(jax.random.PRNGKey(1), origins, directions, 2.0, 6.0, background)
  bias = np.asarray(params["params"]["proposal_0"]["density"]["bias"])
  params["params"]["proposal_0"]["density"]["bias"] = bias + np.float32(8.0)
  return jax.jit(model.apply)(params, origins, directions, 2.0, 6.0, background)[-1]


def test_the_model_pads_its_resampling_and_the_step_reports_the_collapse():
  trapped, padded = _spiked_model(0.0), _spiked_model(0.05)
  diagnose = jax.jit(train_step.proposal_diagnostics)
  diagnostics = {k: float(v) for k, v in diagnose(trapped).items()}
  assert diagnostics["heavy"] > 0.9 and diagnostics["window"] < 0.1
  padded_diagnostics = {k: float(v) for k, v in diagnose(padded).items()}
  assert padded_diagnostics["window"] > 0.8
  # The same proposal (padding changes only where the NeRF samples): as heavy as before.
  np.testing.assert_array_equal(np.asarray(trapped["proposals"][0]["weights"]),
                                np.asarray(padded["proposals"][0]["weights"]))
  for d in (diagnostics, padded_diagnostics):
    assert 0.0 <= d["saturated"] <= 1.0 and 0.0 <= d["proposal_saturated"] <= 1.0


def test_proposal_diagnostics_against_hand_made_histograms():
  s_edges = jnp.array([[0.2, 0.3, 0.5], [0.0, 0.5, 1.0]])
  proposal_weights = jnp.array([[0.995, 0.004, 0.0], [0.3, 0.3, 0.3]])
  sigma = jnp.array([[1.0, nerf_model.SATURATED_DENSITY * 1.1], [0.0, 0.0]])

  @jax.jit  # one program rather than one per operation
  def diagnose(s_edges, proposal_weights, sigma, proposal_sigma):
    final = {"s_edges": s_edges, "saturated": nerf_model.saturated_share(sigma),
             "proposals": [{"weights": proposal_weights, "saturated": nerf_model.saturated_share(proposal_sigma)}]}
    return train_step.proposal_diagnostics(final)
  d = {k: float(v) for k, v in diagnose(s_edges, proposal_weights, sigma, np.full((2, 3), 1e7, np.float32)).items()}
  assert d == pytest.approx({"window": 0.65, "heavy": 0.5, "saturated": 0.25, "proposal_saturated": 1.0})


def test_the_collapse_warning_comes_once_after_a_whole_log_window_collapsed():
  from nerfpod.run.train import CollapseWatch
  watch = CollapseWatch()
  healthy = {"window": 0.43, "heavy": 0.0, "interlevel": 1e-3}
  collapsed = {"window": 0.02, "heavy": 0.9, "interlevel": 1e-9}
  narrow_but_spread = {"window": 0.02, "heavy": 0.1, "interlevel": 1e-4}  # a window, not a trap
  assert watch.check(100, healthy) is None
  assert watch.check(200, collapsed) is None  # one log step: a moment, not yet a window
  assert watch.check(300, healthy) is None    # it came back
  assert watch.check(400, collapsed) is None
  assert watch.check(500, narrow_but_spread) is None
  assert watch.check(600, collapsed) is None
  warning = watch.check(700, collapsed)
  assert warning.startswith("step 700: proposal sampling has collapsed since step 600")
  assert "0.020 of each ray" in warning and "90%" in warning and "1.0e-09" in warning
  assert "--config.render.proposal_padding=0.01" in warning
  assert watch.check(800, collapsed) is None  # one line per run
  assert watch.check(900, {"loss": 0.1}) is None  # a model without proposals: nothing to watch
