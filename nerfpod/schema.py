"""The one config schema: every field of every config, its type and range, and the rules between fields.

`validate(config)` checks a whole config at start-up, before any work, for every mode alike: it raises one
ConfigError listing every mistake, one sentence each, naming the field and a valid value. The entry point
runs it before JAX starts (a mistake costs nobody a device), and again with the device count once JAX runs.
No module checks config fields on its own; a config that passed here is used as it is.

This module imports no JAX (nor anything that does): checking a config takes milliseconds.
"""
import dataclasses
import math
from typing import Any, Callable

from nerfpod import scenes
from nerfpod.errors import UserError

class ConfigError(UserError):
  """Every mistake found in a config, one sentence each."""

  def __init__(self, messages: list[str]):
    super().__init__(" ".join(messages))
    self.messages = list(messages)


@dataclasses.dataclass(frozen=True)
class Field:
  """What a config field may hold: `accepts(value)` says whether it is valid, `means` says what is."""
  accepts: Callable[[Any], bool]
  means: str    # "an integer >= 1", ...: completes "must be ..."
  example: Any  # a valid value, shown in the message
  bad: tuple = ()  # invalid values that a command line can give (for the tests that walk every field)

  def message(self, name: str, value) -> str | None:
    if self.accepts(value):
      return None
    return (f"{name}={_show(value)} is not valid: it must be {self.means} "
            f"(e.g. --config.{name}={_show(self.example)}).")


def _show(value) -> str:
  if isinstance(value, bool):
    return str(value).lower()
  if isinstance(value, (tuple, list)):  # strings quoted, as the command line's tuples need them: '("a",)'
    items = [f'"{v}"' if isinstance(v, str) else str(v) for v in value]
    return "'(" + ",".join(items) + (",)'" if len(value) == 1 else ")'")
  if isinstance(value, str):
    return value if value else "''"
  return str(value)


def _is_int(value) -> bool:
  return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
  return (isinstance(value, (int, float)) and not isinstance(value, bool)) and math.isfinite(value)


def integer(low: int | None = None, high: int | None = None, example: int | None = None) -> Field:
  def accepts(v):
    return _is_int(v) and (low is None or v >= low) and (high is None or v <= high)
  if low is not None and high is not None:
    means = f"an integer from {low} to {high}"
  elif low is not None:
    means = f"an integer >= {low}"
  else:
    means = "an integer"
  bad = tuple(v for v in (None if low is None else low - 1, None if high is None else high + 1) if v is not None)
  return Field(accepts, means, example if example is not None else low if low is not None else 0, bad)


def number(low: float | None = None, high: float | None = None, above: float | None = None,
           example: float | None = None) -> Field:
  """A finite number in [low, high] and > above (each where given)."""
  def accepts(v):
    return (_is_number(v) and (low is None or v >= low) and (high is None or v <= high)
            and (above is None or v > above))
  parts = []
  if above is not None:
    parts.append(f"> {above:g}")
  if low is not None:
    parts.append(f">= {low:g}")
  if high is not None:
    parts.append(f"<= {high:g}")
  means = "a finite number" + (" " + " and ".join(parts) if parts else "")
  if example is None:
    example = low if low is not None else above + 1.0 if above is not None else 0.0
  bad = tuple(v for v in (None if low is None else low - 1.0, None if high is None else high + 1.0, above)
              if v is not None) + (float("nan"),)
  return Field(accepts, means, example, bad)


def boolean() -> Field:
  return Field(lambda v: isinstance(v, bool), "true or false", True)


def choice(*values: str) -> Field:
  return Field(lambda v: v in values, "one of " + ", ".join(repr(v) for v in values), values[0], ("nope",))


def text() -> Field:
  return Field(lambda v: isinstance(v, str), "a string", "")


def strings() -> Field:
  return Field(lambda v: isinstance(v, (tuple, list)) and all(isinstance(i, str) for i in v),
               "a tuple of strings", ("nerf",), ((1,),))


def integers(low: int = 0) -> Field:
  return Field(lambda v: isinstance(v, (tuple, list)) and all(_is_int(i) and i >= low for i in v),
               f"a tuple of integers >= {low}", (low,), ((low - 1,),))


def step_range() -> Field:
  """() (off) or (first, last): steps counted from 1, first <= last."""
  return Field(lambda v: isinstance(v, (tuple, list)) and (len(v) == 0 or (
      len(v) == 2 and all(_is_int(i) and i >= 1 for i in v) and v[0] <= v[1])),
               "() or (first, last): two steps >= 1 with first <= last", (100, 110), ((0, 3), (5, 2), (1, 2, 3)))


FIELDS: dict[str, Field] = {
    "data.kind": choice(*scenes.KINDS),
    "data.path": text(),
    "data.downscale": integer(1),
    "data.image_size": integer(2, example=100),
    "data.pixel_center": number(0.0, 1.0, example=0.5),
    "data.llffhold": integer(2, example=8),
    "data.orient": choice("auto", "llff", "up", "pca", "none"),
    "data.center": choice("auto", "focus", "poses", "none"),
    "data.scale": number(0.0),
    "data.space": choice("auto", *scenes.SPACES),
    "data.shards": integer(1, example=4),
    "data.host_memory_gib": number(0.0, example=64.0),

    "model.field": choice("mlp", "hashgrid"),
    "model.use_viewdirs": boolean(),
    "model.compute_dtype": choice("float32", "bfloat16"),
    "model.appearance_dim": integer(0, example=16),
    "model.mlp.num_frequencies": integer(0, 30, example=10),
    "model.mlp.depth": integer(1, example=8),
    "model.mlp.width": integer(1, example=256),
    "model.mlp.skips": integers(0),
    "model.mlp.viewdir_frequencies": integer(0, 30, example=4),
    "model.mlp.density_activation": choice("relu", "softplus", "exp"),
    "model.hashgrid.bound": number(above=0.0, example=1.5),
    "model.hashgrid.num_levels": integer(1, example=16),
    "model.hashgrid.features_per_level": integer(1, example=2),
    "model.hashgrid.log2_table_size": integer(4, 30, example=19),
    "model.hashgrid.base_resolution": integer(1, example=16),
    "model.hashgrid.max_resolution": integer(1, example=2048),
    "model.hashgrid.hidden_width": integer(1, example=64),
    "model.hashgrid.geo_features": integer(0, example=15),
    "model.proposal.num_levels": integer(1, example=5),
    "model.proposal.log2_table_size": integer(4, 30, example=17),
    "model.proposal.base_resolution": integer(1, example=16),
    "model.proposal.max_resolution": integer(1, example=128),
    "model.proposal.hidden_width": integer(1, example=16),

    "render.num_samples": integer(1, example=64),
    "render.num_importance": integer(0),
    "render.eval_samples": integer(0, example=48),
    "render.last_delta": number(0.0, example=1e10),
    "render.proposal_samples": integers(2),
    "render.near": number(example=2.0),
    "render.far": number(example=6.0),
    "render.space": choice("euclidean", "ndc", "contract"),
    "render.spacing": choice("linear", "inverse"),

    "train.num_steps": integer(0, example=1000),
    "train.batch_size": integer(1, example=4096),
    "train.microbatches": integer(0),
    "train.lr_init": number(above=0.0, example=5e-4),
    "train.lr_final": number(above=0.0, example=5e-5),
    "train.lr_warmup_steps": integer(0),
    "train.adam_eps": number(above=0.0, example=1e-15),
    "train.adam_b1": number(0.0, 0.9999, example=0.9),
    "train.adam_b2": number(0.0, 0.9999, example=0.99),
    "train.random_background": boolean(),
    "train.grad_clip": number(0.0),
    "train.interlevel_weight": number(0.0, example=1.0),
    "train.distortion_weight": number(0.0, example=0.002),
    "train.near_gradient_distance": number(0.0, example=1.0),
    "train.pose_refine": boolean(),
    "train.pose_lr_init": number(above=0.0, example=1e-3),
    "train.pose_lr_final": number(above=0.0, example=1e-4),
    "train.pose_weight_decay": number(0.0, example=0.01),
    "train.seed": integer(0),
    "train.log_every": integer(1, example=100),
    "train.image_every": integer(0, example=500),
    "train.max_nonfinite_steps": integer(1, example=20),
    "train.profile_steps": step_range(),

    "compile.cpu_ynnpack": boolean(),
    "compile.cpu_memory_gib": number(above=0.0, example=3.0),
    "compile.cpu_reuse_host_memory": boolean(),
    "compile.gradient_mean": choice("auto", "ordered", "pmean"),
    "compile.hashgrid_lookup": choice("auto", "gather", "matmul"),
    "compile.matmul_max_rows": integer(0, example=30000),

    "mesh.slices": integer(0, example=2),

    "checkpoint.every_steps": integer(1, example=500),
    "checkpoint.max_to_keep": integer(1, example=3),
    "checkpoint.preempted_exit_code": integer(3, 125, example=75),

    "eval.split": choice("test", "val", "train"),
    "eval.max_views": integer(0),
    "eval.chunk": integer(1, example=4096),
    "eval.lpips_net": choice("alex", "vgg", "none"),

    "orbit.render_after_training": boolean(),
    "orbit.path": choice("orbit", "spiral", "ellipse", "file"),
    "orbit.path_file": text(),
    "orbit.num_frames": integer(1, example=120),
    "orbit.elevation": number(-90.0, 90.0, example=-30.0),
    "orbit.radius": number(above=0.0, example=4.0),
    "orbit.width": integer(0),
    "orbit.height": integer(0),
    "orbit.focal": number(0.0),
    "orbit.chunk": integer(1, example=4096),
    "orbit.fps": number(above=0.0, example=30.0),

    "monitor.wandb.mode": choice("disabled", "online", "offline"),
    "monitor.wandb.project": text(),
    "monitor.wandb.entity": text(),
    "monitor.wandb.name": text(),
    "monitor.wandb.tags": strings(),
}


def _rules(c: dict) -> list[str]:
  """Mistakes between fields (each field alone being valid)."""
  out = []
  if c["data.kind"] != "procedural" and not c["data.path"]:
    out.append(f"data.kind={c['data.kind']} reads its scene from data.path, which is empty: pass "
               f"--config.data.path=FILE_OR_FOLDER.")
  if c["data.kind"] == "tiny" and c["data.downscale"] != 1:
    out.append(f"data.downscale={c['data.downscale']} is not supported for the 100x100 Tiny NeRF data: "
               f"leave it at 1 (--config.data.downscale=1).")
  if c["train.batch_size"] % c["data.shards"]:
    out.append(f"train.batch_size={c['train.batch_size']} does not split into data.shards={c['data.shards']} "
               f"equal sub-batches; make the batch a multiple of the shard count (e.g. --config.train.batch_size="
               f"{max(1, c['train.batch_size'] // c['data.shards']) * c['data.shards']}).")
  if c["data.shards"] > 1 and c["eval.split"] == "train":
    out.append(f"eval.split=train cannot be evaluated with data.shards={c['data.shards']}: each host holds only "
               f"its shard of the training images; evaluate a held-out split (--config.eval.split=test).")
  if c["render.num_importance"] > 0 and c["render.num_samples"] < 3:
    out.append(f"render.num_samples={c['render.num_samples']} is too few for hierarchical sampling "
               f"(render.num_importance={c['render.num_importance']}): the fine samples are drawn from the "
               f"coarse ones' interior weights, so use at least 3 (e.g. --config.render.num_samples=64).")
  if c["render.proposal_samples"] and c["render.num_importance"] > 0:
    out.append(f"render.proposal_samples={_show(c['render.proposal_samples'])} and render.num_importance="
               f"{c['render.num_importance']} are two ways of placing samples; pick one "
               f"(e.g. --config.render.num_importance=0).")
  if c["render.num_importance"] > 0 and 0 < c["render.eval_samples"] < 3:
    out.append(f"render.eval_samples={c['render.eval_samples']} is too few for hierarchical sampling "
               f"(render.num_importance={c['render.num_importance']}): use at least 3, or 0 for "
               f"render.num_samples (e.g. --config.render.eval_samples=64).")
  if c["render.proposal_samples"] and c["render.eval_samples"] == 1:
    out.append("render.eval_samples=1 is too few for proposal sampling: use at least 2, or 0 for "
               "render.num_samples (e.g. --config.render.eval_samples=48).")
  if c["render.proposal_samples"] and c["render.num_samples"] < 2:
    out.append(f"render.num_samples={c['render.num_samples']} is too few for proposal sampling: the field's "
               f"intervals are bounded by midpoints between its samples, so use at least 2 "
               f"(e.g. --config.render.num_samples=16).")
  near, far = c["render.near"], c["render.far"]
  if near >= 0 and far >= 0 and not near < far:
    out.append(f"render.near={near:g} must be less than render.far={far:g} (e.g. --config.render.near=2 "
               f"--config.render.far=6; negative values take the scene's own bounds).")
  if c["orbit.path"] == "file" and not c["orbit.path_file"]:
    out.append("orbit.path=file renders the cameras of a camera_path.json, but orbit.path_file is empty: "
               "pass --config.orbit.path_file=FILE.")
  if c["render.space"] == "ndc" and c["render.spacing"] != "linear":
    out.append(f"render.spacing={c['render.spacing']} cannot be used with render.space=ndc: NDC rays run "
               f"from 0 at the near plane and are already even in inverse depth, so use "
               f"--config.render.spacing=linear.")
  if c["render.space"] == "ndc" and c["train.near_gradient_distance"] > 0:
    out.append(f"train.near_gradient_distance={c['train.near_gradient_distance']:g} cannot be used with "
               f"render.space=ndc, whose ray parameter is no distance from the camera: use "
               f"--config.train.near_gradient_distance=0.")
  if c["render.spacing"] == "inverse" and c["render.near"] == 0:
    out.append("render.near=0 cannot be used with render.spacing=inverse, which is even in 1 / distance: "
               "give a positive near bound (e.g. --config.render.near=0.2).")
  if (c["render.space"] == "contract" and c["model.field"] == "hashgrid"
      and c["model.hashgrid.bound"] != 2):
    out.append(f"model.hashgrid.bound={c['model.hashgrid.bound']:g} does not cover the contracted space of "
               f"render.space=contract, the ball of radius 2: use --config.model.hashgrid.bound=2.")
  if any(s >= c["model.mlp.depth"] - 1 for s in c["model.mlp.skips"]):
    out.append(f"model.mlp.skips={_show(c['model.mlp.skips'])} names layers after which the input rejoins, "
               f"so each must be below model.mlp.depth - 1 = {c['model.mlp.depth'] - 1} "
               f"(e.g. --config.model.mlp.skips='(4,)' with depth 8).")
  if c["model.appearance_dim"] and c["model.field"] == "mlp" and not c["model.use_viewdirs"]:
    out.append(f"model.appearance_dim={c['model.appearance_dim']} feeds appearance codes to the colour head, "
               f"which the MLP field without view directions shares with the density; use "
               f"--config.model.use_viewdirs=true (or --config.model.appearance_dim=0).")
  if c["model.hashgrid.max_resolution"] < c["model.hashgrid.base_resolution"]:
    out.append(f"model.hashgrid.max_resolution={c['model.hashgrid.max_resolution']} must be at least "
               f"model.hashgrid.base_resolution={c['model.hashgrid.base_resolution']}.")
  if c["model.proposal.max_resolution"] < c["model.proposal.base_resolution"]:
    out.append(f"model.proposal.max_resolution={c['model.proposal.max_resolution']} must be at least "
               f"model.proposal.base_resolution={c['model.proposal.base_resolution']}.")
  return out


def device_rules(c: dict, device_count: int) -> list[str]:
  """Mistakes that depend on the number of devices the run has."""
  batch, micro, slices = c["train.batch_size"], c["train.microbatches"], c.get("mesh.slices", 0)
  if slices and device_count % slices:
    divisors = [d for d in range(1, device_count + 1) if device_count % d == 0]
    shown = ", ".join(map(str, divisors[:8])) + (", ..." if len(divisors) > 8 else "")
    return [f"mesh.slices={slices} does not divide the {device_count} devices into slices of equal size; make it "
            f"a divisor of {device_count} (one of {shown}) or 0 for the slices the devices report."]
  if batch % device_count:
    return [f"train.batch_size={batch} does not split over {device_count} devices; make it a multiple of "
            f"{device_count} (e.g. --config.train.batch_size={max(1, batch // device_count) * device_count})."]
  if micro and batch % (device_count * micro):
    return [f"train.batch_size={batch} does not split into train.microbatches={micro} equal slices on each "
            f"of {device_count} devices; make the batch a multiple of {device_count * micro} or use fewer "
            f"micro-batches (e.g. --config.train.microbatches=1)."]
  return []


def package_rules(c: dict) -> list[str]:
  """Optional packages the config asks for that this machine lacks (checked for a run, not for the tools that
  only read a workdir's config)."""
  if c["monitor.wandb.mode"] != "disabled":
    try:
      import wandb  # noqa: F401 (imported only when asked for)
    except ImportError as e:
      return [f"monitor.wandb.mode={c['monitor.wandb.mode']} logs to Weights & Biases, but its package cannot be "
              f"imported ({e}): install nerfpod's wandb extra (pip install 'nerfpod[wandb]') or leave W&B off "
              f"(--config.monitor.wandb.mode=disabled)."]
  return []


def flatten(tree, prefix: str = "") -> dict:
  """{"a.b.c": leaf} of a nested dict or ConfigDict."""
  out = {}
  for key, value in tree.items():
    if hasattr(value, "items"):
      out.update(flatten(value, f"{prefix}{key}."))
    else:
      out[f"{prefix}{key}"] = value
  return out


def problems(config, device_count: int | None = None) -> list[str]:
  """Every mistake in `config`, one sentence each; empty if it is valid. With `device_count` (a run on this
  machine), also the batch's split over the devices and the optional packages the config asks for."""
  flat = flatten(config)
  out = []
  for name in sorted(set(flat) - set(FIELDS)):
    out.append(f"{name} is not a config field nerfpod knows; remove it (its fields are those of "
               f"configs/default.py).")
  for name in FIELDS:
    if name not in flat:
      out.append(f"the config lacks the field {name}; derive configs from configs/default.py, which has "
                 f"every field.")
  if out:
    return out
  for name, field in FIELDS.items():
    message = field.message(name, flat[name])
    if message:
      out.append(message)
  if out:  # the rules assume every field is valid on its own
    return out
  out += _rules(flat)
  if not out and device_count is not None:
    out += device_rules(flat, device_count) + package_rules(flat)
  return out


def validate(config, device_count: int | None = None) -> None:
  """Raises ConfigError with every mistake in `config` (device_count: also check the batch's split)."""
  found = problems(config, device_count)
  if found:
    raise ConfigError(found)
