"""The NeRF renderer: hierarchical sampling, view directions, fields, mixed precision."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod.nerf import fields
from nerfpod.nerf import model as nerf_model


def _rays(n=64, seed=0):
  rng = np.random.default_rng(seed)
  eye = rng.normal(size=(n, 3))
  eye = 4.0 * eye / np.linalg.norm(eye, axis=-1, keepdims=True)
  directions = -eye + 0.3 * rng.normal(size=(n, 3))
  return jnp.asarray(eye, jnp.float32), jnp.asarray(directions, jnp.float32)


def _mlp_field(**sizes):
  """An MLPField sized like the smoke config's MLP, with `sizes` overriding."""
  attributes = dict(smoke_config().model.mlp, use_viewdirs=False, dtype=jnp.float32)
  attributes.update(sizes)
  return fields.MLPField(**attributes)


def _hierarchical(field="mlp", dtype="float32", importance=24):
  config = smoke_config(**{"model.field": field, "model.mlp.depth": 3, "model.mlp.width": 32,
                           "model.mlp.skips": (1,), "model.use_viewdirs": True, "render.num_samples": 16,
                           "render.num_importance": importance, "model.compute_dtype": dtype})
  model = nerf_model.from_config(config)
  origins, directions = _rays()
  params = jax.jit(model.init, static_argnums=(3, 4))(jax.random.key(0), origins, directions, 2.0, 6.0,
                                                      jnp.ones(3))
  return model, params, origins, directions


def _apply(model, *args):
  """model.apply, jitted (the near/far bounds are static floats)."""
  return jax.jit(model.apply, static_argnums=(3, 4))(*args)


def test_hierarchical_sampling_renders_coarse_and_fine_with_union_of_samples():
  model, params, origins, directions = _hierarchical()
  assert set(params["params"]) == {"coarse", "fine"}
  u_c = jax.random.uniform(jax.random.key(1), (64, 16))
  u_f = jax.random.uniform(jax.random.key(2), (64, 24))
  coarse, fine = _apply(model, params, origins, directions, 2.0, 6.0, jnp.ones(3), u_c, u_f)
  assert coarse["t"].shape == (64, 16) and fine["t"].shape == (64, 40)
  assert (np.diff(np.asarray(fine["t"]), axis=-1) >= 0).all()
  # The fine set contains every coarse sample.
  for ray in range(4):
    assert np.isin(np.asarray(coarse["t"][ray]), np.asarray(fine["t"][ray])).all()
  for out in (coarse, fine):
    assert out["rgb"].shape == (64, 3) and out["depth"].shape == (64,)


def test_fine_loss_sends_no_gradient_to_the_coarse_network_through_sample_positions():
  model, params, origins, directions = _hierarchical()
  u_c = jax.random.uniform(jax.random.key(1), (64, 16))
  u_f = jax.random.uniform(jax.random.key(2), (64, 24))

  def fine_rgb_sum(p):
    return jnp.sum(model.apply(p, origins, directions, 2.0, 6.0, jnp.ones(3), u_c, u_f)[-1]["rgb"])

  grads = jax.jit(jax.grad(fine_rgb_sum))(params)["params"]
  assert all(np.all(np.asarray(g) == 0) for g in jax.tree.leaves(grads["coarse"]))
  assert any(np.any(np.asarray(g) != 0) for g in jax.tree.leaves(grads["fine"]))


def test_view_directions_change_colour_but_not_density():
  field = _mlp_field(depth=3, width=32, skips=(1,), use_viewdirs=True)
  points = jax.random.normal(jax.random.key(0), (10, 3))
  dirs_a = jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (10, 1))
  dirs_b = jnp.tile(jnp.array([[1.0, 0.0, 0.0]]), (10, 1))
  params = field.init(jax.random.key(1), points, dirs_a)
  rgb_a, sigma_a = field.apply(params, points, dirs_a)
  rgb_b, sigma_b = field.apply(params, points, dirs_b)
  np.testing.assert_array_equal(sigma_a, sigma_b)
  assert not np.allclose(rgb_a, rgb_b)


def test_tutorial_mlp_has_the_tutorial_shapes():
  field = _mlp_field(depth=8, width=256, skips=(4,), num_frequencies=6)
  params = jax.eval_shape(field.init, jax.random.key(0), jnp.zeros((1, 3)))["params"]
  assert params["trunk_0"]["kernel"].shape == (39, 256)
  assert params["trunk_5"]["kernel"].shape == (256 + 39, 256)  # input rejoins after layer 4
  assert params["trunk_4"]["kernel"].shape == (256, 256)
  assert params["output"]["kernel"].shape == (256, 4)
  assert len([k for k in params if k.startswith("trunk_")]) == 8


@pytest.mark.parametrize("field", ["mlp", "hashgrid"])
def test_bfloat16_matmuls_keep_float32_parameters_and_close_outputs(field):
  model32, params, origins, directions = _hierarchical(field, "float32", importance=0)
  model16, _, _, _ = _hierarchical(field, "bfloat16", importance=0)
  assert all(p.dtype == jnp.float32 for p in jax.tree.leaves(params))
  out32 = _apply(model32, params, origins, directions, 2.0, 6.0, jnp.ones(3))[-1]
  out16 = _apply(model16, params, origins, directions, 2.0, 6.0, jnp.ones(3))[-1]
  assert out16["rgb"].dtype == jnp.float32
  np.testing.assert_allclose(out16["rgb"], out32["rgb"], atol=0.05)
  grads = jax.jit(jax.grad(
      lambda p: jnp.sum(model16.apply(p, origins, directions, 2.0, 6.0, jnp.ones(3))[-1]["rgb"])))(params)
  assert all(g.dtype == jnp.float32 for g in jax.tree.leaves(grads))
