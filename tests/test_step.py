"""The sharded train step: same loss and parameters on 8 simulated devices as on one."""
import jax
import numpy as np
import optax
import pytest
from jax.sharding import Mesh

from conftest import smoke_config
from nerfpod import data, distributed, scenes, train
from nerfpod.nerf import model as nerf_model


def _run_steps(mesh, config, num_steps, optimizer):
  scene = scenes.load(config.data)
  model = nerf_model.from_config(config)
  state = train.init_state(model, optimizer, config.train.seed, mesh)
  step_fn = train.make_train_step(model, optimizer, mesh, 2.0, 6.0, scene.background)
  dataset = data.ray_batches(scene.split("train"), 0, config.train.batch_size,
                             slice(0, config.train.batch_size), 0.5, num_steps)
  key = jax.random.key(7)
  losses = []
  for step in range(num_steps):
    batch = dict(dataset[step])
    batch.pop("step")
    batch = jax.tree.map(lambda x: jax.device_put(x, distributed.batch_sharding(mesh)), batch)
    state, metrics = step_fn(state, batch, key)
    losses.append(float(metrics["loss"]))
  return np.array(losses), jax.device_get(state.params)


@pytest.mark.parametrize("field,importance", [("mlp", 8), ("hashgrid", 0)])
def test_eight_devices_match_one_device(field, importance):
  config = smoke_config(**{"model.field": field, "model.depth": 3, "model.width": 32, "model.skips": (1,),
                           "model.use_viewdirs": True, "render.num_importance": importance,
                           "train.batch_size": 128})
  assert jax.device_count() == 8
  one = Mesh(np.array(jax.devices()[:1]), (distributed.DATA_AXIS,))
  eight = distributed.make_mesh()
  # Plain SGD, so that parameters differ exactly as the averaged gradients do. (Adam maps any near-zero
  # gradient component to a step of +-lr, which turns the summation-order round-off between 1 and 8
  # devices into visible parameter differences.)
  sgd = optax.sgd(0.5)
  losses_1, params_1 = _run_steps(one, config, 3, sgd)
  losses_8, params_8 = _run_steps(eight, config, 3, sgd)
  np.testing.assert_allclose(losses_8, losses_1, rtol=2e-5)
  assert losses_1[-1] != losses_1[0]  # the parameters did move
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), params_8, params_1)


def test_adam_step_on_eight_devices_follows_the_same_loss_trajectory():
  config = smoke_config(**{"train.batch_size": 128})
  one = Mesh(np.array(jax.devices()[:1]), (distributed.DATA_AXIS,))
  optimizer = train.make_optimizer(config.train)
  losses_1, _ = _run_steps(one, config, 4, optimizer)
  losses_8, _ = _run_steps(distributed.make_mesh(), config, 4, optimizer)
  np.testing.assert_allclose(losses_8, losses_1, rtol=1e-4)
