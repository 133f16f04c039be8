"""model.hashgrid.scale_aware: Zip-NeRF's feature downweighting. Each hash-grid level's features are weighted by
erf(1 / sqrt(8 sigma^2 n^2)) for a sample whose pixel footprint has standard deviation sigma on a level of n
cells; the footprint is the scene's pixel angle times the sample's distance, shrunk by the contraction."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod import schema
from nerfpod.nerf import coord, encodings
from nerfpod.run import components


def test_level_weights_are_zip_nerfs_erf_one_at_zero_footprint_and_falling_with_the_cells():
  sigmas = np.array([0.0, 1e-4, 1e-3, 1e-2, 0.1], np.float32)
  level_weights = jax.jit(encodings.level_weights)  # one program a shape, not one per operation
  for n in (16, 128, 2048):
    got = np.asarray(level_weights(jnp.asarray(sigmas), n))
    want = [1.0 if s == 0 else math.erf(1.0 / math.sqrt(8.0 * s * s * n * n)) for s in sigmas]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
  assert float(level_weights(jnp.float32(0.0), 2048)) == 1.0
  # A footprint of one cell keeps about 1/3 of the level; of ten cells, under 4%.
  assert 0.3 < float(level_weights(jnp.float32(1 / 64), 64)) < 0.4
  assert float(level_weights(jnp.float32(10 / 64), 64)) < 0.04


def test_the_encoding_with_footprints_is_each_levels_features_times_its_weight():
  module = encodings.HashGridEncoding(num_levels=3, features_per_level=2, log2_table_size=8, base_resolution=4,
                                      max_resolution=32)

  @jax.jit  # one program rather than one per operation
  def init(key):
    params = module.init(key, jnp.zeros((1, 3)))
    return jax.tree.map(lambda p: jax.random.normal(jax.random.key(1), p.shape), params)
  params = init(jax.random.key(0))
  x = jax.random.uniform(jax.random.key(2), (50, 3))
  scales = jnp.exp(jax.random.uniform(jax.random.key(3), (50,), minval=-8.0, maxval=-1.0))
  apply = jax.jit(module.apply)
  plain = np.asarray(apply(params, x))
  weighted = np.asarray(apply(params, x, scales))
  resolutions = encodings.level_resolutions(3, 4, 32)
  want = plain.copy()
  for level, n in enumerate(resolutions):
    w = np.array([math.erf(1.0 / math.sqrt(8.0 * float(s) ** 2 * n * n)) for s in scales])
    want[:, 2 * level:2 * level + 2] *= w[:, None]
  np.testing.assert_allclose(weighted, want, rtol=1e-5, atol=1e-7)
  np.testing.assert_array_equal(np.asarray(apply(params, x, jnp.zeros(50))), plain)


def test_contraction_scale_is_the_cube_root_of_the_contractions_jacobian_determinant():
  rng = np.random.default_rng(0)
  directions = rng.normal(size=(40, 3))
  directions /= np.linalg.norm(directions, axis=1, keepdims=True)
  radii = np.concatenate([rng.uniform(0.05, 0.99, 10), rng.uniform(1.01, 100.0, 30)])
  points = jnp.asarray(directions * radii[:, None], jnp.float32)
  # One program each rather than one per operation.
  jacobians = jax.jit(jax.vmap(jax.jacfwd(lambda p: coord.contract(p[None])[0])))(points)
  want = np.cbrt(np.abs(np.linalg.det(np.asarray(jacobians, np.float64))))
  got = np.asarray(jax.jit(coord.contraction_scale)(points))[:, 0]
  np.testing.assert_allclose(got, want, rtol=1e-4)
  assert np.all(got[:10] == 1.0)


def _model_and_rays(**overrides):
  config = smoke_config(**{"model.hashgrid.scale_aware": True, **overrides})
  origins = jnp.tile(jnp.array([[0.0, 0.0, 4.0]]), (32, 1))
  directions = jnp.stack([jnp.linspace(-0.2, 0.2, 32), jnp.zeros(32), -jnp.ones(32)], -1)
  return config, origins, directions


def test_a_vanishing_pixel_angle_renders_as_the_plain_model_and_a_large_one_blurs_the_fine_levels():
  no_proposals = {"render.proposal_samples": ()}  # the weighting is the NeRF field's grid's: a smaller program
  config, origins, directions = _model_and_rays(**no_proposals)
  plain = components.make_model(smoke_config(**no_proposals))

  @jax.jit  # one program, not each of the initialisation's operations compiled on its own
  def init(key):
    params = plain.init(key, origins[:2], directions[:2], 2.0, 6.0, jnp.zeros(3))
    # Tables of a trained field's magnitude (the initialisation's 1e-4 would hide any weighting).
    return jax.tree_util.tree_map_with_path(
        lambda path, p: jax.random.normal(jax.random.key(1), p.shape) if "level_" in jax.tree_util.keystr(path)
        else p, params)

  params = init(jax.random.key(0))
  render = lambda model: jax.jit(model.apply)(params, origins, directions, 2.0, 6.0, jnp.ones(3))[-1]  # noqa: E731
  want = render(plain)
  tiny = render(components.make_model(config, pixel_angle=1e-9))
  for key in ("rgb", "depth", "acc"):
    np.testing.assert_allclose(tiny[key], want[key], rtol=1e-5, atol=1e-6)
  blurred = render(components.make_model(config, pixel_angle=0.5))
  assert np.max(np.abs(np.asarray(blurred["rgb"]) - np.asarray(want["rgb"]))) > 1e-3  # the footprints reached the field


def test_footprints_grow_with_distance_and_shrink_with_the_contraction():
  config, origins, directions = _model_and_rays(**{"render.space": "contract", "model.hashgrid.bound": 2.0})
  model = components.make_model(config, pixel_angle=0.01)
  t = jnp.array([[0.5, 1.0, 2.0, 10.0]])
  o, d = jnp.zeros((1, 3)), jnp.array([[0.0, 0.0, -2.0]])  # |d| = 2: distances 1, 2, 4, 20
  got = np.asarray(jax.jit(model._footprints)(o, d, t)["scales_N"])  # one program, not one per operation
  distance = np.array([1.0, 2.0, 4.0, 20.0])
  shrink = np.where(distance <= 1, 1.0, np.cbrt((2 * distance - 1) ** 2) / distance ** 2)
  np.testing.assert_allclose(got, 0.01 / np.sqrt(12.0) * distance * shrink, rtol=1e-6)
  assert components.make_model(smoke_config(), pixel_angle=0.01).pixel_angle == 0.0  # off: no footprints


def test_the_model_needs_the_scenes_pixel_angle_and_takes_the_median_focal_length():
  with pytest.raises(ValueError, match="pixel angle"):
    components.make_model(smoke_config(**{"model.hashgrid.scale_aware": True}))
  from nerfpod import scenes
  config = smoke_config()
  scene = scenes.load(config.data)
  cams = scene.split("train").cameras
  assert components.pixel_angle_of(scene) == pytest.approx(1.0 / np.median((cams.fx + cams.fy) / 2))


@pytest.mark.parametrize("overrides", [{"model.field": "mlp"}, {"model.regions": 4},
                                       {"render.space": "ndc", "data.kind": "llff", "data.path": "x"}])
def test_scale_aware_where_it_does_not_apply_is_one_sentence(overrides):
  messages = [m for m in schema.problems(smoke_config(**{"model.hashgrid.scale_aware": True, **overrides}))
              if "scale_aware" in m]
  assert len(messages) == 1 and messages[0].endswith("--config.model.hashgrid.scale_aware=false)."), messages
