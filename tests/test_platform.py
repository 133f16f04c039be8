"""Which backend a run picks: the CPU where libtpu is installed without a TPU, and never the CPU where a GPU's
plugin is installed (a GPU machine once trained on its CPU because the plugin registers late)."""
import json
import os
import subprocess
import sys

from conftest import REPO

# In a fresh interpreter (the tests' own has picked the CPU already): what keep_off_absent_tpu decides with
# the plugins found, with no plugin, and with a (pretend) GPU plugin.
PROBE = r"""
import json, jax
from nerfpod import distributed
found = sorted(distributed.pjrt_plugins())
real = distributed.pjrt_plugins
distributed.pjrt_plugins = lambda: {"xla_cuda13"}
with_gpu = distributed.keep_off_absent_tpu()
platforms_with_gpu = jax.config.jax_platforms
distributed.pjrt_plugins = lambda: set()
without = distributed.keep_off_absent_tpu()
print(json.dumps({"found": found, "with_gpu": with_gpu, "platforms_with_gpu": platforms_with_gpu,
                  "without": without, "platforms": jax.config.jax_platforms}))
"""


def test_a_gpu_plugin_keeps_the_run_off_the_cpu_and_plugins_are_found_where_jax_looks(tmp_path):
  # A plugin in the jax_plugins namespace package, as jax-cuda13-plugin installs one (never loaded here).
  plugin = tmp_path / "jax_plugins" / "xla_pretend"
  plugin.mkdir(parents=True)
  (plugin / "__init__.py").write_text("")
  env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
  env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(REPO), env.get("PYTHONPATH", "")])
  done = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
  assert done.returncode == 0, done.stderr
  out = json.loads(done.stdout.strip().splitlines()[-1])
  assert "xla_pretend" in out["found"]
  assert out["with_gpu"] is False and not out["platforms_with_gpu"]  # JAX's own choice: the GPU
  # Without a plugin the choice stands as before: the CPU where the TPU runtime has no chip (the tests
  # install the `tpu` extra), else JAX's own choice.
  try:
    import libtpu  # noqa: F401
    assert out["without"] is True and out["platforms"] == "cpu"
  except ImportError:
    assert out["without"] is (out["platforms"] == "cpu")
