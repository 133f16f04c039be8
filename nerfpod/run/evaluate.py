"""Held-out evaluation: render the views of a split; PSNR, SSIM and LPIPS per view and on average, under
the plain protocol and, for runs with per-frame parameters, theirs (nerfpod.run.protocols)."""

import dataclasses
from typing import Any

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
  evaluator, why_not = _lpips_evaluator(comps)
  run = _Evaluation(comps, params, comps.scene.split(config.eval.split), evaluator, why_not,
                    protocols.gauge(params, comps.scene.split("train").poses))
  chosen = [protocol for protocol in (kind.set_up(run) for kind in PROTOCOLS) if protocol is not None]
  for index, out in render_views(comps, params):
    view = _View({"index": index, "name": run.split.names[index]}, run.split.image(index),
                 run.split.poses[index], run.split.cameras[index], np.clip(out["rgb"], 0.0, 1.0))
    if writer is not None and index < 3:
      writer.add_image(f"eval/{index}/rgb", np.concatenate([view.rgb, view.truth], 1), step, dataformats="HWC")
      writer.add_image(f"eval/{index}/depth", video.depth_image(out["depth"], comps.near, comps.far)[..., None],
                       step, dataformats="HWC")
    for protocol in chosen:
      view = protocol.add(view)
  result = {"step": int(step), "scene": comps.scene.name, "split": config.eval.split,
            "lpips_net": None if evaluator is None else evaluator.net}
  blocks = []  # (protocol, its block of the result)
  for protocol in chosen:
    if protocol.key is None:  # the plain protocol's, at the top level
      result.update(protocol.result())
    else:
      result[protocol.key] = protocol.result()
    blocks.append((protocol, result if protocol.key is None else result[protocol.key]))
  if jax.process_index() == 0:
    workdir_files.write_json(storage.path(workdir) / "eval" / "metrics.json", result)  # local path or gs://
    if writer is not None:
      for name in METRICS:
        for protocol, block in blocks:
          if block["mean"][name] is not None:
            writer.add_scalar(f"eval/{config.eval.split}/{protocol.tag}{name}", block["mean"][name], step)
      writer.flush()
    for protocol, block in blocks:
      print(protocol.summary(config.eval.split, block), flush=True)
  return result


@dataclasses.dataclass(frozen=True)
class _Evaluation:
  """What the protocols of one evaluation share: the run's components and parameters, the evaluated split,
  the LPIPS evaluator (None: `why_not` says why) and the gauge of the refined cameras (protocols.gauge; None
  where the run has no pose refinement)."""
  comps: Any
  params: Any
  split: Any
  evaluator: Any
  why_not: str | None
  similarity: tuple | None

  def scores(self) -> _Scores:
    """A new protocol's scores, LPIPS in batches of as many views as the mesh has devices."""
    return _Scores(self.evaluator, self.comps.mesh.size)

  def render(self, pose, intr):
    """The whole image seen from `pose` with `intr`, clipped to [0, 1]."""
    config = self.comps.config
    out = renderer.render_image(self.comps.renderer, self.params, self.comps.mesh, pose, intr,
                                config.data.pixel_center, config.eval.chunk)
    return np.clip(out["rgb"], 0.0, 1.0)

  def seed(self, index: int) -> int:
    """The seed of view `index`'s fits (their rays drawn at random)."""
    return self.comps.config.train.seed * 1_000_003 + index

  @property
  def cameras(self) -> str:
    """Which held-out cameras the fits start from: 'plain' (as given) or 'aligned'."""
    return "plain" if self.similarity is None else "aligned"


@dataclasses.dataclass(frozen=True)
class _View:
  """A held-out view as a protocol is given it: its entry (index, name), its image, and the camera the
  protocols after the aligned one start from (the given pose, or the aligned one) with the rendering from it."""
  entry: dict
  truth: np.ndarray
  pose: np.ndarray
  intr: Any
  rgb: np.ndarray


class _Plain:
  """protocols.PLAIN: the whole image, the given pose, the mean appearance code; "views" and "mean" at the
  top level of metrics.json (with "lpips_note" where LPIPS cannot be computed)."""
  key, tag = None, ""

  @classmethod
  def set_up(cls, run: _Evaluation):
    return cls(run)

  def __init__(self, run: _Evaluation):
    self.run, self.scores = run, run.scores()

  def add(self, view: _View) -> _View:
    self.scores.add(view.entry, view.rgb, view.truth)
    return view

  def result(self) -> dict:
    views, mean = self.scores.result()
    return {"views": views, "mean": mean, "protocol": protocols.PLAIN,
            **({"lpips_note": self.run.why_not} if self.run.why_not else {})}

  def summary(self, split: str, block: dict) -> str:
    return (f"eval {split}: {len(block['views'])} views, {_summary(block['mean'])}"
            + (f" (no LPIPS: {self.run.why_not})" if self.run.why_not else ""))


class _Aligned:
  """protocols.ALIGNED (runs with pose refinement): the held-out camera mapped by the gauge; the protocols
  after it start from the aligned pose and its rendering."""
  key, tag = "poses_aligned", "aligned/"

  @classmethod
  def set_up(cls, run: _Evaluation):
    return None if run.similarity is None else cls(run)

  def __init__(self, run: _Evaluation):
    self.run, self.scores = run, run.scores()

  def add(self, view: _View) -> _View:
    pose = alignment.transform_poses(view.pose, *self.run.similarity)
    view = dataclasses.replace(view, pose=pose, rgb=self.run.render(pose, view.intr))
    self.scores.add(view.entry, view.rgb, view.truth)
    return view

  def result(self) -> dict:
    views, mean = self.scores.result()
    return {"protocol": protocols.ALIGNED, "similarity": protocols.describe_gauge(self.run.similarity),
            "views": views, "mean": mean}

  def summary(self, split: str, block: dict) -> str:
    return f"eval {split}, held-out cameras aligned: {_summary(block['mean'])}"


class _AppearanceHalf:
  """protocols.APPEARANCE_HALF (runs with appearance codes and eval.appearance_steps > 0, one region): each
  view's code fitted on its left half, metrics on its right half, beside the mean code's on that half."""
  key, tag = "appearance_half", "appearance_half/"

  @classmethod
  def set_up(cls, run: _Evaluation):
    config, comps = run.comps.config, run.comps
    if not (protocols.has_codes(run.params) and config.eval.appearance_steps > 0 and comps.model.regions == 1):
      return None
    return cls(run, protocols.make_code_fitter(comps.render_model, comps.mesh, comps.near, comps.far,
                                               comps.background, config.eval.appearance_lr,
                                               compilation.gradient_mean_is_ordered(config)))

  def __init__(self, run: _Evaluation, fitter):
    self.run, self.fitter = run, fitter
    self.half, self.half_mean = run.scores(), run.scores()

  def add(self, view: _View) -> _View:
    run, config = self.run, self.run.comps.config
    self.half_mean.add(view.entry, _right_half(view.rgb), _right_half(view.truth))
    code = protocols.fit_code(self.fitter, run.params, run.comps.mesh, view.pose, view.intr, view.truth,
                              config.data.pixel_center, config.eval.appearance_steps, config.eval.appearance_rays,
                              seed=run.seed(view.entry["index"]))
    origins, directions = (_right_half(x) for x in cameras.image_rays(view.pose, view.intr,
                                                                      config.data.pixel_center))
    got = renderer.render_rays(run.comps.renderer, protocols.with_code(run.params, code), run.comps.mesh,
                               origins.reshape(-1, 3), directions.reshape(-1, 3), config.eval.chunk)
    self.half.add(view.entry, np.clip(got["rgb"].reshape(origins.shape), 0.0, 1.0), _right_half(view.truth))
    return view

  def result(self) -> dict:
    config = self.run.comps.config
    half_views, half_means = self.half.result()
    mean_views, mean_means = self.half_mean.result()
    for view, before in zip(half_views, mean_views):
      view["mean_code"] = {name: before[name] for name in METRICS}
    return {"protocol": protocols.APPEARANCE_HALF, "cameras": self.run.cameras,
            "steps": int(config.eval.appearance_steps), "lr": float(config.eval.appearance_lr),
            "rays_per_step": int(config.eval.appearance_rays), "views": half_views, "mean": half_means,
            "mean_code": mean_means}

  def summary(self, split: str, block: dict) -> str:
    return (f"eval {split}, right halves: codes fitted on the left halves {_summary(block['mean'])}; "
            f"the mean code {_summary(block['mean_code'])}")


class _PosesOptimised:
  """protocols.POSES_OPTIMISED (eval.pose_fit, one region): each held-out camera's pose fitted to its whole
  image from the aligned pose (or the given one), metrics from the fitted pose, its correction beside them."""
  key, tag = "poses_optimised", "poses_optimised/"

  @classmethod
  def set_up(cls, run: _Evaluation):
    config, comps = run.comps.config, run.comps
    if not (comps.model.regions == 1 and (config.eval.pose_fit == "always" or
                                          (config.eval.pose_fit == "refined" and run.similarity is not None))):
      return None
    return cls(run, protocols.make_pose_fitter(comps.render_model, comps.mesh, comps.near, comps.far,
                                               comps.background, config.eval.pose_lr, config.eval.pose_steps,
                                               compilation.gradient_mean_is_ordered(config)))

  def __init__(self, run: _Evaluation, fitter):
    self.run, self.fitter = run, fitter
    self.scores, self.corrections = run.scores(), []

  def add(self, view: _View) -> _View:
    run, config = self.run, self.run.comps.config
    fitted, correction = protocols.fit_pose(self.fitter, run.params, run.comps.mesh, view.pose, view.intr,
                                            view.truth, config.data.pixel_center, config.eval.pose_steps,
                                            config.eval.pose_rays, seed=run.seed(view.entry["index"]))
    self.scores.add(view.entry, run.render(fitted, view.intr), view.truth)
    self.corrections.append(protocols.describe_correction(correction))
    return view

  def result(self) -> dict:
    config = self.run.comps.config
    views, mean = self.scores.result()
    for view, correction in zip(views, self.corrections):
      view["correction"] = correction
    return {"protocol": protocols.POSES_OPTIMISED, "cameras": self.run.cameras,
            "steps": int(config.eval.pose_steps), "lr": float(config.eval.pose_lr),
            "rays_per_step": int(config.eval.pose_rays), "views": views, "mean": mean,
            "correction": {name: float(np.median([c[name] for c in self.corrections]))
                           for name in ("rotation_deg", "translation")}}

  def summary(self, split: str, block: dict) -> str:
    return (f"eval {split}, held-out cameras fitted to their images: {_summary(block['mean'])} "
            f"(median correction {block['correction']['rotation_deg']:.3f} deg, "
            f"{block['correction']['translation']:.4f} units)")


# The protocols, in the order each view passes through them (the fits start from the aligned camera) and
# their blocks and lines come: each with set_up(run) (None where it does not apply to the run), add(view)
# (the view the next protocols get), result() (its block of metrics.json; `key` None: the top level),
# summary(split, block) (its console line) and `tag` (its TensorBoard scalars' prefix).
PROTOCOLS = (_Plain, _Aligned, _AppearanceHalf, _PosesOptimised)


def _summary(mean: dict) -> str:
  """'mean PSNR 28.82 dB, SSIM 0.9620, LPIPS 0.0412' (a null one shown as None)."""
  show = lambda name, fmt: "None" if mean[name] is None else format(mean[name], fmt)
  return (f"mean PSNR {show('psnr', '.2f')} dB, SSIM {show('ssim', '.4f')}"
          + (f", LPIPS {show('lpips', '.4f')}" if mean["lpips"] is not None else ""))
