"""Held-out evaluation: render the views of a split; PSNR, SSIM and LPIPS per view and on average."""

import jax
import numpy as np

from nerfpod import storage
from nerfpod.render import lpips, metrics, renderer, video
from nerfpod.workdir import files as workdir_files

METRICS = ("psnr", "ssim", "lpips")  # per view and their means, in eval/metrics.json and TensorBoard


def render_views(comps, params):
  """(index, rendering) of each evaluated view of eval.split: the first eval.max_views (0: all)."""
  config = comps.config
  split = comps.scene.split(config.eval.split)
  count = len(split) if config.eval.max_views <= 0 else min(len(split), config.eval.max_views)
  for index in range(count):
    yield index, renderer.render_image(comps.renderer, params, comps.mesh, split.poses[index], split.cameras[index],
                                     config.data.pixel_center, config.eval.chunk)


def _finite_or_null(entry: dict) -> dict:
  """`entry` with its non-finite metrics as null (valid JSON, unlike a bare NaN) and a "reason" saying why:
  a rendering with NaNs or infinities (a diverged model), or a view equal to its target (infinite PSNR).
  A metric that is None already (LPIPS not computed) stays null without a reason here."""
  bad = [name for name in METRICS if entry.get(name) is not None and not np.isfinite(entry[name])]
  if not bad:
    return entry
  out = dict(entry, **{name: None for name in bad})
  reason = (f"{' and '.join(bad)} not finite ({', '.join(f'{n}={entry[n]}' for n in bad)}): a rendering "
            f"with non-finite values, or one equal to its target")
  out["reason"] = f"{entry['reason']}; {reason}" if entry.get("reason") else reason
  return out


def _lpips_evaluator(comps):
  """(evaluator or None, why not): LPIPS with eval.lpips_net on the run's mesh, where it can be computed."""
  net = comps.config.eval.lpips_net
  if net == "none":
    return None, "eval.lpips_net is 'none'."
  if not lpips.available(net):
    return None, lpips.MISSING + "."
  return lpips.evaluator(comps.mesh, net), None


def _add_lpips(views: list, pending: list, evaluator) -> None:
  """Fills in the LPIPS of the views in `pending` [(position in views, rgb, truth)], all of one size."""
  values = evaluator.distances(np.stack([p[1] for p in pending]), np.stack([p[2] for p in pending]))
  for (position, _, _), value in zip(pending, values):
    views[position]["lpips"] = float(value)
  pending.clear()


def evaluate(comps, params, workdir: str, step: int, writer=None) -> dict:
  """Renders eval.split with `comps`' renderer, writes workdir/eval/metrics.json (process 0) and returns
  the metrics. `writer`: TensorBoard (process 0), for the means and the first three views.

  LPIPS (eval.lpips_net) is computed on the mesh's devices a batch of views at a time (as many as there are
  devices, of one size). Where it cannot be, "lpips" is null: for every view, with "lpips_note" saying why
  in one sentence (the lpips extra absent, eval.lpips_net='none'), or for a view smaller than the network
  takes, with a "reason"."""
  config = comps.config
  split = comps.scene.split(config.eval.split)
  evaluator, why_not = _lpips_evaluator(comps)
  views, pending = [], []  # pending: views of one size waiting for their LPIPS batch
  too_small = set()  # views LPIPS cannot measure, left out of its mean
  for index, out in render_views(comps, params):
    rgb = np.clip(out["rgb"], 0.0, 1.0)
    truth = split.image(index)
    view = {"index": index, "name": split.names[index], "psnr": metrics.psnr(rgb, truth),
            "ssim": metrics.ssim(rgb, truth), "lpips": None}
    views.append(view)
    if evaluator is not None and min(rgb.shape[:2]) < lpips.MIN_SIZE[evaluator.net]:
      too_small.add(index)
      view["reason"] = (f"lpips: the view is {rgb.shape[1]}x{rgb.shape[0]} pixels, smaller than the "
                        f"{evaluator.net} network takes ({lpips.MIN_SIZE[evaluator.net]} on each side)")
    elif evaluator is not None:
      if pending and pending[0][1].shape != rgb.shape:
        _add_lpips(views, pending, evaluator)
      pending.append((len(views) - 1, rgb, truth))
      if len(pending) == comps.mesh.size:
        _add_lpips(views, pending, evaluator)
    if writer is not None and index < 3:
      writer.add_image(f"eval/{index}/rgb", np.concatenate([rgb, truth], 1), step,
                       dataformats="HWC")
      writer.add_image(f"eval/{index}/depth", video.depth_image(out["depth"], comps.near, comps.far)[..., None],
                       step, dataformats="HWC")
  if pending:
    _add_lpips(views, pending, evaluator)
  views = [_finite_or_null(v) for v in views]
  mean = {name: float(np.mean([np.nan if v[name] is None else v[name] for v in views])) for name in ("psnr", "ssim")}
  with_lpips = [v for v in views if v["index"] not in too_small]
  mean["lpips"] = (None if evaluator is None or not with_lpips else
                   float(np.mean([np.nan if v["lpips"] is None else v["lpips"] for v in with_lpips])))
  result = {"step": int(step), "scene": comps.scene.name, "split": config.eval.split,
            "lpips_net": None if evaluator is None else evaluator.net, "views": views, "mean": _finite_or_null(mean)}
  if why_not:
    result["lpips_note"] = why_not
  if jax.process_index() == 0:
    workdir_files.write_json(storage.path(workdir) / "eval" / "metrics.json", result)  # local path or gs://
    if writer is not None:
      for name in METRICS:
        if result["mean"][name] is not None:
          writer.add_scalar(f"eval/{config.eval.split}/{name}", result["mean"][name], step)
      writer.flush()
    print(f"eval {config.eval.split}: {len(views)} views, {_summary(result['mean'])}"
          + (f" (no LPIPS: {why_not})" if why_not else ""), flush=True)
  return result


def _summary(mean: dict) -> str:
  """'mean PSNR 28.82 dB, SSIM 0.9620, LPIPS 0.0412' (a null one shown as None)."""
  show = lambda name, fmt: "None" if mean[name] is None else format(mean[name], fmt)
  return (f"mean PSNR {show('psnr', '.2f')} dB, SSIM {show('ssim', '.4f')}"
          + (f", LPIPS {show('lpips', '.4f')}" if mean["lpips"] is not None else ""))
