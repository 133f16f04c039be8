"""Held-out evaluation: render the views of a split, PSNR and SSIM per view and on average."""

import jax
import numpy as np
from etils import epath

from nerfpod import checkpoints, metrics, render, video


def render_views(comps, params):
  """(index, rendering) of each evaluated view of eval.split: the first eval.max_views (0: all)."""
  config = comps.config
  split = comps.scene.split(config.eval.split)
  count = len(split) if config.eval.max_views <= 0 else min(len(split), config.eval.max_views)
  for index in range(count):
    yield index, render.render_image(comps.renderer, params, comps.mesh, split.poses[index], split.cameras[index],
                                     config.data.pixel_center, config.eval.chunk)


def evaluate(comps, params, workdir: str, step: int, writer=None) -> dict:
  """Renders eval.split with `comps`' renderer, writes workdir/eval/metrics.json (process 0) and returns
  the metrics. `writer`: TensorBoard (process 0), for the means and the first three views."""
  config = comps.config
  split = comps.scene.split(config.eval.split)
  views = []
  for index, out in render_views(comps, params):
    rgb = np.clip(out["rgb"], 0.0, 1.0)
    truth = split.image(index)
    views.append({"index": index, "name": split.names[index],
                  "psnr": metrics.psnr(rgb, truth),
                  "ssim": metrics.ssim(rgb, truth)})
    if writer is not None and index < 3:
      writer.add_image(f"eval/{index}/rgb", np.concatenate([rgb, truth], 1), step,
                       dataformats="HWC")
      writer.add_image(f"eval/{index}/depth", video.depth_image(out["depth"], comps.near, comps.far)[..., None],
                       step, dataformats="HWC")
  result = {"step": int(step), "scene": comps.scene.name, "split": config.eval.split, "views": views,
            "mean": {"psnr": float(np.mean([v["psnr"] for v in views])),
                     "ssim": float(np.mean([v["ssim"] for v in views]))}}
  if jax.process_index() == 0:
    checkpoints.write_json(epath.Path(workdir) / "eval" / "metrics.json", result)  # local path or gs://
    if writer is not None:
      writer.add_scalar(f"eval/{config.eval.split}/psnr", result["mean"]["psnr"], step)
      writer.add_scalar(f"eval/{config.eval.split}/ssim", result["mean"]["ssim"], step)
      writer.flush()
    print(f"eval {config.eval.split}: {len(views)} views, mean PSNR {result['mean']['psnr']:.2f} dB, "
          f"SSIM {result['mean']['ssim']:.4f}", flush=True)
  return result
