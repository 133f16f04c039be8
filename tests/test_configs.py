"""The configs: every one loads, keeps the names scripts rely on, and documents its fields."""
import ast
import json

import ml_collections
import pytest

from conftest import REPO, load_config
from nerfpod.errors import UserError

CONFIGS = ["default", "tiny", "blender", "tiny_fast", "blender_fast", "llff", "capture"]
CONTRACT = ["data.path", "data.downscale", "train.num_steps", "train.seed", "checkpoint.every_steps",
            "eval.split", "eval.max_views", "orbit.num_frames"]


def _get(config, dotted):
  for part in dotted.split("."):
    config = config[part]
  return config


@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("arg", [None, "smoke"])
def test_config_loads_with_the_contract_names(name, arg):
  config = load_config(name, arg)
  for dotted in CONTRACT:
    _get(config, dotted)
  if arg == "smoke":
    assert config.train.num_steps <= 20 and config.train.batch_size <= 256


def test_config_arguments_are_parsed_and_unknown_ones_refused():
  assert load_config("blender", "scene=chair").data.path.endswith("chair")
  with pytest.raises(UserError, match="unknown config argument 'scen'"):
    load_config("blender", "scen=chair")


def test_every_field_is_declared_once_with_a_valid_default_and_what_it_means():
  """nerfpod/schema.py's FIELDS is the one declaration; configs/default.py is its defaults."""
  from nerfpod import schema
  assert len(schema.FIELDS) > 40
  for name, field in schema.FIELDS.items():
    assert field.accepts(field.default), (name, field.default)
    assert field.doc and "\n" not in field.doc and field.doc == " ".join(field.doc.split()), name
  assert load_config("default").to_dict() == schema.defaults().to_dict()
  listing = schema.describe()
  for name, field in schema.FIELDS.items():
    assert f"--config.{name}={schema._show(field.default)}  ({field.means})" in listing, name


@pytest.mark.parametrize("given,value", [(None, 0.0), ("auto", "auto"), ("0.5", 0.5), ("0", 0.0), ("1", 1.0),
                                         ("nope", "nope")])
@pytest.mark.filterwarnings("ignore:the load_module:DeprecationWarning")  # (ml_collections' loader of the file)
def test_the_region_capacity_takes_auto_or_a_number_on_the_command_line(monkeypatch, given, value):
  """--config.model.region_capacity=auto and =0.5 both parse (the field is a number or a word: schema.NumberOrWord),
  a number as the float it always was; any other word is the schema's to refuse (tests/test_schema.py)."""
  import sys
  from absl import flags
  from ml_collections import config_flags
  argv = ["nerfpod", f"--config={REPO / 'configs' / 'street.py'}:regions=4"]
  argv += [f"--config.model.region_capacity={given}"] if given is not None else []
  monkeypatch.setattr(sys, "argv", argv)  # (config_flags reads the overrides from sys.argv)
  flag_values = flags.FlagValues()
  config_flags.DEFINE_config_file("config", None, "", flag_values=flag_values, lock_config=True)
  flag_values(argv)
  got = flag_values.config.model.region_capacity
  assert got == value and type(got) is type(value)
  assert json.loads(flag_values.config.to_json_best_effort())["model"]["region_capacity"] == value


def test_tiny_config_is_the_tutorials_model_and_blender_the_papers():
  tiny = load_config("tiny")
  assert (tiny.model.field, tiny.model.use_viewdirs) == ("mlp", False)
  assert (tiny.model.mlp.num_frequencies, tiny.model.mlp.depth, tiny.model.mlp.width,
          tuple(tiny.model.mlp.skips)) == (6, 8, 256, (4,))
  assert (tiny.render.num_samples, tiny.render.num_importance, tiny.train.lr_init) == (256, 0, 5e-4)
  blender = load_config("blender")
  assert (blender.model.mlp.num_frequencies, blender.model.mlp.viewdir_frequencies, blender.model.mlp.depth,
          blender.model.mlp.width, blender.model.use_viewdirs) == (10, 4, 8, 256, True)
  assert (blender.render.num_samples, blender.render.num_importance) == (64, 128)


def test_real_capture_configs_pick_their_space_sampling_and_path():
  llff = load_config("llff", "scene=horns")
  assert llff.data.path.endswith("horns") and (llff.data.kind, llff.data.downscale) == ("llff", 8)
  assert (llff.render.space, llff.render.spacing, llff.orbit.path) == ("ndc", "linear", "spiral")
  capture = load_config("capture", "path=/x/cup,downscale=2")
  assert (capture.data.path, capture.data.kind, capture.data.downscale) == ("/x/cup", "auto", 2)
  assert (capture.render.space, capture.render.spacing, capture.orbit.path) == ("contract", "inverse", "ellipse")
  assert capture.model.hashgrid.bound == 2.0
  # The CPU-sized configs render in calls of 1,024 rays, as blender_fast.py:cpu (not the schema's 4,096,
  # which renders the horns' spiral about 1.6 times slower on a CPU: docs/results.md).
  cpu_sized = (llff, capture, load_config("blender_fast", "scene=lego,cpu"))
  assert {(c.eval.chunk, c.orbit.chunk) for c in cpu_sized} == {(1024, 1024)}
  for smoke in (load_config(name, "smoke") for name in ("llff", "capture")):
    assert smoke.render.space in ("ndc", "contract") and smoke.train.num_steps <= 20


@pytest.mark.parametrize("name,arg", [("capture", "path=/x/cup,big"), ("llff", "scene=horns,big")])
def test_the_big_variants_are_accelerator_sized_and_keep_their_kind(name, arg):
  from nerfpod import schema
  small, big = load_config(name, arg.removesuffix(",big")), load_config(name, arg)
  g = big.model.hashgrid
  assert (g.num_levels, g.log2_table_size, g.max_resolution, g.hidden_width) == (16, 19, 2048, 64)
  assert tuple(big.render.proposal_samples) == (256, 96) and big.render.num_samples == 48
  assert (big.train.batch_size, big.train.num_steps, big.eval.chunk) == (4096, 30_000, 32768)
  for dotted in ("data.kind", "data.space", "render.space", "render.spacing", "orbit.path", "data.path"):
    assert _get(big, dotted) == _get(small, dotted), dotted  # the same kind of scene, only bigger
  assert schema.problems(big) == []
  assert load_config(name, arg + ",smoke").train.num_steps <= 20  # big and smoke together shrink


# Every config file with the arguments the docs and tests call it with: the snapshot below pins what each
# resolves to (tests/data/README.md says how it was made).
SNAPSHOT = REPO / "tests" / "data" / "configs_snapshot.json"
SNAPSHOT_CASES = [
    ("default", None), ("default", "smoke"), ("tiny", None), ("tiny", "smoke"),
    ("tiny_fast", None), ("tiny_fast", "smoke"), ("tiny_fast", "path=/x/tiny.npz"),
    ("blender", None), ("blender", "smoke"), ("blender", "scene=chair"), ("blender", "scene=lego,smoke"),
    ("blender_fast", None), ("blender_fast", "smoke"), ("blender_fast", "scene=lego,cpu"),
    ("blender_fast", "scene=lego,cpu,smoke"),
    ("llff", None), ("llff", "smoke"), ("llff", "scene=horns"), ("llff", "scene=horns,big"),
    ("llff", "scene=horns,big,smoke"),
    ("capture", None), ("capture", "smoke"), ("capture", "path=/x/cup,downscale=2"), ("capture", "path=/x/cup,big"),
    ("capture", "path=/x/cup,downscale=1,big"), ("capture", "path=/x/cup,big,smoke"),
    ("street", None), ("street", "regions=4"), ("street", "smoke,regions=4"),
]


def _ordered_fields(config) -> list[tuple[str, str]]:
  """(dotted name, repr of the value) of every field, in the config's own order (as to_json_best_effort
  writes it): the repr tells an int from a float and a tuple from a list."""
  def walk(node, prefix):
    for key in json.loads(node.to_json_best_effort()):  # the insertion order (ConfigDict.keys() sorts)
      value = node[key]
      if isinstance(value, ml_collections.ConfigDict):
        yield from walk(value, f"{prefix}{key}.")
      else:
        yield f"{prefix}{key}", repr(value)
  return list(walk(config, ""))


def resolved_configs() -> dict:
  """{"fields": the default config's [name, repr] in order, "configs": {"name:arg": {name: repr} where it
  differs from the default}} of every case of SNAPSHOT_CASES."""
  default = _ordered_fields(load_config("default"))
  out = {"fields": [list(f) for f in default], "configs": {}}
  for name, arg in SNAPSHOT_CASES:
    fields = _ordered_fields(load_config(name, arg))
    assert [n for n, _ in fields] == [n for n, _ in default], (name, arg)
    out["configs"][f"{name}:{arg or ''}"] = {n: v for (n, v), (_, d) in zip(fields, default) if v != d}
  return out


@pytest.mark.parametrize("name,arg", SNAPSHOT_CASES)
def test_every_config_resolves_as_the_snapshot_pins(name, arg):
  """The same field names in the same order, the same values of the same types, and the same JSON."""
  snapshot = json.loads(SNAPSHOT.read_text())
  expected = dict(snapshot["fields"]) | snapshot["configs"][f"{name}:{arg or ''}"]
  config = load_config(name, arg)
  assert _ordered_fields(config) == list(expected.items())
  tree = {}
  for dotted, shown in expected.items():
    *parents, leaf = dotted.split(".")
    node = tree
    for part in parents:
      node = node.setdefault(part, {})
    node[leaf] = ast.literal_eval(shown)
  assert config.to_json_best_effort() == json.dumps(tree)
  assert config.to_json_best_effort(sort_keys=True) == json.dumps(tree, sort_keys=True)


@pytest.mark.parametrize("name,arg", [("default", "smoke"), ("llff", "scene=horns,big"), ("capture", None)])
def test_a_runs_config_json_reads_back_as_the_config(tmp_path, name, arg):
  """workdir.files.read_config (the viewer, exports) takes the config.json a run wrote, checked by the schema."""
  from nerfpod.workdir import files
  config = load_config(name, arg)
  files.write_config(str(tmp_path), json.loads(config.to_json_best_effort()))
  read = files.read_config(str(tmp_path))
  assert read.to_json_best_effort(sort_keys=True) == config.to_json_best_effort(sort_keys=True)
