"""The one config schema: every field of every config, declared once in FIELDS (its default, the values it may
hold, what it means and whether it may change when a run resumes a workdir), and the rules between fields.

`defaults()` is the config of every field at its default: configs/default.py, which every other config starts
from. `python -m nerfpod.schema` prints every field as its override, with its default, range and meaning.
`validate(config)` checks a whole config at start-up, before any work, for every mode alike: it raises one
ConfigError listing every mistake, one sentence each, naming the field and a valid value. The entry point
runs it before JAX starts (a mistake costs nobody a device), and again with the device count once JAX runs.
No module checks config fields on its own; a config that passed here is used as it is.

This module imports no JAX (nor anything that does): checking a config takes milliseconds.
"""
import abc
import dataclasses
import math
import textwrap
from typing import Any, Callable

import ml_collections
from absl import flags
from ml_collections import config_flags

from nerfpod import scenes
from nerfpod.errors import UserError

class ConfigError(UserError):
  """Every mistake found in a config, one sentence each."""

  def __init__(self, messages: list[str]):
    super().__init__(" ".join(messages))
    self.messages = list(messages)


@dataclasses.dataclass(frozen=True)
class Field:
  """What a config field may hold: `accepts(value)` says whether it is valid, `means` says what is; and, once
  declared in FIELDS, its `default`, `doc` (what it means, one line) and whether it is `resumable`."""
  accepts: Callable[[Any], bool]
  means: str    # "an integer >= 1", ...: completes "must be ..."
  example: Any  # a valid value, shown in the message
  bad: tuple = ()  # invalid values that a command line can give (for the tests that walk every field)
  default: Any = None
  doc: str = ""
  resumable: bool = False  # may differ between a workdir's config and the run that resumes it (RESUMABLE)
  # The type ml_collections gives the field (its command-line parser's), where not its default's: a field that
  # holds a number or a word (model.region_capacity) is a FieldReference of this type in defaults()
  flag_type: type | None = None

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


class NumberOrWord(abc.ABC):
  """The type ml_collections sees for a field that holds a number or a word (model.region_capacity: a fraction
  or 'auto'): a float field's parser refuses --config.model.region_capacity=auto, and a string field's would
  keep 0.5 a string. Its parser (_NumberOrWordParser) reads a number as a float, as a float field's does, and
  anything else as the word it is, for the schema to accept or refuse in one sentence."""


for _type in (float, int, str):
  NumberOrWord.register(_type)


class _NumberOrWordParser(flags.ArgumentParser):

  def parse(self, argument):
    if not isinstance(argument, str):
      return argument
    try:
      return float(argument)
    except ValueError:
      return argument

  def flag_type(self):
    return "number or word"


config_flags.register_flag_parser_for_type(NumberOrWord, _NumberOrWordParser())


def number_or(word: str, low: float, high: float, example: float) -> Field:
  """`word` (e.g. 'auto') or a finite number in [low, high]."""
  numeric = number(low, high, example=example)
  return Field(lambda v: (isinstance(v, str) and v == word) or numeric.accepts(v), f"'{word}' or {numeric.means}",
               example, numeric.bad + ("nope",), flag_type=NumberOrWord)


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


def numbers(low: float = 0.0) -> Field:
  return Field(lambda v: isinstance(v, (tuple, list)) and all(_is_number(i) and i >= low for i in v),
               f"a tuple of numbers >= {low:g}", (0.03,), ((low - 1.0,),))


def fractions() -> Field:
  """A tuple of fractions in (0, 1] (or ())."""
  return Field(lambda v: isinstance(v, (tuple, list)) and all(_is_number(i) and 0.0 < i <= 1.0 for i in v),
               "a tuple of fractions, each > 0 and <= 1", (0.5, 0.4), ((0.0,), (1.5,)))


def step_range() -> Field:
  """() (off) or (first, last): steps counted from 1, first <= last."""
  return Field(lambda v: isinstance(v, (tuple, list)) and (len(v) == 0 or (
      len(v) == 2 and all(_is_int(i) and i >= 1 for i in v) and v[0] <= v[1])),
               "() or (first, last): two steps >= 1 with first <= last", (100, 110), ((0, 3), (5, 2), (1, 2, 3)))


def fraction_range() -> Field:
  """() (off) or (start, end): two fractions of a length, 0 <= start < end <= 1."""
  return Field(lambda v: isinstance(v, (tuple, list)) and (len(v) == 0 or (
      len(v) == 2 and all(_is_number(i) for i in v) and 0.0 <= v[0] < v[1] <= 1.0)),
               "() or (start, end): two fractions with 0 <= start < end <= 1", (0.1, 0.5),
               ((0.5, 0.1), (0.0, 2.0), (0.1, 0.2, 0.3)))


def pose_noise() -> Field:
  """() (off) or (degrees, units): two numbers >= 0."""
  return Field(lambda v: isinstance(v, (tuple, list)) and (len(v) == 0 or (
      len(v) == 2 and all(_is_number(i) and i >= 0 for i in v))),
               "() or (degrees, units): two numbers >= 0", (1.0, 0.03), ((-1.0, 0.0), (1.0,), (1.0, 0.0, 0.0)))


# A field entry's fourth item: the field may change when a run resumes a workdir (workdir.files.check_compatible
# refuses any other difference). Such a field changes neither shapes nor the trajectory's inputs (the step
# count, the cadence of logs and checkpoints, evaluation, the orbit, compilation, the mesh, monitoring, the
# host's image budget, the samples of renderings that train nothing); or it is one of the proposal sampler's
# guards, which change no state, only where samples go from the resume on: a run whose sampling collapsed is
# resumed with them (docs/training.md); or the regions' capacity, which changes no state either, only which rays
# a step may drop: a run stopped for dropping rays is resumed with a larger one. docs/scale.md lists them
# (tests/test_schema.py holds it to this).
RESUMABLE = "resumable"


def _declare(table: dict) -> dict[str, Field]:
  """{name: (default, field, doc[, RESUMABLE])} -> {name: the field with its default, doc and resumable}."""
  out = {}
  for name, (default, field, doc, *marks) in table.items():
    assert set(marks) <= {RESUMABLE}, (name, marks)
    out[name] = dataclasses.replace(field, default=default, doc=doc, resumable=RESUMABLE in marks)
  return out


# Every field of every config, declared once: "section.name": (its default, the values it may hold, what it means
# with its unit[, RESUMABLE where it may change on resuming]). The defaults are the default job's
# (configs/default.py is `defaults()`); the other configs start from it. The order is the config's own
# (config.json sorts it; the orbit archive's copy keeps it). `python -m nerfpod.schema` prints them all.
FIELDS: dict[str, Field] = _declare({
    "data.kind": ("procedural", choice(*scenes.KINDS),
        "scene format: 'procedural' and 'street' (built in), 'tiny' (npz), 'blender' (folder), captures 'llff', 'colmap', "
        "'nerfstudio', or 'auto' (told by data.path's files)"),
    "data.path": ("", text(),
        "the npz file or scene folder; the built-in scenes read none, but the street 'blocks=B' (a street B "
        "times as long: configs/street.py:blocks=B)"),
    "data.downscale": (1, integer(1),
        "integer factor the images are shrunk by (captures: images_N/ where it exists)"),
    "data.image_size": (100, integer(2, example=100),
        "the built-in scenes (procedural, street): width and height of their images, pixels"),
    "data.pixel_center": (0.5, number(0.0, 1.0, example=0.5),
        "where in its pixel a ray passes: 0.5 centre, 0.0 corner (original code)"),
    "data.llffhold": (8, integer(2, example=8),
        "captures: every Nth frame (from the first) is held out as test and val"),
    "data.orient": ("auto", choice("auto", "llff", "up", "pca", "none"),
        "captures' rotation: 'llff' avg camera, 'up' mean up -> +z, 'pca', 'none'"),
    "data.center": ("auto", choice("auto", "focus", "poses", "none"),
        "captures' origin: 'focus' (what cameras look at), 'poses' (their mean), 'none'"),
    "data.scale": (0.0, number(0.0),
        "captures' scale factor; 0: LLFF near bound at 1/0.75, else farthest camera at 1"),
    "data.space": ("auto", choice("auto", *scenes.SPACES),
        "'object', 'forward_facing' (LLFF's default), 'unbounded' (COLMAP/nerfstudio's)"),
    "data.shards": (1, integer(1, example=4),
        "training frames split into this many shards (frame i -> i mod shards); each host reads only its own: a "
        "multiple of every host count the run may use"),
    "data.host_memory_gib": (0.0, number(0.0, example=64.0),
        "images a host may hold (its shards + held-out), GiB; 0: half its memory", RESUMABLE),
    "data.pose_noise": ((), pose_noise(),
        "(degrees, units): every training camera turned by this angle about a random axis through its centre "
        "and shifted this far in a random direction (held-out cameras exact), to measure pose refinement where "
        "the truth is known, as BARF does; (): the given poses"),
    "data.pose_noise_seed": (0, integer(0), "the NumPy seed of data.pose_noise's axes and directions"),

    "model.field": ("hashgrid", choice("mlp", "hashgrid"),
        "'mlp' (NeRF's) or 'hashgrid' (Instant-NGP's encoding + small MLPs)"),
    "model.use_viewdirs": (False, boolean(),
        "feed the view direction to the colour head (view-dependent effects)"),
    "model.compute_dtype": ("float32", choice("float32", "bfloat16"),
        "matmul dtype: 'bfloat16' for mixed precision on TPU/GPU"),
    "model.appearance_dim": (0, integer(0, example=16),
        "width of a learned appearance code per training frame (GLO, NeRF-W), fed to the colour head; held-out "
        "views get the codes' mean; 0: off"),
    "model.trunc_exp": (False, boolean(),
        "the hash-grid fields' density exp(min(h, 15)) keeps its gradient above the clamp (nerfacto's trunc_exp), "
        "so a saturated density can come down; false: zero gradient there", RESUMABLE),
    "model.regions": (1, integer(1, 4096, example=4),
        "fields, one per convex region of space, parameters sharded over the mesh's region axis (NeRF-XL, "
        "docs/scale.md#scenes-bigger-than-one-chip); a divisor of the device count; 1: one field everywhere"),
    "model.region_cut": ("grid", choice("grid", "cameras", "balanced"),
        "how model.regions > 1 cuts space: 'grid' (cells of the ground plane over the hash grid's box), "
        "'cameras' (Voronoi cells of the k-means centres of the training cameras' ground positions) or "
        "'balanced' (NeRF-XL's recursive median: vertical planes where the samples along seeded training rays "
        "split evenly, so each region holds about 1/K of them)"),
    "model.region_box": ("scene", choice("scene", "own"),
        "the box each region's fields span with model.regions > 1: 'scene' (the hash grid's whole box: a hash "
        "grid stores only what its region's points touch) or 'own' (the region's cell, mapped onto the field's "
        "box axis by axis: finer along the cell's short sides; 1.2 dB lower on the street, docs/results.md)"),
    "model.region_capacity": (0.0, number_or("auto", 0.0, 1.0, example=0.5),
        "model.regions > 1, training: each chip renders, per region, only the rays whose segment meets it, up to "
        "this fraction of its rays (rows C, rounded up to a multiple of 8); a ray over capacity is dropped whole, "
        "counted, and a run dropping over 0.1% of its rays stops (docs/scale.md#dispatch-and-capacity); 'auto': "
        "the fullest region's share of the training rays, measured before the first step, plus a margin for a "
        "batch's spread (the fraction is recorded in the workdir's config.json, which a resume with 'auto' "
        "keeps); 0: every ray through every region (dense). Evaluation and renders are always dense", RESUMABLE),
    "model.region_split": (0, integer(0, 8, example=3),
        "model.regions > 1 with a capacity: a ray's samples split across its segments (a flat cost per ray, "
        "docs/scale.md#a-flat-cost-per-ray): each segment renders 2^-j of every sampling round's count, j the "
        "class of its share of the ray (the smallest 2^-j at least the share, j < this), each class with its own "
        "rows; 0 or 1: every segment with every sample"),
    "model.region_split_by": ("weights", choice("length", "weights"),
        "model.region_split=J: what picks a segment's class for the NeRF field's samples: 'weights' (the "
        "proposal rounds at the class of the segment's length, then the NeRF's samples by the segment's share of "
        "the ray's proposal weight, gathered over the regions: where the surface is; a class over its rows gives "
        "its segments the next class's samples rather than dropping them; needs proposal sampling) or 'length' "
        "(its share of the ray, before any sampling: every round at that class; docs/scale.md#a-flat-cost-per-ray)"),
    "model.region_split_capacity": ((), fractions(),
        "model.region_split=J: the capacity of each of the J sample classes, a fraction of a chip's rays "
        "(as model.region_capacity); (): model.region_capacity for every class. model.region_capacity=auto "
        "measures them (and config.json records them)", RESUMABLE),
    # model.mlp: NeRF's MLP: the Tiny NeRF tutorial's by default
    "model.mlp.num_frequencies": (6, integer(0, 30, example=10),
        "positional-encoding frequencies L of points; 0 switches it off"),
    "model.mlp.depth": (8, integer(1, example=8), "number of hidden layers"),
    "model.mlp.width": (256, integer(1, example=256), "units per hidden layer"),
    "model.mlp.skips": ((4,), integers(0), "after these (0-based) layers the encoded input is concatenated again"),
    "model.mlp.viewdir_frequencies": (4, integer(0, 30, example=4),
        "positional-encoding frequencies of view directions"),
    "model.mlp.density_activation": ("relu", choice("relu", "softplus", "exp"),
        "'relu' (paper), 'softplus' or 'exp'"),
    "model.hashgrid.bound": (1.5, number(above=0.0, example=1.5),
        "the field lives in the box [-bound, bound]^3, world units"),
    "model.hashgrid.num_levels": (8, integer(1, example=16), "resolution levels of the grid"),
    "model.hashgrid.features_per_level": (2, integer(1, example=2), "features stored per grid vertex and level"),
    "model.hashgrid.log2_table_size": (16, integer(4, 30, example=19),
        "rows per level's table, log2; finer levels share them by hashing"),
    "model.hashgrid.base_resolution": (16, integer(1, example=16), "cells per side of the coarsest level"),
    "model.hashgrid.max_resolution": (256, integer(1, example=2048), "cells per side of the finest level"),
    "model.hashgrid.hidden_width": (32, integer(1, example=64),
        "units of the density and colour MLPs' hidden layers"),
    "model.hashgrid.geo_features": (7, integer(0, example=15),
        "features passed from the density MLP to the colour MLP"),
    "model.hashgrid.scale_aware": (False, boolean(),
        "weight each level's features by how well its cells resolve the sample's pixel footprint (Zip-NeRF's "
        "anti-aliasing; the footprint from the training cameras' focal length)"),
    # model.proposal: proposal fields (render.proposal_samples): density only, in the hash grid's box,
    # model.hashgrid.features_per_level wide
    "model.proposal.num_levels": (5, integer(1, example=5),
        "resolution levels of each proposal field's hash grid"),
    "model.proposal.log2_table_size": (17, integer(4, 30, example=17), "rows per level's table, log2"),
    "model.proposal.base_resolution": (16, integer(1, example=16), "cells per side of the coarsest level"),
    "model.proposal.max_resolution": (128, integer(1, example=128), "cells per side of the finest level"),
    "model.proposal.hidden_width": (16, integer(1, example=16), "units of its one hidden layer"),

    "render.num_samples": (16, integer(1, example=64),
        "samples per ray of the NeRF field (stratified ones where no proposals)"),
    "render.num_importance": (0, integer(0),
        "extra importance samples per ray for a fine network; 0: no fine network"),
    "render.eval_samples": (0, integer(0, example=48),
        "render.num_samples of every rendering that trains nothing (evaluation, previews, orbits, the viewer, "
        "exports): more than in training gives a finer quadrature of the same field (docs/training.md); 0: "
        "render.num_samples", RESUMABLE),
    "render.proposal_samples": ((32,), integers(2),
        "intervals per ray of each proposal round, e.g. (64, 32): the NeRF field then gets render.num_samples "
        "intervals drawn from the last; (): no proposals, render.num_samples stratified samples "
        "(docs/training.md, Speed settings)"),
    "render.proposal_padding": (0.0, number(0.0, example=0.01),
        "added to every interval's weight of a proposal histogram before the next round draws from it "
        "(nerfacto: 0.01): some samples always follow the previous round's intervals, so resampling cannot trap "
        "the NeRF's window in one interval (docs/training.md); 0: the raw histogram", RESUMABLE),
    "render.last_delta": (0.0, number(0.0, example=1e10),
        "length of the last sample's interval, world units (the paper: 1e10, opaque at the far end: use it only "
        "with a fixed background colour)"),
    "render.near": (-1.0, number(example=2.0), "ray start, world units; negative: the scene's own bound"),
    "render.far": (-1.0, number(example=6.0), "ray end, world units; negative: the scene's own bound"),
    "render.space": ("euclidean", choice("euclidean", "ndc", "contract"),
        "where the field lives: 'euclidean' (the world), 'ndc' (forward-facing scenes: NDC rays, near/far in "
        "[0, 1]), 'contract' (unbounded: mip-NeRF 360's contraction into the ball of radius 2)"),
    "render.spacing": ("linear", choice("linear", "inverse", "piecewise"),
        "samples even in distance ('linear'), in 1/distance ('inverse'), or in distance up to 1 and in "
        "1/distance beyond ('piecewise', nerfacto's initial sampler)"),

    "train.num_steps": (1500, integer(0, example=1000), "optimiser steps", RESUMABLE),
    "train.batch_size": (1024, integer(1, example=4096), "rays per step, over all devices of all hosts"),
    "train.microbatches": (1, integer(0),
        "slices each device's rays are processed in (gradient accumulation); 0: as few as fit the memory (XLA's "
        "analysis of the compiled step)"),
    "train.lr_init": (1e-2, number(above=0.0, example=5e-4), "learning rate at the start (after warm-up)"),
    "train.lr_final": (1e-3, number(above=0.0, example=5e-5),
        "learning rate at the last step (log-linear decay in between)"),
    "train.lr_warmup_steps": (50, integer(0), "linear warm-up from 0, steps"),
    "train.adam_eps": (1e-15, number(above=0.0, example=1e-15),
        "Adam's epsilon (1e-15 for hash grids, 1e-8 for MLPs)"),
    "train.adam_b1": (0.9, number(0.0, 0.9999, example=0.9), "Adam's decay of the gradients' mean"),
    "train.adam_b2": (0.999, number(0.0, 0.9999, example=0.99),
        "Adam's decay of the squared gradients' mean (Instant-NGP: 0.99, which follows a hash grid's sparse "
        "gradients faster)"),
    "train.random_background": (True, boolean(), "data with alpha: composite training rays on random colours"),
    "train.grad_clip": (0.0, number(0.0), "clip the global gradient norm to this; 0: no clipping"),
    "train.sparse_table_updates": (False, boolean(),
        "Adam for the hash tables as Instant-NGP's: an entry whose gradient is exactly zero keeps its moments "
        "and value (dense Adam moves it on along its momentum)"),
    "train.interlevel_weight": (1.0, number(0.0, example=1.0),
        "proposal sampling: weight of the interlevel loss (mip-NeRF 360 eq. 13)"),
    "train.interlevel_blur": ((), numbers(0.0),
        "Zip-NeRF's anti-aliased interlevel loss: one box half-width per proposal round, in normalised ray "
        "distance (Zip-NeRF: (0.03, 0.003)), the NeRF's weights blurred by it before the proposals bound "
        "them; (): mip-NeRF 360's loss (no better on the cup and the fox: docs/results.md)"),
    "train.proposal_anneal_steps": (0, integer(0, example=1000),
        "the proposal weights are raised to a power rising from 0 to 1 over this many steps before resampling "
        "(nerfacto: 1,000, slope 10): early samples spread over the whole ray; 0: no annealing", RESUMABLE),
    "train.single_jitter": (False, boolean(),
        "one random offset per ray and sampling round, shared by all its strata (nerfacto's single jitter), "
        "rather than one per stratum"),
    "train.distortion_weight": (0.0, number(0.0, example=0.002),
        "proposal sampling: weight of the distortion loss (eq. 15); 0: off"),
    "train.near_gradient_distance": (0.0, number(0.0, example=1.0),
        "> 0: scale the field's gradients by min(1, (distance from the ray's origin / this)^2), world units: "
        "fewer floaters in front of the cameras; 0: off"),
    "train.pose_refine": (False, boolean(),
        "learn an SE(3) correction of each training frame's pose (nerfacto's camera optimiser); held-out frames "
        "keep their given poses"),
    "train.pose_lr_init": (3e-4, number(above=0.0, example=3e-4),
        "the corrections' own learning rate at the start (after warm-up); with the gate at 5, 3e-4 cost 0.13 dB "
        "on exact poses and gained 3.1 dB with every camera a degree off, 1e-3 0.49 and 3.4 (docs/results.md)"),
    "train.pose_lr_final": (3e-5, number(above=0.0, example=3e-5),
        "the corrections' own learning rate at the last step (log-linear decay, as train.lr_*)"),
    "train.pose_weight_decay": (0.0, number(0.0, example=0.01),
        "decoupled weight decay of the corrections (AdamW), pulls them to zero"),
    "train.pose_b1": (0.99, number(0.0, 0.9999, example=0.99),
        "the corrections' Adam's first-moment decay: the gradient's mean the gate tests is averaged over about "
        "1 / (1 - b1) steps; the second-moment decay is 0.999"),
    "train.pose_gate": (5.0, number(0.0, example=5.0),
        "> 0: each correction's Adam step is scaled by max(0, 1 - gate / |z|), z its gradient's mean over the "
        "spread that noise alone would give it, so a correction whose gradient is noise does not walk; 0: Adam"),
    "train.pose_pin_mean": (False, boolean(),
        "keep the corrections' mean (over the training frames) at zero: a common shift or turn of every camera, "
        "which no training pixel sees, is taken out of each update (held-out cameras keep their given poses)"),
    "train.pose_precondition": (False, boolean(),
        "CamP's preconditioning of the corrections: each frame's 6 numbers whitened by how they move its image "
        "(a shift and a turn that move it alike are decorrelated); the learning rates then step image sizes; "
        "no better than without on the default scene with poses a degree off (docs/results.md)"),
    "train.coarse_to_fine": ((), fraction_range(),
        "(start, end), fractions of train.num_steps: the hash grid's finer levels open one after another from "
        "start to end (BARF's coarse-to-fine, the coarsest level always on), so that early pose corrections "
        "follow the scene's coarse shape; (): every level from the first step"),
    "train.seed": (0, integer(0), "seeds the parameters, the ray batches and the stratified jitter"),
    "train.log_every": (100, integer(1, example=100),
        "steps between TensorBoard scalars and console lines", RESUMABLE),
    "train.image_every": (500, integer(0, example=500),
        "steps between rendered held-out views in TensorBoard; 0: never", RESUMABLE),
    "train.max_nonfinite_steps": (20, integer(1, example=20),
        "stop (exit 2) after this many steps in a row with a non-finite loss or gradient; each such step is "
        "skipped, its update never reaches the state", RESUMABLE),
    "train.profile_steps": ((), step_range(),
        "(first, last): a jax.profiler trace of these steps into the workdir (TensorBoard's profile tab, xprof); "
        "(): none", RESUMABLE),

    "compile.cpu_ynnpack": (False, boolean(),
        "CPU: let XLA hand dots to YNNPACK (its default); off, the steps ran faster on a 2-core CPU "
        "(docs/results.md). Ignored on TPU/GPU.", RESUMABLE),
    "compile.cpu_memory_gib": (3.0, number(above=0.0, example=3.0),
        "CPU: memory the train step may use (all of a process's simulated devices together) when "
        "train.microbatches=0; accelerators use their own size", RESUMABLE),
    "compile.cpu_reuse_host_memory": (True, boolean(),
        "CPU: glibc's malloc keeps freed memory for the next step instead of unmapping it (faster steps on "
        "2 cores for more peak memory; docs/results.md)", RESUMABLE),
    "compile.gradient_mean": ("auto", choice("auto", "ordered", "pmean"),
        "'ordered' (the same bits on any topology: log2(N) exchanges), 'pmean' (one all-reduce) or 'auto' "
        "(ordered on CPU, pmean on TPU/GPU; docs/scale.md)", RESUMABLE),
    "compile.hashgrid_lookup": ("auto", choice("auto", "gather", "matmul", "sparsecore"),
        "hash-grid levels: 'gather', 'matmul' (dense levels, no gather or scatter), 'sparsecore' (matmul for "
        "dense levels, Pallas gather and scatter-add kernels on the SparseCores for the rest: TPU v5p and v6e "
        "only) or 'auto' (matmul on TPU, gather elsewhere; never sparsecore; docs/pod-compile.md)", RESUMABLE),
    "compile.matmul_max_rows": (30000, integer(0, example=30000),
        "'matmul' applies to dense levels of at most this many rows", RESUMABLE),
    "compile.hashgrid_layout": ("rows", choice("rows", "lane_dense"),
        "hash-grid lookups: 'rows' ((N, 8) corner rows, (N, 8, F) values) or 'lane_dense' (samples the minor "
        "dimension: (8, N), (F, 8, N); the same values and parameters, so a checkpoint restores under either; "
        "docs/pod-compile.md)", RESUMABLE),

    "mesh.slices": (0, integer(0, example=2),
        "TPU slices joined by the data-centre network (DCN) the mesh spans; 0: as many as the devices report "
        "(1 on CPU; a count > 1 there simulates slices, docs/scale.md#multi-slice)", RESUMABLE),

    "checkpoint.every_steps": (500, integer(1, example=500),
        "steps between (asynchronous) checkpoints; one is always saved at the end", RESUMABLE),
    "checkpoint.max_to_keep": (3, integer(1, example=3), "newest checkpoints kept on disk", RESUMABLE),
    "checkpoint.preempted_exit_code": (75, integer(3, 125, example=75),
        'exit status after a preemption/SIGTERM/Ctrl-C saved a step (75: EX_TEMPFAIL of sysexits.h, "try again": '
        'schedulers requeue on it)', RESUMABLE),
    "checkpoint.storage_timeout_s": (20.0, number(above=0.0, example=20.0),
        "seconds a gs:// workdir's storage may leave a request, or a checkpoint save training waits on, "
        "unanswered before the run stops with one sentence (exit 69); below a pod's SIGTERM grace period", RESUMABLE),

    "eval.split": ("test", choice("test", "val", "train"),
        "held-out split the final metrics are computed on", RESUMABLE),
    "eval.max_views": (0, integer(0), "evaluate at most this many views of the split; 0: all", RESUMABLE),
    "eval.chunk": (4096, integer(1, example=4096),
        "rays rendered per device call, over all devices (bounds memory)", RESUMABLE),
    "eval.lpips_net": ("alex", choice("alex", "vgg", "none"),
        "LPIPS network: 'alex' (the papers'), 'vgg', or 'none'; needs nerfpod[lpips]", RESUMABLE),
    "eval.appearance_steps": (100, integer(0, example=100),
        "with appearance codes, NeRF-W's protocol: Adam steps fitting each held-out view's code on its left half "
        "(metrics on its right half, eval/metrics.json's appearance_half); 0: not fitted", RESUMABLE),
    "eval.appearance_lr": (0.01, number(above=0.0, example=0.01), "learning rate of that fit (Adam)", RESUMABLE),
    "eval.appearance_rays": (1024, integer(1, example=1024),
        "random rays of the left half per step of that fit (rounded up to a multiple of the device count)",
        RESUMABLE),
    "eval.pose_fit": ("refined", choice("refined", "always", "never"),
        "BARF's test-time pose optimisation of each held-out camera (the field frozen; eval/metrics.json's "
        "poses_optimised): for runs with train.pose_refine ('refined'), for every run ('always': the same "
        "protocol for a run without, to compare), or 'never'", RESUMABLE),
    "eval.pose_steps": (100, integer(1, example=100),
        "Adam steps of that fit, each on eval.pose_rays random pixels of the whole view", RESUMABLE),
    "eval.pose_lr": (1e-3, number(above=0.0, example=1e-3),
        "learning rate of that fit (radians and scene units), decayed log-linearly to a tenth at its last step",
        RESUMABLE),
    "eval.pose_rays": (1024, integer(1, example=1024),
        "random rays of the view per step of that fit (rounded up to a multiple of the device count)", RESUMABLE),

    "orbit.render_after_training": (True, boolean(),
        "render the orbit (archive + videos) when training ends", RESUMABLE),
    "orbit.path": ("orbit", choice("orbit", "spiral", "ellipse", "file"),
        "camera path: 'orbit' (the tutorial's circle), 'spiral' (LLFF's, from the capture's cameras), 'ellipse' "
        "(mip-NeRF 360's), 'file' (orbit.path_file)", RESUMABLE),
    "orbit.path_file": ("", text(),
        "orbit.path=file: a nerfstudio camera_path.json (its size, fov and fps rule)", RESUMABLE),
    "orbit.num_frames": (120, integer(1, example=120),
        "frames of the path (orbit: over one full turn; spiral: over two turns)", RESUMABLE),
    "orbit.elevation": (-30.0, number(-90.0, 90.0, example=-30.0),
        "degrees, the tutorial's sign: -30 is 30 degrees above the z = 0 plane", RESUMABLE),
    "orbit.radius": (4.0, number(above=0.0, example=4.0),
        "distance of the cameras from the origin they look at, world units", RESUMABLE),
    "orbit.width": (0, integer(0), "frame width, pixels; 0: the eval split's", RESUMABLE),
    "orbit.height": (0, integer(0),
        "frame height, pixels; 0: from the width with the eval split's aspect", RESUMABLE),
    "orbit.focal": (0.0, number(0.0),
        "focal length, pixels; 0: the eval split's field of view at this width", RESUMABLE),
    "orbit.chunk": (4096, integer(1, example=4096),
        "rays each host feeds per call of the whole-slice renderer (bounds memory)", RESUMABLE),
    "orbit.fps": (30.0, number(above=0.0, example=30.0), "frames per second of the exported videos", RESUMABLE),

    # monitor: TensorBoard always; Weights & Biases as well (the wandb extra)
    "monitor.wandb.mode": ("disabled", choice("disabled", "online", "offline"),
        "'online', 'offline' (a local run folder for `wandb sync`) or 'disabled'", RESUMABLE),
    "monitor.wandb.project": ("", text(), "W&B project; '': $WANDB_PROJECT, else 'nerfpod'", RESUMABLE),
    "monitor.wandb.entity": ("", text(), "W&B user or team; '': $WANDB_ENTITY, else your default entity", RESUMABLE),
    "monitor.wandb.name": ("", text(),
        "the run's display name; '': $WANDB_NAME, else the workdir's folder name", RESUMABLE),
    "monitor.wandb.tags": ((), strings(), 'the run\'s tags, e.g. ("lego", "hashgrid"); (): $WANDB_TAGS', RESUMABLE),
})


def defaults() -> ml_collections.ConfigDict:
  """A config of every field at its default (the default job, configs/default.py), in FIELDS' order."""
  config = ml_collections.ConfigDict()
  for name, field in FIELDS.items():
    *sections, leaf = name.split(".")
    node = config
    for section in sections:
      if section not in node:
        node[section] = ml_collections.ConfigDict()
      node = node[section]
    node[leaf] = (field.default if field.flag_type is None else
                  ml_collections.FieldReference(field.default, field_type=field.flag_type))
  return config


def describe() -> str:
  """Every field as its override with the default, the values it may hold and what it means: one paragraph
  each (`python -m nerfpod.schema`)."""
  return "\n".join(f"--config.{name}={_show(field.default)}  ({field.means})\n"
                   + textwrap.fill(field.doc, 100, initial_indent="    ", subsequent_indent="    ")
                   for name, field in FIELDS.items())


def resumable(name: str) -> bool:
  """Whether the field `name` may differ between a workdir's config and the run that resumes it (RESUMABLE).
  A name this version does not know (a field a workdir's config.json holds that was since removed) may where
  every field of its section may (e.g. any `eval.` name)."""
  return FIELDS[name].resumable if name in FIELDS else _resumable_section(name.split(".")[0])


def _resumable_section(section: str) -> bool:
  """Whether the section has fields and every one of them may change on resuming."""
  fields = [field for name, field in FIELDS.items() if name.split(".")[0] == section]
  return bool(fields) and all(field.resumable for field in fields)


def resumable_names() -> list[str]:
  """The fields that may change on resuming, in FIELDS' order, a section whose every field may as `section.*`
  (as the refusal of another config lists them, and docs/scale.md)."""
  out = []
  for name, field in FIELDS.items():
    section = name.split(".")[0]
    if field.resumable:
      out.append(f"{section}.*" if _resumable_section(section) else name)
  return list(dict.fromkeys(out))


def _rules(c: dict) -> list[str]:
  """Mistakes between fields (each field alone being valid)."""
  out = []
  if c["data.kind"] in scenes.LOADERS and scenes.LOADERS[c["data.kind"]].needs_path and not c["data.path"]:
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
  if c["model.regions"] > 1 and c["render.space"] != "euclidean":
    out.append(f"model.regions={c['model.regions']} cuts the world into regions, but render.space="
               f"{c['render.space']} maps the rays out of it; use --config.render.space=euclidean "
               f"(or --config.model.regions=1).")
  if c["model.region_capacity"] and c["model.regions"] == 1:
    out.append(f"model.region_capacity={_show(c['model.region_capacity'])} shares each region's rows out among the "
               f"rays that meet it, and model.regions=1 has one region that every ray meets; leave it at 0 "
               f"(--config.model.region_capacity=0) or give more regions.")
  split, split_capacity = c["model.region_split"], c["model.region_split_capacity"]
  if split > 1 and (c["model.regions"] == 1 or not c["model.region_capacity"]):
    out.append(f"model.region_split={split} splits a ray's samples across its segments in the regions' "
               f"compacted step, which needs model.regions > 1 and a capacity; add "
               f"--config.model.region_capacity=auto (or --config.model.region_split=0).")
  if split > 1 and c["model.region_split_by"] == "weights" and not c["render.proposal_samples"]:
    out.append(f"model.region_split={split} splits the NeRF field's samples by the proposal rounds' weights "
               f"(model.region_split_by=weights), and render.proposal_samples=() has no proposal rounds; use "
               f"--config.model.region_split_by=length (or give proposal rounds, e.g. "
               f"--config.render.proposal_samples='(32,)').")
  if split_capacity and len(split_capacity) != max(split, 1):
    out.append(f"model.region_split_capacity={_show(split_capacity)} gives {len(split_capacity)} capacities for "
               f"model.region_split={split}'s {max(split, 1)} sample class(es); give one fraction per class "
               f"(or --config.model.region_split_capacity='()': model.region_capacity for every class).")
  if c["model.regions"] > 1 and c["render.num_importance"]:
    out.append(f"model.regions={c['model.regions']} renders each region's segment with proposal or stratified "
               f"samples, not hierarchical ones; use --config.render.num_importance=0 (or "
               f"--config.model.regions=1).")
  if c["model.hashgrid.scale_aware"] and (c["model.field"] != "hashgrid" or c["render.space"] == "ndc"
                                           or c["model.regions"] > 1):
    out.append(f"model.hashgrid.scale_aware weighs the hash grid's levels by pixel footprints in world or "
               f"contracted space, and this run has model.field={c['model.field']}, render.space="
               f"{c['render.space']}, model.regions={c['model.regions']}; use it with model.field=hashgrid, "
               f"render.space euclidean or contract and one region (or --config.model.hashgrid.scale_aware=false).")
  rounds = len(c["render.proposal_samples"])
  for name, value in (("render.proposal_padding", c["render.proposal_padding"]),
                      ("train.proposal_anneal_steps", c["train.proposal_anneal_steps"])):
    if value and not rounds:
      out.append(f"{name}={_show(value)} shapes the proposal rounds' histograms, and render.proposal_samples='()' "
                 f"has none: leave it at 0 (--config.{name}=0) or give proposal rounds.")
  if c["train.single_jitter"] and c["render.num_importance"]:
    out.append(f"train.single_jitter=true cannot be used with render.num_importance={c['render.num_importance']}: "
               f"the fine round draws its samples from unsorted random numbers, and one per ray would put them "
               f"all at one point; use proposal sampling or stratified samples (--config.render.num_importance=0) "
               f"or --config.train.single_jitter=false.")
  if c["train.proposal_anneal_steps"] > c["train.num_steps"]:
    out.append(f"train.proposal_anneal_steps={c['train.proposal_anneal_steps']} is longer than the run "
               f"(train.num_steps={c['train.num_steps']}): its proposals would be resampled annealed to the end; "
               f"use at most the run's length (e.g. --config.train.proposal_anneal_steps="
               f"{min(1000, c['train.num_steps'] // 10)}).")
  if c["train.interlevel_blur"] and len(c["train.interlevel_blur"]) != rounds:
    fix = (f"give one radius per round (e.g. --config.train.interlevel_blur={_show((0.03,) * rounds)}) or "
           if rounds else "")
    out.append(f"train.interlevel_blur={_show(c['train.interlevel_blur'])} blurs the interlevel loss of each "
               f"proposal round, and render.proposal_samples={_show(c['render.proposal_samples'])} has {rounds}: "
               f"{fix}use --config.train.interlevel_blur='()'.")
  if c["train.coarse_to_fine"] and (c["model.field"] != "hashgrid" or c["model.regions"] > 1):
    out.append(f"train.coarse_to_fine={_show(c['train.coarse_to_fine'])} opens the hash grid's levels one by one, "
               f"and this run has model.field={c['model.field']}, model.regions={c['model.regions']}; use it "
               f"with model.field=hashgrid and one region (or --config.train.coarse_to_fine='()').")
  ceiling = math.sqrt((1 + c["train.pose_b1"]) / (1 - c["train.pose_b1"]))  # the gate's statistic stays under it
  if c["train.pose_refine"] and c["train.pose_gate"] >= ceiling:
    out.append(f"train.pose_gate={c['train.pose_gate']:g} would never open at train.pose_b1={c['train.pose_b1']:g}: "
               f"the gate's statistic stays under sqrt((1 + b1) / (1 - b1)) = {ceiling:.1f}; lower the gate or "
               f"raise train.pose_b1 (e.g. --config.train.pose_b1=0.99).")
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
  regions = c.get("model.regions", 1)
  if regions > 1 and (device_count % regions or (slices and (device_count // slices) % regions)):
    per_slice = device_count // max(slices, 1)
    fits = [d for d in range(2, per_slice + 1) if per_slice % d == 0]
    shown = ", ".join(map(str, fits[:8])) + (", ..." if len(fits) > 8 else "")
    return [f"model.regions={regions} does not split over the {per_slice} devices of a slice (each region's "
            f"fields live on the devices of its place on the mesh's region axis); make it a divisor of "
            f"{per_slice} (one of {shown or 'none above 1'}) or 1."]
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


# TPU generations whose SparseCores compile.hashgrid_lookup=sparsecore runs on (nerf/sparsecore.py): those that
# JAX's Pallas reaches (jax/_src/pallas/mosaic/tpu_info.py): v5p has 4 SparseCores of 16 vector subcores a chip,
# v6e 2 of 16; v4's are not reachable from Pallas and v5e has none.
SPARSECORE_GENERATIONS = ("v5p", "v6e")


def backend_rules(c: dict, backend: str, tpu_generation: str | None = None, pod: str | None = None) -> list[str]:
  """Mistakes that depend on what runs the program: the run's JAX backend ('cpu', 'gpu', 'tpu'), and for a
  TPU the chip generation where it is known (`nerfpod aot`: `pod`, the pod's name, with its generation)."""
  if c["compile.hashgrid_lookup"] != "sparsecore":
    return []
  what = ("compile.hashgrid_lookup=sparsecore runs the hash grid's lookups on the SparseCores of TPU "
          f"{' and '.join(SPARSECORE_GENERATIONS)}")
  fix = "use --config.compile.hashgrid_lookup=auto"
  if backend != "tpu":
    return [f"{what}, and this run's backend is {backend}; {fix}."]
  if tpu_generation is not None and tpu_generation not in SPARSECORE_GENERATIONS:
    where = f"{pod} ({tpu_generation})" if pod else tpu_generation
    return [f"{what}, and {where} has none that Pallas reaches; {fix}, or compile for a "
            f"{' or '.join(SPARSECORE_GENERATIONS)} pod."]
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


def problems(config, device_count: int | None = None, backend: str | None = None,
             tpu_generation: str | None = None, pod: str | None = None) -> list[str]:
  """Every mistake in `config`, one sentence each; empty if it is valid. With `device_count` (a run on this
  machine), also the batch's split over the devices, the optional packages the config asks for and what the
  run's `backend` (default: JAX's) cannot run; `nerfpod aot` names backend 'tpu' and the pod (`pod`, its
  `tpu_generation`)."""
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
    if backend is None:
      import jax  # only for a run's check: the schema itself needs no JAX
      backend = jax.default_backend()
    out += device_rules(flat, device_count) + package_rules(flat) + backend_rules(flat, backend, tpu_generation,
                                                                                 pod)
  return out


def validate(config, device_count: int | None = None, backend: str | None = None,
             tpu_generation: str | None = None, pod: str | None = None) -> None:
  """Raises ConfigError with every mistake in `config` (device_count: also check the batch's split and what
  the backend cannot run; the rest as for problems)."""
  found = problems(config, device_count, backend, tpu_generation, pod)
  if found:
    raise ConfigError(found)


if __name__ == "__main__":
  print(describe())
