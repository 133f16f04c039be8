"""Helpers for config files: derive from a sibling config file, parse `key=value,flag` arguments, set
fields by dotted name."""
import importlib.util
import os

from nerfpod.errors import UserError


def sibling_module(this_file: str, name: str):
  """The config module configs/<name>.py, found next to `this_file` (works wherever the repo is)."""
  path = os.path.join(os.path.dirname(os.path.abspath(this_file)), f"{name}.py")
  spec = importlib.util.spec_from_file_location(f"nerfpod_config_{name}", path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def parse_arg(arg: str | None, **defaults) -> dict:
  """'scene=lego,smoke' -> {'scene': 'lego', 'smoke': True} on top of defaults; unknown keys are refused
  with a UserError (not a ValueError, which ml_collections would wrap in a printed traceback)."""
  out = dict(defaults)
  for item in filter(None, (arg or "").split(",")):
    key, _, value = item.partition("=")
    if key not in defaults:
      known = ", ".join(f"{k}=..." if isinstance(v, str) else k for k, v in defaults.items())
      raise UserError(f"unknown config argument {key!r} after the config file's colon; it takes: {known} "
                      f"(e.g. --config=configs/blender.py:scene=lego,smoke).")
    out[key] = value if value else True
  return out


def override(config, **dotted):
  """Sets fields by dotted name, e.g. override(config, **{"train.num_steps": 5}); returns `config` (a
  ConfigDict, or a config's JSON as nested dicts)."""
  for name, value in dotted.items():
    node = config
    *parents, leaf = name.split(".")
    for p in parents:
      node = node[p]
    node[leaf] = value
  return config
