"""Evaluation protocols for per-frame parameters (nerfpod.run.protocols): the similarity of two camera sets
(Umeyama) against known answers, held-out cameras aligned into a refined frame that drifted by one
similarity, the pinned mean of the pose corrections, NeRF-W's half-image appearance fit, BARF's test-time
pose fit, and the blocks evaluate() adds to metrics.json. Tiny fields and images: seconds."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import procs
from conftest import smoke_config
from nerfpod import distributed
from nerfpod.nerf import alignment, cameras, pose_correction
from nerfpod.render import metrics, renderer
from nerfpod.run import components, evaluate, protocols, train_state


def _rotation(rng) -> np.ndarray:
  q, r = np.linalg.qr(rng.normal(size=(3, 3)))
  q = q * np.sign(np.diag(r))
  return q if np.linalg.det(q) > 0 else -q


def _objective(src, dst, s, rotation, t) -> float:
  return float(np.sum((dst - (s * src @ rotation.T + t))**2))


@pytest.mark.parametrize("seed", range(4))
def test_umeyama_gives_back_a_known_similarity_and_no_nearby_one_fits_better(seed):
  rng = np.random.default_rng(seed)
  src = rng.normal(size=(20, 3))
  s, rotation, t = float(np.exp(rng.normal() * 0.5)), _rotation(rng), rng.normal(size=3)
  dst = s * src @ rotation.T + t
  got_s, got_r, got_t = alignment.umeyama(src, dst)
  np.testing.assert_allclose(got_s, s, rtol=1e-10)
  np.testing.assert_allclose(got_r, rotation, atol=1e-10)
  np.testing.assert_allclose(got_t, t, atol=1e-10)
  # With noise, the least-squares answer: every small perturbation of (s, R, t) fits worse (brute force).
  noisy = dst + 0.05 * rng.normal(size=dst.shape)
  best = alignment.umeyama(src, noisy)
  floor = _objective(src, noisy, *best)
  for _ in range(200):
    w = rng.normal(size=3) * 1e-2
    perturbed = (best[0] * (1 + rng.normal() * 1e-2), pose_correction.so3_exp_numpy(w) @ best[1],
                 best[2] + rng.normal(size=3) * 1e-2)
    assert _objective(src, noisy, *perturbed) >= floor
  assert np.linalg.det(best[1]) > 0.999  # a rotation, never a reflection


def test_umeyama_of_one_point_is_a_translation():
  s, rotation, t = alignment.umeyama(np.ones((4, 3)), np.ones((4, 3)) + [1.0, 2.0, 3.0])
  assert s == 1.0 and np.array_equal(rotation, np.eye(3))
  np.testing.assert_allclose(t, [1.0, 2.0, 3.0])


def _drifted(given_Nx4x4, s, rotation, t) -> np.ndarray:
  """Pose corrections (N, 6) that move every given camera by the similarity x -> s R x + t (the refined
  cameras of a run whose cameras and scene drifted together)."""
  moved = alignment.transform_poses(given_Nx4x4, s, rotation, t)
  corrections = np.zeros((len(given_Nx4x4), 6))
  corrections[:, :3] = moved[:, :3, 3] - given_Nx4x4[:, :3, 3]
  angle = np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))
  axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
  corrections[:, 3:] = axis / (2 * np.sin(angle)) * angle
  np.testing.assert_allclose(pose_correction.corrected_poses(given_Nx4x4, corrections), moved, atol=1e-9)
  return corrections


def test_held_out_rays_through_the_gauge_are_the_given_rays_moved_by_the_scenes_similarity():
  """Every training camera (and so the scene) moved by one similarity: the gauge found from the refined
  training cameras maps a held-out camera's rays to its given rays moved by that similarity, so the
  held-out view sees the moved scene exactly as the given one saw the scene."""
  given = np.stack([cameras.spherical_pose(a, 20.0 + 10 * (i % 3), 1.0) for i, a in enumerate(range(0, 360, 24))])
  s, rotation, t = 1.07, pose_correction.so3_exp_numpy(np.array([0.02, -0.03, 0.05])), np.array([0.03, -0.01, 0.02])
  params = {"params": {pose_correction.PARAM: jnp.asarray(_drifted(given, s, rotation, t), jnp.float32)}}
  similarity = protocols.gauge(params, given)
  np.testing.assert_allclose(similarity[0], s, atol=1e-5)
  np.testing.assert_allclose(similarity[1], rotation, atol=1e-5)
  held_out = cameras.spherical_pose(37.0, 25.0, 1.0)
  intr = cameras.Intrinsics.from_focal(12, 10, 11.0)
  origins, directions = cameras.image_rays(held_out, intr)
  aligned_o, aligned_d = cameras.image_rays(alignment.transform_poses(held_out, *similarity), intr)
  np.testing.assert_allclose(aligned_o, s * origins @ rotation.T + t, atol=2e-5)
  np.testing.assert_allclose(aligned_d, directions @ rotation.T, atol=2e-5)
  assert np.abs(aligned_o - origins).max() > 0.05  # the drift was real
  assert protocols.gauge({"params": {}}, given) is None  # no pose refinement: no gauge
  described = protocols.describe_gauge(similarity)
  assert abs(described["rotation_deg"] - np.degrees(np.linalg.norm([0.02, -0.03, 0.05]))) < 1e-3


def test_pinned_mean_keeps_the_corrections_mean_at_zero_and_leaves_the_field_alone():
  plain = {"train.pose_refine": True, "train.lr_warmup_steps": 0, "train.pose_gate": 0.0}  # moving from step 1
  config = smoke_config(**plain, **{"train.pose_pin_mean": True})
  pinned = train_state.make_optimizer(config.train)
  free = train_state.make_optimizer(smoke_config(**plain).train)
  rng = np.random.default_rng(3)
  corrections_grads = [[(rng.normal(size=(6, 6)) + 1.0).astype(np.float32) for i in range(5)] for _ in range(2)]

  # One program rather than one per operation, its bits from optimised kernels (procs.OPTIMIZED_KERNELS), as in
  # every claim that two computations give the same bits.
  @functools.partial(jax.jit, compiler_options=procs.OPTIMIZED_KERNELS)
  def run(corrections_grads):
    params = {"params": {pose_correction.PARAM: jnp.zeros((6, 6)), "field": jnp.zeros(3)}}
    out = {}
    for (name, optimizer), grads_of_steps in zip((("pinned", pinned), ("free", free)), corrections_grads):
      p, state = params, optimizer.init(params)
      for g in grads_of_steps:
        grads = {"params": {pose_correction.PARAM: g, "field": jnp.ones(3)}}
        updates, state = optimizer.update(grads, state, p)
        p = optax.apply_updates(p, updates)
      out[name] = p
    return out

  out = jax.tree.map(np.asarray, run(corrections_grads))
  corrections = np.asarray(out["pinned"]["params"][pose_correction.PARAM])
  np.testing.assert_allclose(corrections.mean(0), 0.0, atol=1e-9)
  assert np.abs(corrections).max() > 1e-5
  assert np.abs(np.asarray(out["free"]["params"][pose_correction.PARAM]).mean(0)).max() > 1e-5  # common drift
  np.testing.assert_array_equal(out["pinned"]["params"]["field"], out["free"]["params"]["field"])


def _tiny_model():
  config = smoke_config(**{"render.proposal_samples": (), "model.use_viewdirs": True, "model.appearance_dim": 4,
                           "render.num_samples": 8})
  model = components.make_model(config, num_frames=5)
  # (NumPy float32 inputs, put on the device as they are: no program each.)
  origins = np.float32([[0.0, 0.0, 4.0]] * 2)
  params = jax.jit(model.init, static_argnums=(3, 4))(jax.random.key(0), origins, np.float32([[0.0, 0.0, -1.0]] * 2),
                                                       2.0, 6.0, np.ones(3, np.float32))
  table = jax.device_put((np.random.default_rng(5).normal(size=(5, 4)) * 0.3).astype(np.float32))
  return model, {**params, "params": {**params["params"], "appearance": table}}


def test_the_half_image_fit_recovers_a_views_own_code_and_never_changes_the_field():
  """A held-out view whose image is what the field renders with a code c far from the training codes' mean
  (an appearance the mean does not have): the code fitted on its left half renders its right half far
  closer than the mean code does; the field's parameters are the same arrays, equal, afterwards."""
  model, params = _tiny_model()
  mesh = distributed.make_mesh()
  render = renderer.make_renderer(model, mesh, 2.0, 6.0, (1.0, 1.0, 1.0))
  pose, intr = cameras.look_at(np.array([0.0, -3.5, 1.5])), cameras.Intrinsics.from_focal(16, 12, 16.0)
  own = protocols.mean_code(params) + np.array([2.0, -1.5, 1.0, -2.0])
  target = renderer.render_image(render, protocols.with_code(params, own), mesh, pose, intr, 0.5, 1024)["rgb"]
  as_mean = renderer.render_image(render, params, mesh, pose, intr, 0.5, 1024)["rgb"]
  before = jax.tree.map(np.array, params)
  fitter = protocols.make_code_fitter(model, mesh, 2.0, 6.0, (1.0, 1.0, 1.0), lr=0.1)
  code = protocols.fit_code(fitter, params, mesh, pose, intr, target, 0.5, steps=150, rays_per_step=64, seed=0)
  fitted = renderer.render_image(render, protocols.with_code(params, code), mesh, pose, intr, 0.5, 1024)["rgb"]
  right = evaluate._right_half
  mean_psnr, fit_psnr = metrics.psnr(right(as_mean), right(target)), metrics.psnr(right(fitted), right(target))
  assert mean_psnr < 30.0 and fit_psnr > mean_psnr + 10.0, (mean_psnr, fit_psnr)  # 26.1 -> 38.5 dB
  jax.tree.map(np.testing.assert_array_equal, jax.tree.map(np.array, params), before)


def _rotation_error_deg(a_4x4, b_4x4) -> float:
  return float(np.degrees(np.arccos(np.clip((np.trace(a_4x4[:3, :3].T @ b_4x4[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


def test_the_pose_fit_finds_a_held_out_camera_again_and_never_changes_the_field():
  """BARF's test-time pose fit: a field with texture at every scale (random hash tables, coarse levels the
  strongest), a view rendered from a true camera, the fit started from that camera turned by 1.5 degrees and
  moved by 0.05 units. The fitted pose renders the view far closer (29.6 -> 42 dB), lies nearer the truth in
  both its turn and its centre, is the start pose moved by the correction it reports, and the field's
  parameters are the same arrays, equal, afterwards."""
  config = smoke_config(**{"render.proposal_samples": (), "render.num_samples": 16})
  model = components.make_model(config)
  origins = jnp.asarray([[0.0, 0.0, 4.0]] * 2, jnp.float32)
  params = jax.jit(model.init, static_argnums=(3, 4))(jax.random.key(0), origins, jnp.asarray([[0.0, 0.0, -1.0]] * 2),
                                                       2.0, 6.0, jnp.ones(3))
  rng = np.random.default_rng(0)
  grid = {name: jnp.asarray(rng.normal(size=table.shape) * 3.0 ** (1 - level), jnp.float32)
          for level, (name, table) in enumerate(sorted(params["params"]["coarse"]["grid"].items()))}
  params = {"params": {"coarse": {**params["params"]["coarse"], "grid": grid}}}
  mesh = distributed.make_mesh()
  render = renderer.make_renderer(model, mesh, 2.0, 6.0, (1.0, 1.0, 1.0))
  true, intr = cameras.look_at(np.array([0.0, -3.5, 1.5])), cameras.Intrinsics.from_focal(24, 24, 24.0)
  target = renderer.render_image(render, params, mesh, true, intr, 0.5, 1024)["rgb"]
  start = pose_correction.corrected_poses(true[None], np.array([[0.04, -0.03, 0.02, 0.015, -0.02, 0.01]]))[0]
  before = jax.tree.map(np.array, params)
  fitter = protocols.make_pose_fitter(model, mesh, 2.0, 6.0, (1.0, 1.0, 1.0), lr=1e-2, steps=100)
  pose, correction = protocols.fit_pose(fitter, params, mesh, start, intr, target, 0.5, steps=100, rays_per_step=256,
                                        seed=0)
  np.testing.assert_allclose(pose, pose_correction.corrected_poses(start[None], correction[None])[0], atol=1e-12)
  at_start = metrics.psnr(renderer.render_image(render, params, mesh, start, intr, 0.5, 1024)["rgb"], target)
  fitted = metrics.psnr(renderer.render_image(render, params, mesh, pose, intr, 0.5, 1024)["rgb"], target)
  assert at_start < 32.0 and fitted > at_start + 8.0, (at_start, fitted)  # 29.6 -> 42.0 dB
  turn, shift = _rotation_error_deg(start, true), np.linalg.norm(start[:3, 3] - true[:3, 3])
  assert _rotation_error_deg(pose, true) < 0.5 * turn, (_rotation_error_deg(pose, true), turn)  # 1.54 -> 0.48
  assert np.linalg.norm(pose[:3, 3] - true[:3, 3]) < 0.8 * shift  # 0.054 -> 0.032
  described = protocols.describe_correction(correction)
  np.testing.assert_allclose(described["rotation_deg"], np.degrees(np.linalg.norm(correction[3:])), rtol=1e-6)
  jax.tree.map(np.testing.assert_array_equal, jax.tree.map(np.array, params), before)


def test_evaluate_adds_each_protocols_numbers_and_leaves_the_plain_ones_as_they_were(tmp_path):
  """A run with codes and pose refinement, its cameras drifted by one translation: metrics.json keeps the
  plain numbers (the same as a run without either) and adds "poses_aligned" (the drift found),
  "appearance_half" (per view, with the mean code's numbers beside) and "poses_optimised" (from the aligned
  cameras, each view's fitted correction beside its numbers); a run without refinement fits no pose unless
  eval.pose_fit asks for it ('always': from the given cameras)."""
  overrides = {"model.use_viewdirs": True, "eval.max_views": 1, "eval.lpips_net": "none",
               "render.proposal_samples": ()}  # (the protocols render and fit through any field: a smaller program)
  plain_comps = components.build(smoke_config(**overrides))
  plain = evaluate.evaluate(plain_comps, plain_comps.init_state().params, str(tmp_path / "plain"), 0)
  comps = components.build(smoke_config(**overrides, **{"model.appearance_dim": 4, "train.pose_refine": True,
                                                         "eval.appearance_steps": 2}))
  params = comps.init_state().params
  frames = len(comps.scene.split("train"))
  shift = jax.device_put(np.tile(np.float32([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]), (frames, 1)))  # (no program to build)
  params = {**params, "params": {**params["params"], pose_correction.PARAM: shift}}
  result = evaluate.evaluate(comps, params, str(tmp_path / "both"), 0)
  assert result["protocol"] == protocols.PLAIN and plain["protocol"] == protocols.PLAIN
  assert "poses_aligned" not in plain and "appearance_half" not in plain
  split = comps.scene.split("test")
  given = renderer.render_image(comps.renderer, params, comps.mesh, split.poses[0], split.cameras[0], 0.5, 1024)
  np.testing.assert_allclose(result["views"][0]["psnr"], metrics.psnr(np.clip(given["rgb"], 0, 1), split.image(0)),
                             rtol=1e-9)  # plain: the whole image from the given pose, as before
  aligned = result["poses_aligned"]
  assert aligned["protocol"] == protocols.ALIGNED
  np.testing.assert_allclose(aligned["similarity"]["translation"], [0.05, 0.0, 0.0], atol=1e-5)
  np.testing.assert_allclose(aligned["similarity"]["scale"], 1.0, atol=1e-5)
  half = result["appearance_half"]
  assert half["protocol"] == protocols.APPEARANCE_HALF and half["cameras"] == "aligned" and half["steps"] == 2
  assert len(half["views"]) == 1 and set(half["views"][0]["mean_code"]) == {"psnr", "ssim", "lpips"}
  assert np.isfinite(half["mean"]["psnr"]) and np.isfinite(half["mean_code"]["psnr"])
  # Recomputed here: the held-out camera moved by the drift (0.05 along x), rendered with the mean code (no
  # frames), scored whole (poses_aligned) and on its right half (appearance_half's mean_code).
  moved = np.array(split.poses[0], np.float64)
  moved[:3, 3] += [0.05, 0.0, 0.0]
  at_mean = np.clip(renderer.render_image(comps.renderer, params, comps.mesh, moved.astype(np.float32),
                                          split.cameras[0], 0.5, 1024)["rgb"], 0, 1)
  right = evaluate._right_half
  np.testing.assert_allclose(aligned["views"][0]["psnr"], metrics.psnr(at_mean, split.image(0)), rtol=1e-4)
  np.testing.assert_allclose(half["views"][0]["mean_code"]["psnr"],
                             metrics.psnr(right(at_mean), right(split.image(0))), rtol=1e-4)
  assert abs(half["views"][0]["mean_code"]["psnr"] - result["views"][0]["psnr"]) > 1e-3  # another image than plain
  fitted = result["poses_optimised"]
  assert fitted["protocol"] == protocols.POSES_OPTIMISED and fitted["cameras"] == "aligned"
  assert (fitted["steps"], fitted["rays_per_step"]) == (comps.config.eval.pose_steps, comps.config.eval.pose_rays)
  assert len(fitted["views"]) == 1 and set(fitted["views"][0]["correction"]) == {"rotation_deg", "translation"}
  assert np.isfinite(fitted["mean"]["psnr"]) and fitted["correction"] == fitted["views"][0]["correction"]
  always = components.build(smoke_config(**overrides, **{"eval.pose_fit": "always"}))
  result = evaluate.evaluate(always, plain_comps.init_state().params, str(tmp_path / "always"), 0)
  assert result["views"] == plain["views"] and result["poses_optimised"]["cameras"] == "plain"
  assert "poses_aligned" not in result and len(result["poses_optimised"]["views"]) == 1


def test_a_workdir_written_before_train_pose_pin_mean_resumes_with_it_at_its_default():
  """config.json of a run from before the field: absent counts as the default (what that run did), so the
  run resumes and evaluates; asking for the field's other value is refused as any other change would be."""
  import json

  from nerfpod.workdir import files as workdir_files
  saved = json.loads(smoke_config(**{"train.pose_refine": True}).to_json_best_effort())
  del saved["train"]["pose_pin_mean"]
  same = smoke_config(**{"train.pose_refine": True})
  assert workdir_files.incompatible_fields(saved, json.loads(same.to_json_best_effort())) == []
  pinned = smoke_config(**{"train.pose_refine": True, "train.pose_pin_mean": True})
  assert workdir_files.incompatible_fields(saved, json.loads(pinned.to_json_best_effort())) == ["train.pose_pin_mean"]


@pytest.mark.slow
def test_the_main_jobs_held_out_cameras_moved_by_half_a_degree_are_found_again(default_run):
  """The main job's model (conftest.default_run, also the README's headline metrics), a test view whose camera
  is turned by 0.5 degrees about a random axis and moved by 0.01 units (about 1.2 pixels): from the moved
  camera its PSNR falls by several dB (27.8 -> 18.4); the pose fit at the config's settings (eval.pose_*),
  started there, ends within 0.3 dB of the given cameras' PSNR and nearer the true cameras than it started."""
  from nerfpod.run import trained
  assert default_run.result.returncode == 0, default_run.result.stderr[-3000:]
  run = trained.restore(str(default_run.workdir))
  comps, config = run.comps, run.config
  split = comps.scene.split("test")
  fitter = protocols.make_pose_fitter(comps.render_model, comps.mesh, comps.near, comps.far, comps.background,
                                      config.eval.pose_lr, config.eval.pose_steps)
  rng = np.random.default_rng(7)
  for index in (0,):
    true, intr, truth = np.asarray(split.poses[index], np.float64), split.cameras[index], split.image(index)
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    move = np.concatenate([0.01 * direction / np.linalg.norm(direction), np.radians(0.5) * axis / np.linalg.norm(axis)])
    start = pose_correction.corrected_poses(true[None], move[None])[0]
    psnr = lambda pose: metrics.psnr(np.clip(renderer.render_image(  # noqa: E731
        comps.renderer, run.params, comps.mesh, pose, intr, 0.5, config.eval.chunk)["rgb"], 0.0, 1.0), truth)
    pose, _ = protocols.fit_pose(fitter, run.params, comps.mesh, start, intr, truth, 0.5, config.eval.pose_steps,
                                 config.eval.pose_rays, seed=index)
    given, moved, fitted = psnr(true), psnr(start), psnr(pose)
    print(f"view {index}: given {given:.2f} dB, moved {moved:.2f}, fitted {fitted:.2f}; turn "
          f"{_rotation_error_deg(start, true):.3f} -> {_rotation_error_deg(pose, true):.3f} deg, centre "
          f"{np.linalg.norm(start[:3, 3] - true[:3, 3]):.4f} -> {np.linalg.norm(pose[:3, 3] - true[:3, 3]):.4f}")
    assert moved < given - 3.0 and fitted > given - 0.3, (given, moved, fitted)
    assert _rotation_error_deg(pose, true) < 0.5 * _rotation_error_deg(start, true)
