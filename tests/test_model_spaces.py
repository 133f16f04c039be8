"""The model in the spaces of real scenes: NDC rays (forward-facing) and the contracted ball (unbounded),
with linear or inverse sample spacing. An analytic field (an opaque wall or sphere, known in the field's own
space) checks that the model maps rays and points where nerf/coord.py says, and that depth and disparity
come out in world terms."""
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod.nerf import cameras, coord
from nerfpod.nerf import model as nerf_model
from nerfpod.run import components


class _OpaqueBeyond(nn.Module):
  """Opaque (grey) wherever `surface(point) > 0`, empty elsewhere; records nothing, has no parameters."""
  surface: object

  def __call__(self, points_Nx3, viewdirs_Nx3=None):
    sigma = jnp.where(self.surface(points_Nx3) > 0, 1e4, 0.0)
    return jnp.full(points_Nx3.shape, 0.5), sigma


def _model(monkeypatch, surface, space, spacing, samples, importance=0, ndc_camera=None):
  monkeypatch.setattr(nerf_model.fields, "make_field", lambda *a, **k: _OpaqueBeyond(surface, name=k["name"]))
  config = smoke_config(**{"render.space": space, "render.spacing": spacing, "render.num_samples": samples,
                           "render.num_importance": importance, "model.field": "mlp",
                           "render.proposal_samples": ()})
  return components.make_model(config, ndc_camera)


def _camera_rays(n=64):
  intr = cameras.Intrinsics.from_focal(40, 30, 35.0)
  rng = np.random.default_rng(0)
  origins, directions = cameras.rays_for_pixels(np.eye(4), intr, rng.integers(0, 30, n), rng.integers(0, 40, n))
  return intr, origins.astype(np.float32), directions.astype(np.float32)  # (NumPy: no program each)


def test_ndc_model_sees_a_wall_at_its_world_depth(monkeypatch):
  """A wall at world depth D is the plane z' = 1 - 2/D in NDC (near = 1); every pixel's depth output is D
  (depth along the camera axis) and its disparity 1/D, whatever the ray's slant."""
  intr, origins, directions = _camera_rays()
  wall = 5.0
  model = _model(monkeypatch, lambda p: p[:, 2] - (1.0 - 2.0 / wall), "ndc", "linear", 512,
                 ndc_camera=(intr.fx, intr.fy, intr.width, intr.height))
  out = jax.jit(model.apply)({}, origins, directions, 0.0, 1.0, jnp.ones(3))[-1]
  np.testing.assert_allclose(out["acc"], 1.0, atol=1e-4)
  np.testing.assert_allclose(out["disparity"], 1.0 / wall, atol=2.0 / 512)
  np.testing.assert_allclose(out["depth"], wall, rtol=0.05)
  assert (np.asarray(out["t"]) >= 0).all() and (np.asarray(out["t"]) <= 1).all()


def test_ndc_model_takes_view_directions_from_the_world_rays(monkeypatch):
  seen = {}

  class _Recorder(nn.Module):
    def __call__(self, points_Nx3, viewdirs_Nx3=None):
      seen["viewdirs"], seen["points"] = viewdirs_Nx3, points_Nx3
      return jnp.zeros_like(points_Nx3), jnp.zeros(points_Nx3.shape[:-1])

  monkeypatch.setattr(nerf_model.fields, "make_field", lambda *a, **k: _Recorder(name=k["name"]))
  intr, origins, directions = _camera_rays(8)
  config = smoke_config(**{"render.space": "ndc", "render.num_samples": 4, "model.field": "mlp",
                           "render.proposal_samples": ()})
  camera = (intr.fx, intr.fy, intr.width, intr.height)
  model = components.make_model(config, camera)

  @jax.jit
  def render(origins, directions):
    model.apply({}, origins, directions, 0.0, 1.0, jnp.ones(3))
    return seen["viewdirs"], seen["points"]  # what the field was asked about, out of the program

  seen["viewdirs"], seen["points"] = render(origins, directions)
  world = np.asarray(directions) / np.linalg.norm(np.asarray(directions), axis=-1, keepdims=True)
  np.testing.assert_allclose(np.asarray(seen["viewdirs"]).reshape(8, 4, 3), np.repeat(world[:, None], 4, 1),
                             rtol=1e-6)

  @jax.jit  # one program rather than one per operation
  def points(origins, directions):
    o_ndc, d_ndc = coord.ndc_rays(origins, directions, *camera)
    return o_ndc[:, None] + jnp.linspace(0.0, 1.0, 4)[None, :, None] * d_ndc[:, None]
  want = points(origins, directions)
  np.testing.assert_allclose(np.asarray(seen["points"]).reshape(8, 4, 3), want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("importance", [0, 32])
def test_contracted_model_sees_a_far_sphere_at_its_distance(monkeypatch, importance):
  """A sphere of world radius R around the camera is the sphere of radius 2 - 1/R in the contracted ball;
  with inverse spacing out to 1e6 the model finds it at distance R along every ray, and the fine samples
  (drawn in s) crowd around it."""
  _, origins, directions = _camera_rays()
  radius = 30.0 if importance == 0 else 3.0  # 3: inside the span of 64 random coarse samples
  model = _model(monkeypatch, lambda p: jnp.linalg.norm(p, axis=-1) - (2.0 - 1.0 / radius), "contract",
                 "inverse", 1024 if importance == 0 else 64, importance)
  u = None if importance == 0 else (jax.random.uniform(jax.random.key(0), (64, 64)),
                                    jax.random.uniform(jax.random.key(1), (64, importance)))
  levels = jax.jit(model.apply)({}, origins, directions, 0.2, 1e6, jnp.ones(3), *(u or ()))
  distance = np.asarray(levels[-1]["depth"]) * np.linalg.norm(np.asarray(directions), axis=-1)
  np.testing.assert_allclose(levels[-1]["acc"], 1.0, atol=1e-4)
  # An opaque surface is found at the first sample beyond it: at most one step of 1/t (the evenly spaced
  # evaluation samples) past R; the random coarse and fine samples of training, within half of R.
  step = (1.0 / 0.2 - 1.0 / 1e6) / (1024 - 1)
  farthest = 1.0 / (1.0 / radius - step) if importance == 0 else 1.5 * radius
  assert (distance > radius * (1 - 1e-4)).all() and (distance < farthest * (1 + 1e-4)).all(), distance
  t = np.asarray(levels[0]["t"])
  assert t.min() >= 0.2 and (importance or np.allclose(t[:, -1], 1e6))  # not clipped to a box: out to far
  if importance:
    fine = np.asarray(levels[-1]["t"]) * np.linalg.norm(np.asarray(directions), axis=-1, keepdims=True)
    coarse = t * np.linalg.norm(np.asarray(directions), axis=-1, keepdims=True)
    near_surface = lambda d: np.mean(np.abs(d / radius - 1.0) < 0.3)
    assert near_surface(fine) > near_surface(coarse) + 0.2


def test_inverse_spacing_is_even_in_inverse_distance(monkeypatch):
  _, origins, directions = _camera_rays(4)
  model = _model(monkeypatch, lambda p: -jnp.ones(p.shape[:-1]), "euclidean", "inverse", 9)
  t = np.asarray(jax.jit(model.apply)({}, origins, directions, 0.5, 100.0, jnp.ones(3))[-1]["t"], np.float64)
  np.testing.assert_allclose(1.0 / t, np.broadcast_to(np.linspace(2.0, 0.01, 9), t.shape), rtol=1e-5)


def test_ndc_is_refused_for_a_scene_not_framed_as_a_forward_facing_capture():
  from nerfpod.errors import UserError
  with pytest.raises(UserError, match="render.space=ndc needs a forward-facing capture framed as LLFF"):
    components.build(smoke_config(**{"render.space": "ndc"}))


class _ConstantDensity(nn.Module):
  """A proposal field of constant density that records the points it is asked about."""
  record: object  # called with the points

  def __call__(self, points_Nx3):
    self.record(points_Nx3)
    return jnp.ones(points_Nx3.shape[:-1])


def _proposal_model(monkeypatch, surface, space, spacing, proposal, samples, ndc_camera=None):
  seen = []
  monkeypatch.setattr(nerf_model.fields, "make_field", lambda *a, **k: _OpaqueBeyond(surface, name=k["name"]))
  monkeypatch.setattr(nerf_model.fields, "make_proposal_field",
                      lambda *a, **k: _ConstantDensity(seen.append, name=k["name"]))
  config = smoke_config(**{"render.space": space, "render.spacing": spacing, "render.num_samples": samples,
                           "render.num_importance": 0, "render.proposal_samples": proposal,
                           "model.field": "mlp"})
  return components.make_model(config, ndc_camera), seen


def test_proposal_sampling_in_contracted_space_with_inverse_spacing(monkeypatch):
  """Proposal rounds in an unbounded scene: their points are contracted (inside the ball of radius 2), their
  distances stay in [near, far] = [0.2, 1e6], and the NeRF field's samples, spread evenly in inverse distance,
  find a sphere of world radius 2 (contracted radius 1.5) at its distance."""
  _, origins, directions = _camera_rays()
  model, seen = _proposal_model(monkeypatch, lambda p: jnp.linalg.norm(p, axis=-1) - 1.5, "contract", "inverse",
                                (64,), 256)

  @jax.jit  # one program, not each operation compiled on its own
  def render(origins, directions):
    out = model.apply({}, origins, directions, 0.2, 1e6, jnp.ones(3))[-1]
    assert len(seen) == 1 and seen[0].shape == (64 * 64, 3)
    return out, jnp.max(jnp.linalg.norm(seen[0], axis=-1))

  out, farthest = render(origins, directions)
  assert float(farthest) < 2.0
  t = np.asarray(out["t"])
  assert t.shape == (64, 256) and (t >= 0.2).all() and (t <= 1e6).all()
  np.testing.assert_allclose(out["acc"], 1.0, atol=1e-4)
  np.testing.assert_allclose(out["depth"], 2.0 / np.linalg.norm(directions, axis=-1), rtol=0.1)


def test_proposal_sampling_in_ndc_space_gives_world_depth(monkeypatch):
  intr, origins, directions = _camera_rays()
  wall = 5.0
  model, _ = _proposal_model(monkeypatch, lambda p: p[:, 2] - (1.0 - 2.0 / wall), "ndc", "linear", (64,), 256,
                             ndc_camera=(intr.fx, intr.fy, intr.width, intr.height))
  out = jax.jit(model.apply)({}, origins, directions, 0.0, 1.0, jnp.ones(3))[-1]
  np.testing.assert_allclose(out["acc"], 1.0, atol=1e-4)
  np.testing.assert_allclose(out["disparity"], 1.0 / wall, atol=2.0 / 256)
  np.testing.assert_allclose(out["depth"], wall, rtol=0.05)
