"""Test set-up: 8 simulated CPU devices (before any JAX call), the shared real data, tiny configs."""
import os
import pathlib

import jax

jax.config.update("jax_num_cpu_devices", 8)
jax.config.update("jax_platforms", "cpu")  # CPU only, also where libtpu (the `tpu` extra) is installed

import pytest  # noqa: E402

REPO = pathlib.Path(__file__).resolve().parent.parent
DATA = pathlib.Path(os.environ.get("NERFPOD_TEST_DATA", REPO.parent / "shared" / "data"))
TINY_NPZ = DATA / "tiny_nerf_data.npz"
LEGO = DATA / "lego_400"


def require(path: pathlib.Path):
  """Skips the test, saying why, where the real data is absent (a user's clone has no ../shared)."""
  if not path.exists():
    pytest.skip(f"real data {path} is absent (set NERFPOD_TEST_DATA to a folder holding it)")
  return path


def smoke_config(**overrides):
  """configs/default.py:smoke with dotted overrides, e.g. smoke_config(**{"train.num_steps": 5})."""
  from nerfpod.config_util import override
  return override(load_config("default", "smoke"), **overrides)


def load_config(name: str, arg: str | None = None):
  """The config that --config=configs/<name>.py:<arg> gives, e.g. load_config("llff", "scene=horns")."""
  from nerfpod.config_util import sibling_module
  return sibling_module(str(REPO / "configs" / f"{name}.py"), name).get_config(arg)
