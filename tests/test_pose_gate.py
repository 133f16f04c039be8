"""Pose refinement's noise gate (train.pose_gate, train_state.scale_by_gated_adam) and the known pose error
that measures it (data.pose_noise, scenes.base.with_pose_noise): the first moment's noise variance against
a Monte Carlo estimate, the gate off as Adam to the last bit, a pure-noise gradient held still while a
gradient with a mean still moves, and every training camera moved by exactly the angle and distance asked.
NumPy and a few jitted updates: seconds."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import procs
from conftest import smoke_config
from nerfpod import scenes
from nerfpod.nerf import alignment, pose_correction
from nerfpod.run import train_state

# One program each rather than one per operation (b1, a Python float, static as it is eagerly).
_noise_variance = jax.jit(train_state.noise_variance, static_argnums=0)


@pytest.mark.parametrize("b1", [0.9, 0.99])
def test_the_first_moments_noise_variance_matches_a_monte_carlo_estimate(b1):
  rng = np.random.default_rng(0)
  g = rng.normal(size=(200_000, 60))  # 200,000 sequences of 60 steps of unit noise
  m = np.zeros(g.shape[0])
  for t in range(1, 61):
    m = b1 * m + (1 - b1) * g[:, t - 1]
    if t in (1, 2, 5, 20, 60):
      estimate = np.var(m / (1 - b1**t))
      np.testing.assert_allclose(float(_noise_variance(b1, np.float32(t))), estimate, rtol=0.02)


def _run(transform, grads):
  """The sum of a transform's updates over a sequence of gradients (T, ...)."""
  @jax.jit  # one program for the whole sequence, not one call per step (nor a program per operation of init)
  def updates(grads):
    def step(state, g):
      u, state = transform.update(g, state)
      return state, u
    return jax.lax.scan(step, transform.init(jnp.zeros(grads.shape[1:])), grads)[1]

  steps = np.asarray(updates(grads.astype(np.float32)))
  total = np.zeros(grads.shape[1:])
  for u in steps:
    total += u
  return total, steps


def test_the_gate_at_zero_is_adams_step():
  grads = np.random.default_rng(1).normal(size=(30, 8, 6)) * 1e-3 + 2e-4
  _, gated = _run(train_state.scale_by_gated_adam(0.9, 0.999, 1e-8, 0.0), grads)
  _, adam = _run(optax.scale_by_adam(0.9, 0.999, 1e-8), grads)
  np.testing.assert_allclose(gated, adam, rtol=1e-5, atol=1e-7)


def test_a_noise_gradient_stays_put_under_the_gate_while_a_mean_still_moves():
  rng = np.random.default_rng(2)
  steps, entries = 1500, 400
  noise = rng.normal(size=(steps, entries))
  # Pure noise: Adam walks each entry about sqrt(steps) x sqrt((1 - b1) / (1 + b1)); the gate holds it.
  adam_walk, _ = _run(optax.scale_by_adam(0.99, 0.999, 1e-8), noise)
  gated_walk, _ = _run(train_state.scale_by_gated_adam(0.99, 0.999, 1e-8, 3.0), noise)
  assert np.median(np.abs(adam_walk)) > 1.0
  assert np.median(np.abs(gated_walk)) < 0.05 * np.median(np.abs(adam_walk))
  # A gradient with a mean moves every entry the mean's way, with Adam's step times 1 - 3 / z: at a mean of a
  # third of the noise's spread (z about 4.5 at b1 = 0.99) a third of Adam's progress, at a mean as large as
  # the spread (z about 10) seven tenths.
  for mean, kept in ((1.0 / 3.0, 0.25), (1.0, 0.6)):
    signal = noise + mean
    adam_move, _ = _run(optax.scale_by_adam(0.99, 0.999, 1e-8), signal)
    gated_move, _ = _run(train_state.scale_by_gated_adam(0.99, 0.999, 1e-8, 3.0), signal)
    assert np.all(gated_move > 0)
    assert kept * np.median(adam_move) < np.median(gated_move) < np.median(adam_move)


def test_make_optimizer_gates_the_pose_corrections_only():
  tc = smoke_config(**{"train.pose_refine": True, "train.pose_gate": 3.0, "train.pose_b1": 0.99,
                       "train.lr_warmup_steps": 0}).train
  optimizer = train_state.make_optimizer(tc)
  # The field alone under plain Adam on the same schedule: what the gate must leave the field's updates.
  adam = optax.adam(train_state.learning_rate_schedule(tc), b1=tc.adam_b1, b2=tc.adam_b2, eps=tc.adam_eps)
  rng = np.random.default_rng(3)
  all_grads = []
  for _ in range(20):  # noise on the corrections, a steady gradient with noise on the field
    all_grads.append({"params": {pose_correction.PARAM: (rng.normal(size=(4, 6)) * 1e-3).astype(np.float32),
                                 "w": (1e-3 * (1.0 + 0.5 * rng.uniform(size=3))).astype(np.float32)}})

  # One program rather than one per operation, its bits from optimised kernels (procs.OPTIMIZED_KERNELS), as in
  # every claim that two computations give the same bits.
  @functools.partial(jax.jit, compiler_options=procs.OPTIMIZED_KERNELS)
  def run(all_grads):
    params = {"params": {pose_correction.PARAM: jnp.zeros((4, 6)), "w": jnp.zeros((3,))}}
    state = optimizer.init(params)
    field = params["params"]["w"]
    field_state = adam.init(field)
    for grads in all_grads:
      updates, state = optimizer.update(grads, state, params)
      params = optax.apply_updates(params, updates)
      field_updates, field_state = adam.update(grads["params"]["w"], field_state, field)
      field = optax.apply_updates(field, field_updates)
    return params, field

  params, field = jax.tree.map(np.asarray, run(all_grads))
  assert np.all(np.asarray(params["params"][pose_correction.PARAM]) == 0)
  assert np.all(np.asarray(params["params"]["w"]) < 0)
  np.testing.assert_array_equal(params["params"]["w"], field)


@pytest.mark.parametrize("degrees, units", [(1.0, 0.03), (5.0, 0.0)])
def test_pose_noise_moves_every_training_camera_by_the_angle_and_distance_asked(degrees, units):
  config = smoke_config()
  exact = scenes.load(config.data)
  config.data.pose_noise = (degrees, units)
  moved = scenes.load(config.data)
  given, noisy = exact.split("train").poses.astype(np.float64), moved.split("train").poses.astype(np.float64)
  turn = noisy[:, :3, :3] @ np.swapaxes(given[:, :3, :3], 1, 2)
  angles = np.array([alignment.rotation_angle_deg(r) for r in turn])
  np.testing.assert_allclose(angles, degrees, atol=2e-3)
  np.testing.assert_allclose(np.linalg.norm(noisy[:, :3, 3] - given[:, :3, 3], axis=-1), units, atol=1e-5)
  # Axes spread over the sphere (not one shared axis), rotations still rotations, held-out views exact.
  if degrees:
    axes = np.stack([turn[:, 2, 1] - turn[:, 1, 2], turn[:, 0, 2] - turn[:, 2, 0], turn[:, 1, 0] - turn[:, 0, 1]], -1)
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    assert np.linalg.norm(axes.mean(0)) < 0.5
  np.testing.assert_allclose(np.linalg.det(noisy[:, :3, :3]), 1.0, atol=1e-5)
  for name in ("val", "test"):
    if name in exact.splits:
      np.testing.assert_array_equal(moved.split(name).poses, exact.split(name).poses)
  # The same seed gives the same draw, another seed another.
  np.testing.assert_array_equal(scenes.load(config.data).split("train").poses, moved.split("train").poses)
  config.data.pose_noise_seed = 1
  assert not np.array_equal(scenes.load(config.data).split("train").poses, moved.split("train").poses)


def test_a_pose_refined_workdir_written_before_the_gate_resumes_with_the_plain_adam_it_ran():
  """config.json of a run from before train.pose_gate and train.pose_b1 reads as what that run did (gate 0,
  b1 0.9: optax's AdamW), whatever their defaults are now: the same optimiser state to resume into, and a
  resume that asks for the gate is refused as any other change of the optimiser would be."""
  import json

  from nerfpod.workdir import files as workdir_files
  saved = json.loads(smoke_config(**{"train.pose_refine": True}).to_json_best_effort())
  del saved["train"]["pose_gate"], saved["train"]["pose_b1"]
  read = workdir_files.with_defaults(saved)["train"]
  assert (read["pose_gate"], read["pose_b1"]) == (0.0, 0.9)
  then = smoke_config(**{"train.pose_refine": True, "train.pose_gate": 0.0, "train.pose_b1": 0.9})
  assert workdir_files.incompatible_fields(saved, json.loads(then.to_json_best_effort())) == []
  gated = smoke_config(**{"train.pose_refine": True, "train.pose_gate": 5.0, "train.pose_b1": 0.99})
  assert workdir_files.incompatible_fields(saved, json.loads(gated.to_json_best_effort())) == [
      "train.pose_b1", "train.pose_gate"]


def test_a_gradient_without_noise_takes_adams_step_times_one_less_the_gate_over_its_ceiling():
  """A constant gradient: z is its ceiling 1 / sqrt(c_t), so the factor is max(0, 1 - gate sqrt(c_t)): shut
  for the first steps, then rising to 1 - 5 sqrt(0.01 / 1.99) = 0.65 at b1 = 0.99."""
  grads = np.full((400, 3), 0.02)
  _, gated = _run(train_state.scale_by_gated_adam(0.99, 0.999, 1e-8, 5.0), grads)
  _, adam = _run(optax.scale_by_adam(0.99, 0.999, 1e-8), grads)
  t = np.arange(1, 401, dtype=np.float64)
  ceiling = 1 / np.sqrt(np.asarray(_noise_variance(0.99, t.astype(np.float32))))
  factor = np.maximum(0.0, 1.0 - 5.0 / ceiling)
  np.testing.assert_allclose(gated[:, 0], factor * adam[:, 0], rtol=1e-4, atol=1e-7)
  assert factor[:20].max() == 0.0 and 0.6 < factor[-1] < 0.66
