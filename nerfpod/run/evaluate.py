"""Held-out evaluation: render the views of a split; PSNR, SSIM and LPIPS per view and on average, under
the plain protocol and, for runs with per-frame parameters, theirs (nerfpod.run.protocols)."""

import jax
import numpy as np

from nerfpod import storage
from nerfpod.nerf import alignment, cameras
from nerfpod.render import lpips, metrics, renderer, video
from nerfpod.run import compilation, protocols
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


class _Scores:
  """PSNR, SSIM and LPIPS of views given one at a time (streamed: LPIPS in batches of views of one size, as
  many as the mesh has devices), and their means: one protocol's numbers."""

  def __init__(self, evaluator, batch: int):
    self.evaluator, self.batch = evaluator, batch
    self.views, self.pending, self.too_small = [], [], set()  # pending: (position, rgb, truth) of one size

  def add(self, entry: dict, rgb, truth) -> dict:
    """Scores `rgb` against `truth` into a copy of `entry` (index, name) and keeps it; returns it."""
    view = dict(entry, psnr=metrics.psnr(rgb, truth), ssim=metrics.ssim(rgb, truth), lpips=None)
    self.views.append(view)
    evaluator = self.evaluator
    if evaluator is not None and min(rgb.shape[:2]) < lpips.MIN_SIZE[evaluator.net]:
      self.too_small.add(len(self.views) - 1)
      view["reason"] = (f"lpips: the view is {rgb.shape[1]}x{rgb.shape[0]} pixels, smaller than the "
                        f"{evaluator.net} network takes ({lpips.MIN_SIZE[evaluator.net]} on each side)")
    elif evaluator is not None:
      if self.pending and self.pending[0][1].shape != rgb.shape:
        self._flush()
      self.pending.append((len(self.views) - 1, rgb, truth))
      if len(self.pending) == self.batch:
        self._flush()
    return view

  def _flush(self) -> None:
    """Fills in the LPIPS of the pending views."""
    values = self.evaluator.distances(np.stack([p[1] for p in self.pending]), np.stack([p[2] for p in self.pending]))
    for (position, _, _), value in zip(self.pending, values):
      self.views[position]["lpips"] = float(value)
    self.pending.clear()

  def result(self) -> tuple[list, dict]:
    """(views, mean): every view's metrics (non-finite ones null, with a reason) and their means."""
    if self.pending:
      self._flush()
    views = [_finite_or_null(v) for v in self.views]
    mean = {name: float(np.mean([np.nan if v[name] is None else v[name] for v in views])) for name in ("psnr", "ssim")}
    with_lpips = [v for i, v in enumerate(views) if i not in self.too_small]
    mean["lpips"] = (None if self.evaluator is None or not with_lpips else
                     float(np.mean([np.nan if v["lpips"] is None else v["lpips"] for v in with_lpips])))
    return views, _finite_or_null(mean)


def _right_half(image):
  """Columns W // 2 onwards of an (H, W, ...) image: where NeRF-W's protocol scores a view."""
  return image[:, image.shape[1] // 2:]


def evaluate(comps, params, workdir: str, step: int, writer=None) -> dict:
  """Renders eval.split with `comps`' renderer, writes workdir/eval/metrics.json (process 0) and returns
  the metrics. `writer`: TensorBoard (process 0), for the means and the first three views.

  LPIPS (eval.lpips_net) is computed on the mesh's devices a batch of views at a time (as many as there are
  devices, of one size). Where it cannot be, "lpips" is null: for every view, with "lpips_note" saying why
  in one sentence (the lpips extra absent, eval.lpips_net='none'), or for a view smaller than the network
  takes, with a "reason".

  "views" and "mean" are the plain protocol's (nerfpod.run.protocols; named under "protocol"): the whole
  image, the given pose, the mean appearance code. A run with pose refinement adds "poses_aligned" (the
  held-out cameras mapped into the refined cameras' frame: its similarity, views and means); one with
  appearance codes and eval.appearance_steps > 0 adds "appearance_half" (NeRF-W's: each view's code fitted
  on its left half, metrics on its right half, beside the mean code's on that same half under "mean_code";
  through the aligned cameras where there are); eval.pose_fit ('refined': runs with pose refinement) adds
  "poses_optimised" (BARF's: each held-out camera's pose fitted to its whole image from the aligned pose, or
  the given one, metrics from the fitted pose, each view's fitted correction beside them). Neither fit is made
  for a model of several regions, whose fields their programs do not shard."""
  config = comps.config
  split = comps.scene.split(config.eval.split)
  evaluator, why_not = _lpips_evaluator(comps)
  plain = _Scores(evaluator, comps.mesh.size)
  similarity = protocols.gauge(params, comps.scene.split("train").poses)
  aligned = None if similarity is None else _Scores(evaluator, comps.mesh.size)
  ordered = compilation.gradient_mean_is_ordered(config)
  fit = protocols.has_codes(params) and config.eval.appearance_steps > 0 and comps.model.regions == 1
  if fit:
    fitter = protocols.make_code_fitter(comps.render_model, comps.mesh, comps.near, comps.far, comps.background,
                                        config.eval.appearance_lr, ordered)
    half, half_mean = _Scores(evaluator, comps.mesh.size), _Scores(evaluator, comps.mesh.size)
  fit_poses = comps.model.regions == 1 and (
      config.eval.pose_fit == "always" or (config.eval.pose_fit == "refined" and similarity is not None))
  if fit_poses:
    pose_fitter = protocols.make_pose_fitter(comps.render_model, comps.mesh, comps.near, comps.far,
                                             comps.background, config.eval.pose_lr, config.eval.pose_steps, ordered)
    optimised, corrections = _Scores(evaluator, comps.mesh.size), []
  for index, out in render_views(comps, params):
    rgb = np.clip(out["rgb"], 0.0, 1.0)
    truth = split.image(index)
    entry = {"index": index, "name": split.names[index]}
    plain.add(entry, rgb, truth)
    if writer is not None and index < 3:
      writer.add_image(f"eval/{index}/rgb", np.concatenate([rgb, truth], 1), step,
                       dataformats="HWC")
      writer.add_image(f"eval/{index}/depth", video.depth_image(out["depth"], comps.near, comps.far)[..., None],
                       step, dataformats="HWC")
    pose, intr = split.poses[index], split.cameras[index]
    if similarity is not None:
      pose = alignment.transform_poses(pose, *similarity)
      out = renderer.render_image(comps.renderer, params, comps.mesh, pose, intr, config.data.pixel_center,
                                  config.eval.chunk)
      aligned.add(entry, np.clip(out["rgb"], 0.0, 1.0), truth)
    if fit:
      half_mean.add(entry, _right_half(np.clip(out["rgb"], 0.0, 1.0)), _right_half(truth))
      code = protocols.fit_code(fitter, params, comps.mesh, pose, intr, truth, config.data.pixel_center,
                                config.eval.appearance_steps, config.eval.appearance_rays,
                                seed=config.train.seed * 1_000_003 + index)
      origins, directions = (_right_half(x) for x in cameras.image_rays(pose, intr, config.data.pixel_center))
      got = renderer.render_rays(comps.renderer, protocols.with_code(params, code), comps.mesh,
                                 origins.reshape(-1, 3), directions.reshape(-1, 3), config.eval.chunk)
      half.add(entry, np.clip(got["rgb"].reshape(origins.shape), 0.0, 1.0), _right_half(truth))
    if fit_poses:
      fitted, correction = protocols.fit_pose(pose_fitter, params, comps.mesh, pose, intr, truth,
                                              config.data.pixel_center, config.eval.pose_steps,
                                              config.eval.pose_rays, seed=config.train.seed * 1_000_003 + index)
      out = renderer.render_image(comps.renderer, params, comps.mesh, fitted, intr, config.data.pixel_center,
                                  config.eval.chunk)
      optimised.add(entry, np.clip(out["rgb"], 0.0, 1.0), truth)
      corrections.append(protocols.describe_correction(correction))
  views, mean = plain.result()
  result = {"step": int(step), "scene": comps.scene.name, "split": config.eval.split,
            "lpips_net": None if evaluator is None else evaluator.net, "views": views, "mean": mean,
            "protocol": protocols.PLAIN}
  if why_not:
    result["lpips_note"] = why_not
  if aligned is not None:
    aligned_views, aligned_mean = aligned.result()
    result["poses_aligned"] = {"protocol": protocols.ALIGNED, "similarity": protocols.describe_gauge(similarity),
                               "views": aligned_views, "mean": aligned_mean}
  if fit:
    half_views, half_means = half.result()
    mean_views, mean_means = half_mean.result()
    for view, before in zip(half_views, mean_views):
      view["mean_code"] = {name: before[name] for name in METRICS}
    result["appearance_half"] = {
        "protocol": protocols.APPEARANCE_HALF, "cameras": "plain" if similarity is None else "aligned",
        "steps": int(config.eval.appearance_steps), "lr": float(config.eval.appearance_lr),
        "rays_per_step": int(config.eval.appearance_rays), "views": half_views, "mean": half_means,
        "mean_code": mean_means}
  if fit_poses:
    optimised_views, optimised_mean = optimised.result()
    for view, correction in zip(optimised_views, corrections):
      view["correction"] = correction
    result["poses_optimised"] = {
        "protocol": protocols.POSES_OPTIMISED, "cameras": "plain" if similarity is None else "aligned",
        "steps": int(config.eval.pose_steps), "lr": float(config.eval.pose_lr),
        "rays_per_step": int(config.eval.pose_rays), "views": optimised_views, "mean": optimised_mean,
        "correction": {name: float(np.median([c[name] for c in corrections])) for name in ("rotation_deg",
                                                                                           "translation")}}
  if jax.process_index() == 0:
    workdir_files.write_json(storage.path(workdir) / "eval" / "metrics.json", result)  # local path or gs://
    if writer is not None:
      for name in METRICS:
        for key, tag in ((None, ""), ("poses_aligned", "aligned/"), ("appearance_half", "appearance_half/"),
                         ("poses_optimised", "poses_optimised/")):
          block = result if key is None else result.get(key)
          if block is not None and block["mean"][name] is not None:
            writer.add_scalar(f"eval/{config.eval.split}/{tag}{name}", block["mean"][name], step)
      writer.flush()
    print(f"eval {config.eval.split}: {len(views)} views, {_summary(result['mean'])}"
          + (f" (no LPIPS: {why_not})" if why_not else ""), flush=True)
    if "poses_aligned" in result:
      print(f"eval {config.eval.split}, held-out cameras aligned: {_summary(result['poses_aligned']['mean'])}",
            flush=True)
    if "appearance_half" in result:
      block = result["appearance_half"]
      print(f"eval {config.eval.split}, right halves: codes fitted on the left halves {_summary(block['mean'])}; "
            f"the mean code {_summary(block['mean_code'])}", flush=True)
    if "poses_optimised" in result:
      block = result["poses_optimised"]
      print(f"eval {config.eval.split}, held-out cameras fitted to their images: {_summary(block['mean'])} "
            f"(median correction {block['correction']['rotation_deg']:.3f} deg, "
            f"{block['correction']['translation']:.4f} units)", flush=True)
  return result


def _summary(mean: dict) -> str:
  """'mean PSNR 28.82 dB, SSIM 0.9620, LPIPS 0.0412' (a null one shown as None)."""
  show = lambda name, fmt: "None" if mean[name] is None else format(mean[name], fmt)
  return (f"mean PSNR {show('psnr', '.2f')} dB, SSIM {show('ssim', '.4f')}"
          + (f", LPIPS {show('lpips', '.4f')}" if mean["lpips"] is not None else ""))
