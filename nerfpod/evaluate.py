"""Held-out evaluation: render the views of a split, PSNR and SSIM per view and on average."""

import jax
import numpy as np
from etils import epath

from nerfpod import checkpoints, distributed, metrics, render, xla_options
from nerfpod.errors import UserError


def depth_image(depth_HxW, near: float, far: float) -> np.ndarray:
  """Depth mapped to [0, 1] between the ray bounds (near white, far black), for viewing."""
  return np.clip((far - np.asarray(depth_HxW)) / (far - near), 0.0, 1.0)


def check_config(config) -> None:
  """Refuses evaluation settings that cannot work, before any training or rendering starts."""
  if config.eval.chunk <= 0:
    raise UserError(f"eval.chunk={config.eval.chunk} must be a positive number of rays.")


def render_views(config, scene, render_fn, params, mesh):
  """(index, rendering) of each evaluated view of config.eval.split: the first eval.max_views (0: all)."""
  split = scene.split(config.eval.split)
  count = len(split) if config.eval.max_views <= 0 else min(len(split), config.eval.max_views)
  for index in range(count):
    yield index, render.render_image(render_fn, params, mesh, split.poses[index], split.intrinsics,
                                     config.data.pixel_center, config.eval.chunk)


def evaluate(config, scene, model, params, mesh, workdir: str, step: int, writer=None,
             render_fn=None) -> dict:
  """Renders config.eval.split, writes workdir/eval/metrics.json (process 0) and returns the metrics.

  `render_fn`: an already compiled renderer of this model and mesh (training's), else one is made.
  """
  from nerfpod.train import ray_bounds  # the trainer imports this module
  near, far = ray_bounds(config, scene)
  split = scene.split(config.eval.split)
  if render_fn is None:
    render_fn = render.make_render_fn(model, mesh, near, far, scene.background,
                                      xla_options.compiler_options(config))
  views = []
  for index, out in render_views(config, scene, render_fn, params, mesh):
    rgb = np.clip(out["rgb"], 0.0, 1.0)
    views.append({"index": index, "name": split.names[index],
                  "psnr": metrics.psnr(rgb, split.images[index]),
                  "ssim": metrics.ssim(rgb, split.images[index])})
    if writer is not None and index < 3:
      writer.add_image(f"eval/{index}/rgb", np.concatenate([rgb, split.images[index]], 1), step,
                       dataformats="HWC")
      writer.add_image(f"eval/{index}/depth", depth_image(out["depth"], near, far)[..., None], step,
                       dataformats="HWC")
  result = {"step": int(step), "scene": scene.name, "split": config.eval.split, "views": views,
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


def evaluate_workdir(config, workdir: str) -> dict:
  """--mode=eval: evaluates workdir's newest checkpoint (no training) and writes eval/metrics.json."""
  from nerfpod import train
  trained = train.load_trained(config, workdir)
  writer = distributed.summary_writer(workdir)
  try:
    return evaluate(config, trained.scene, trained.model, trained.state.params, trained.mesh, workdir,
                    trained.step, writer=writer)
  finally:
    if writer is not None:
      writer.close()
