"""Held-out evaluation: render the views of a split, PSNR and SSIM per view and on average."""

import jax
import numpy as np
from etils import epath

from nerfpod import metrics, render, video, workdir_files


def render_views(comps, params):
  """(index, rendering) of each evaluated view of eval.split: the first eval.max_views (0: all)."""
  config = comps.config
  split = comps.scene.split(config.eval.split)
  count = len(split) if config.eval.max_views <= 0 else min(len(split), config.eval.max_views)
  for index in range(count):
    yield index, render.render_image(comps.renderer, params, comps.mesh, split.poses[index], split.cameras[index],
                                     config.data.pixel_center, config.eval.chunk)


def _finite_or_null(entry: dict) -> dict:
  """`entry` with its non-finite PSNR/SSIM as null (valid JSON, unlike a bare NaN) and a "reason" saying why:
  a rendering with NaNs or infinities (a diverged model), or a view equal to its target (infinite PSNR)."""
  bad = [name for name in ("psnr", "ssim") if name in entry and not np.isfinite(entry[name])]
  if not bad:
    return entry
  out = dict(entry, **{name: None for name in bad})
  out["reason"] = (f"{' and '.join(bad)} not finite ({', '.join(f'{n}={entry[n]}' for n in bad)}): a rendering "
                   f"with non-finite values, or one equal to its target")
  return out


def evaluate(comps, params, workdir: str, step: int, writer=None) -> dict:
  """Renders eval.split with `comps`' renderer, writes workdir/eval/metrics.json (process 0) and returns
  the metrics. `writer`: TensorBoard (process 0), for the means and the first three views."""
  config = comps.config
  split = comps.scene.split(config.eval.split)
  views = []
  for index, out in render_views(comps, params):
    rgb = np.clip(out["rgb"], 0.0, 1.0)
    truth = split.image(index)
    views.append(_finite_or_null({"index": index, "name": split.names[index],
                                  "psnr": metrics.psnr(rgb, truth),
                                  "ssim": metrics.ssim(rgb, truth)}))
    if writer is not None and index < 3:
      writer.add_image(f"eval/{index}/rgb", np.concatenate([rgb, truth], 1), step,
                       dataformats="HWC")
      writer.add_image(f"eval/{index}/depth", video.depth_image(out["depth"], comps.near, comps.far)[..., None],
                       step, dataformats="HWC")
  result = {"step": int(step), "scene": comps.scene.name, "split": config.eval.split, "views": views,
            "mean": _finite_or_null({name: float(np.mean([np.nan if v[name] is None else v[name] for v in views]))
                                     for name in ("psnr", "ssim")})}
  if jax.process_index() == 0:
    workdir_files.write_json(epath.Path(workdir) / "eval" / "metrics.json", result)  # local path or gs://
    if writer is not None:
      for name in ("psnr", "ssim"):
        if result["mean"][name] is not None:
          writer.add_scalar(f"eval/{config.eval.split}/{name}", result["mean"][name], step)
      writer.flush()
    mean = result["mean"]
    print(f"eval {config.eval.split}: {len(views)} views, mean PSNR {mean['psnr']} dB, SSIM {mean['ssim']}"
          if "reason" in mean else f"eval {config.eval.split}: {len(views)} views, mean PSNR {mean['psnr']:.2f} "
          f"dB, SSIM {mean['ssim']:.4f}", flush=True)
  return result
