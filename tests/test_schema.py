"""The config schema: every field of every config is checked before any work, one sentence per mistake."""
import json
import re

import ml_collections
import pytest

import procs
from conftest import REPO, load_config, smoke_config
from nerfpod import scenes, schema
from nerfpod.errors import UserError

CONFIGS = ["default", "tiny", "blender", "tiny_fast", "blender_fast", "llff", "capture"]


@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("arg", [None, "smoke"])
def test_every_shipped_config_is_valid_and_every_field_is_in_the_schema(name, arg):
  config = load_config(name, arg)
  assert set(schema.flatten(config)) == set(schema.FIELDS)
  assert schema.problems(config, device_count=8) == []


def _with(config, name, value):
  """`config` with field `name` set to `value`, whatever its type (as a user's own config file can)."""
  *parents, leaf = name.split(".")
  node = config
  for part in parents:
    node = node[part]
  with node.ignore_type():
    node[leaf] = value
  return config


def _wrong_type(field: schema.Field):
  """A value of another type than the field takes."""
  return "x" if field.accepts(field.example) and not isinstance(field.example, str) else 3


@pytest.mark.parametrize("name", sorted(schema.FIELDS))
def test_every_bad_value_of_every_field_is_one_sentence_naming_the_field_and_a_valid_value(name):
  field = schema.FIELDS[name]
  assert field.accepts(field.example), f"{name}: its example {field.example!r} is not valid"
  for value in field.bad + (_wrong_type(field),):
    found = schema.problems(_with(smoke_config(), name, value))
    assert len(found) == 1, (name, value, found)
    assert found[0].startswith(f"{name}=") and f"--config.{name}=" in found[0], found
    assert found[0].replace("e.g. ", "").count(". ") == 0 and found[0].endswith(")."), found  # one sentence
    with pytest.raises(UserError):
      schema.validate(_with(smoke_config(), name, value))



MESSAGES = REPO / "tests" / "data" / "schema_messages.json"


def bad_value_messages() -> list[list[str]]:
  """[field, repr of a bad value, the one sentence] for every bad value (and a value of the wrong type) of
  every field, on the smoke config, in the schema's order (tests/data/README.md says how it was made)."""
  out = []
  for name, field in schema.FIELDS.items():
    for value in field.bad + (_wrong_type(field),):
      out += [[name, repr(value), message] for message in schema.problems(_with(smoke_config(), name, value))]
  return out


def test_every_bad_value_is_the_sentence_the_snapshot_pins():
  # Sorted: the fields are checked in the config's own order, where render.last_delta now follows
  # render.proposal_samples (as configs/default.py listed them before the schema declared them).
  assert sorted(bad_value_messages()) == sorted(json.loads(MESSAGES.read_text()))


@pytest.mark.parametrize("overrides,message", [
    ({"data.kind": "blender", "data.path": ""}, "data.kind=blender reads its scene from data.path, which is empty"),
    ({"data.kind": "tiny", "data.path": "x.npz", "data.downscale": 2}, "data.downscale=2 is not supported"),
    ({"render.num_importance": 8, "render.num_samples": 2, "render.proposal_samples": ()},
     "render.num_samples=2 is too few"),
    ({"render.near": 3.0, "render.far": 2.0}, "render.near=3 must be less than render.far=2"),
    ({"render.num_importance": 8, "render.proposal_samples": (32,)}, "are two ways of placing samples"),
    ({"render.num_samples": 1, "render.proposal_samples": (32,)}, "render.num_samples=1 is too few for proposal"),
    ({"render.eval_samples": 1}, "render.eval_samples=1 is too few for proposal sampling"),
    ({"render.num_importance": 8, "render.eval_samples": 2, "render.proposal_samples": ()},
     "render.eval_samples=2 is too few for hierarchical"),
    ({"model.proposal.base_resolution": 32, "model.proposal.max_resolution": 16},
     "model.proposal.max_resolution=16 must be at least model.proposal.base_resolution=32"),
    ({"model.mlp.depth": 3, "model.mlp.skips": (2,)}, "must be below model.mlp.depth - 1 = 2"),
    ({"model.hashgrid.base_resolution": 32, "model.hashgrid.max_resolution": 16},
     "model.hashgrid.max_resolution=16 must be at least model.hashgrid.base_resolution=32"),
    ({"render.space": "ndc", "render.spacing": "inverse"}, "render.spacing=inverse cannot be used with render"),
    ({"render.spacing": "inverse", "render.near": 0.0, "render.far": 10.0}, "render.near=0 cannot be used"),
    ({"render.space": "ndc", "train.near_gradient_distance": 1.0}, "train.near_gradient_distance=1 cannot be used"),
    ({"render.space": "contract"}, "model.hashgrid.bound=1.5 does not cover the contracted space"),
    ({"orbit.path": "file"}, "orbit.path=file renders the cameras of a camera_path.json, but orbit.path_file"),
    ({"model.regions": 4, "render.space": "contract", "model.hashgrid.bound": 2.0},
     "model.regions=4 cuts the world into regions, but render.space=contract"),
    ({"model.regions": 4, "render.num_importance": 8, "render.proposal_samples": ()},
     "model.regions=4 renders each region's segment with proposal or stratified samples"),
    ({"model.region_capacity": 0.5},
     "model.region_capacity=0.5 shares each region's rows out among the rays that meet it, and model.regions=1 "
     "has one region that every ray meets; leave it at 0 (--config.model.region_capacity=0) or give more "
     "regions."),
    ({"model.region_capacity": "auto"},
     "model.region_capacity=auto shares each region's rows out among the rays that meet it, and model.regions=1 "
     "has one region that every ray meets; leave it at 0 (--config.model.region_capacity=0) or give more "
     "regions."),
    ({"train.coarse_to_fine": (0.1, 0.5), "model.field": "mlp"},
     "train.coarse_to_fine='(0.1,0.5)' opens the hash grid's levels one by one, and this run has model.field=mlp"),
    ({"train.pose_refine": True, "train.pose_b1": 0.9},
     "train.pose_gate=5 would never open at train.pose_b1=0.9: the gate's statistic stays under sqrt((1 + b1) / "
     "(1 - b1)) = 4.4; lower the gate or raise train.pose_b1 (e.g. --config.train.pose_b1=0.99)."),
    ({"train.interlevel_blur": (0.03, 0.003)},
     "train.interlevel_blur='(0.03,0.003)' blurs the interlevel loss of each proposal round, and "
     "render.proposal_samples='(16,)' has 1: give one radius per round (e.g. "
     "--config.train.interlevel_blur='(0.03,)') or use --config.train.interlevel_blur='()'."),
    ({"train.interlevel_blur": (0.03,), "render.proposal_samples": ()},
     "render.proposal_samples='()' has 0: use --config.train.interlevel_blur='()'."),
    ({"train.proposal_anneal_steps": 30},
     "train.proposal_anneal_steps=30 is longer than the run (train.num_steps=20): its proposals would be "
     "resampled annealed to the end; use at most the run's length (e.g. --config.train.proposal_anneal_steps=2)."),
    ({"render.proposal_padding": 0.01, "render.proposal_samples": ()},
     "render.proposal_padding=0.01 shapes the proposal rounds' histograms, and render.proposal_samples='()' has "
     "none: leave it at 0 (--config.render.proposal_padding=0) or give proposal rounds."),
    ({"train.proposal_anneal_steps": 10, "render.proposal_samples": ()},
     "train.proposal_anneal_steps=10 shapes the proposal rounds' histograms"),
    ({"train.single_jitter": True, "render.proposal_samples": (), "render.num_importance": 8},
     "train.single_jitter=true cannot be used with render.num_importance=8: the fine round draws its samples "
     "from unsorted random numbers"),
])
def test_fields_that_must_agree_are_one_sentence(overrides, message):
  found = schema.problems(smoke_config(**overrides))
  assert len(found) == 1 and message in found[0], found


def test_the_batch_must_split_over_the_devices_and_micro_batches():
  assert schema.problems(smoke_config(**{"train.batch_size": 100}), device_count=8) == [
      "train.batch_size=100 does not split over 8 devices; make it a multiple of 8 "
      "(e.g. --config.train.batch_size=96)."]
  found = schema.problems(smoke_config(**{"train.batch_size": 64, "train.microbatches": 3}), device_count=8)
  assert len(found) == 1 and "does not split into train.microbatches=3 equal slices" in found[0]
  assert schema.problems(smoke_config(**{"train.batch_size": 100})) == []  # devices not known yet


def test_the_region_capacity_is_a_fraction_of_the_rays_or_0_or_auto():
  for capacity in (0.0, 0.01, 0.5, 1.0, 1, "auto"):
    assert schema.problems(smoke_config(**{"model.regions": 4, "model.region_capacity": capacity})) == []
  for capacity, shown in ((1.5, "1.5"), ("Auto", "Auto"), ("0.5x", "0.5x"), ("", "''"), (True, "true")):
    assert schema.problems(smoke_config(**{"model.regions": 4, "model.region_capacity": capacity})) == [
        f"model.region_capacity={shown} is not valid: it must be 'auto' or a finite number >= 0 and <= 1 "
        f"(e.g. --config.model.region_capacity=0.5)."]


def test_the_regions_must_split_over_the_devices_of_a_slice():
  assert schema.problems(smoke_config(**{"model.regions": 4}), device_count=8) == []
  assert schema.problems(smoke_config(**{"model.regions": 3}), device_count=8) == [
      "model.regions=3 does not split over the 8 devices of a slice (each region's fields live on the devices "
      "of its place on the mesh's region axis); make it a divisor of 8 (one of 2, 4, 8) or 1."]
  found = schema.problems(smoke_config(**{"model.regions": 8, "mesh.slices": 2}), device_count=8)
  assert len(found) == 1 and "model.regions=8 does not split over the 4 devices of a slice" in found[0]


def test_unknown_and_missing_fields_are_named():
  config = smoke_config()
  config.train.lr_final_ = 1.0
  del config.orbit["fps"]
  found = schema.problems(config)
  assert found == ["train.lr_final_ is not a config field nerfpod knows; remove it (its fields are those of "
                   "configs/default.py).",
                   "the config lacks the field orbit.fps; derive configs from configs/default.py, which has "
                   "every field."]


def test_the_schema_knows_every_scene_kind():
  assert schema.FIELDS["data.kind"].accepts("blender")
  for kind in scenes.KINDS:
    assert schema.FIELDS["data.kind"].accepts(kind)


def _bad_argv(name: str, value) -> list[str]:
  shown = schema._show(value).strip("'")
  return ["--config=configs/default.py:smoke", f"--workdir=/nonexistent/{name}", f"--config.{name}={shown}"]


@pytest.mark.slow
def test_the_command_refuses_every_bad_value_of_every_field_before_any_work():
  """Exit 2, one `nerfpod: error:` line naming the field, no traceback, nothing trained or written. (Each
  command runs `python -m nerfpod.main`'s entry point in a process forked from one that imported it:
  procs.run_main_each; test_an_unknown_config_argument_is_one_sentence starts the command itself.)"""
  cases = [(name, value) for name, field in schema.FIELDS.items() for value in field.bad]
  # Every field but the booleans and data.path (any string; an empty one is a rule's, tested above), whose
  # wrong values a command line cannot give: ml_collections refuses those itself.
  assert {n for n, _ in cases} == {n for n, f in schema.FIELDS.items() if f.bad} and len(cases) > 60
  results = procs.run_main_each([_bad_argv(name, value) for name, value in cases])
  for (name, value), result in zip(cases, results, strict=True):
    errors = [l for l in result.stderr.splitlines() if l.startswith("nerfpod: error:")]
    assert result.returncode == 2, (name, value, result.stderr[-2000:])
    assert len(errors) == 1 and name in errors[0], (name, value, result.stderr)
    assert "Traceback" not in result.stderr and "step " not in result.stdout, (name, value)


def test_an_unknown_config_argument_is_one_sentence(tmp_path):
  result = procs.run_main("--config=configs/blender_fast.py:scene=lego,foo", f"--workdir={tmp_path}")
  assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
  assert result.stderr.strip().splitlines() == [
      "nerfpod: error: unknown config argument 'foo' after the config file's colon; it takes: scene=..., "
      "cpu, smoke (e.g. --config=configs/blender.py:scene=lego,smoke)."]


@pytest.mark.slow  # a run of the command (no steps, but the evaluation's compiles)
def test_config_json_of_a_run_holds_exactly_the_schemas_fields(tmp_path):
  result = procs.run_main("--config=configs/default.py:smoke", f"--workdir={tmp_path}",
                          "--config.train.num_steps=0", "--config.model.mlp.num_frequencies=0",
                          "--config.orbit.render_after_training=false", timeout=300)
  assert result.returncode == 0, result.stderr[-2000:]
  saved = json.loads((tmp_path / "config.json").read_text())
  assert set(schema.flatten(saved)) == set(schema.FIELDS)
  assert saved["model"]["mlp"]["num_frequencies"] == 0


def test_config_error_lists_every_mistake():
  config = ml_collections.ConfigDict(smoke_config().to_dict())
  config.train.log_every = 0
  config.orbit.fps = -1.0
  with pytest.raises(schema.ConfigError) as error:
    schema.validate(config)
  assert [m.split("=")[0] for m in error.value.messages] == ["train.log_every", "orbit.fps"]


def test_the_fields_a_resume_may_change_are_the_schemas_and_the_docs_list_them_all():
  """RESUMABLE is each field's own; docs/scale.md's list of what may change on resuming says the same."""
  names = schema.resumable_names()
  assert {"train.num_steps", "data.host_memory_gib", "render.eval_samples", "eval.*", "monitor.*"} <= set(names)
  assert not {"train.seed", "data.shards", "model.field", "render.num_samples"} & set(names)
  assert schema.resumable("eval.a_field_since_removed") and not schema.resumable("train.a_field_since_removed")
  paragraph = (REPO / "docs" / "scale.md").read_text().split("**Resuming with another config.**")[1]
  listed = re.findall(r"`([a-z_.*]+)`", " ".join(paragraph.split(" Only ")[1].split(" may change ")[0].split()))
  assert sorted(listed) == sorted(names)
