"""The `nerfpod` command: its subcommands, their help, one sentence for a mistake; and the wheel, whose only
top-level package is nerfpod."""
import os
import subprocess
import sys
import zipfile

import pytest

from conftest import REPO
from nerfpod import cli


def _nerfpod(*args, timeout=120):
  """`nerfpod ARGS` as the console script runs it (nerfpod.cli.run), in a process of its own."""
  env = dict(os.environ, JAX_PLATFORMS="cpu")
  return subprocess.run([sys.executable, "-c", "from nerfpod import cli; cli.run()", *args], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=timeout)


def test_help_lists_every_subcommand_with_one_line_each():
  done = _nerfpod("--help")
  assert done.returncode == 0, done.stderr
  listed = [line.split()[0] for line in done.stdout.splitlines() if line.startswith("  ")]
  assert listed == ["train", "eval", "render", "view", "prepare", "export", "aot", "bench"]
  assert list(cli.SUBCOMMANDS) == listed


def test_no_subcommand_prints_the_usage_and_exits_2():
  done = _nerfpod()
  assert done.returncode == 2 and "subcommands:" in done.stderr and done.stdout == ""


def test_an_unknown_subcommand_is_one_sentence_naming_the_known_ones():
  done = _nerfpod("trian")
  assert done.returncode == 2
  assert done.stderr.count("\n") == 1 and "unknown subcommand 'trian'" in done.stderr
  assert "train, eval, render, view, prepare, export, aot, bench" in done.stderr


@pytest.mark.parametrize("name,flag", [("train", "--workdir"), ("eval", "--config"), ("bench", "quality"),
                                       ("view", "--workdir"), ("export", "video")])
def test_each_subcommand_has_its_own_help(name, flag):
  done = _nerfpod(name, "--help")
  assert done.returncode == 0, done.stderr
  assert flag in done.stdout and "Traceback" not in done.stderr


def test_train_eval_render_set_the_mode_and_refuse_another():
  done = _nerfpod("eval", "--mode=train", "--config=configs/default.py", "--workdir=/nonexistent")
  assert done.returncode == 2 and "sets the mode itself" in done.stderr and done.stderr.count("\n") == 1


def test_train_checks_the_config_before_anything_runs(tmp_path):
  """`nerfpod train` is nerfpod.main: a config mistake is its one sentence and exit 2, nothing written."""
  done = _nerfpod("train", "--config=configs/default.py:smoke", "--config.train.log_every=0",
                  f"--workdir={tmp_path / 'run'}")
  assert done.returncode == 2, done.stderr
  assert done.stderr.startswith("nerfpod: error: train.log_every=0 is not valid") and "Traceback" not in done.stderr
  assert not (tmp_path / "run").exists()


def test_eval_of_a_workdir_without_a_checkpoint_is_refused(tmp_path):
  done = _nerfpod("eval", "--config=configs/default.py:smoke", f"--workdir={tmp_path}")
  assert done.returncode == 2 and "holds no checkpoint yet; train first" in done.stderr


@pytest.mark.slow
def test_the_wheel_installs_one_top_level_package_and_declares_what_it_imports(tmp_path):
  done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                         "-w", str(tmp_path), str(REPO)], capture_output=True, text=True, timeout=600)
  assert done.returncode == 0, done.stderr[-2000:]
  (wheel,) = tmp_path.glob("nerfpod-*.whl")
  with zipfile.ZipFile(wheel) as archive:
    names = archive.namelist()
    metadata = archive.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    entry_points = archive.read(next(n for n in names if n.endswith(".dist-info/entry_points.txt"))).decode()
  top_level = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
  assert top_level == {"nerfpod"}
  assert "nerfpod = nerfpod.cli:run" in entry_points
  assert "nerfpod/pod/aot.py" in names and "nerfpod/bench.py" in names and "nerfpod/export/__init__.py" in names
  # Every third-party package the package imports is a declared dependency (or an extra, for optional ones).
  required = {line.split(":", 1)[1].split(";")[0].split("[")[0].split(">")[0].split("=")[0].strip().lower()
              for line in metadata.splitlines() if line.startswith("Requires-Dist:")}
  imported = {"jax": "jax", "flax": "flax", "optax": "optax", "numpy": "numpy", "orbax": "orbax-checkpoint",
              "grain": "grain", "tensorstore": "tensorstore", "ml_collections": "ml-collections",
              "absl": "absl-py", "tensorboardX": "tensorboardx", "PIL": "pillow", "imageio": "imageio",
              "etils": "etils", "viser": "viser", "pycolmap": "pycolmap",
              "imageio_ffmpeg": "imageio-ffmpeg", "wandb": "wandb", "skimage": "scikit-image", "fsspec": "fsspec",
              "jax_plugins": "jax"}  # (the namespace JAX finds its PJRT plugins in, e.g. a GPU's)
  import ast
  found = set()
  for path in (REPO / "nerfpod").rglob("*.py"):
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.Import):
        found |= {a.name.split(".")[0] for a in node.names}
      elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        found.add(node.module.split(".")[0])
  third_party = {name for name in found if name not in sys.stdlib_module_names and name != "nerfpod"}
  assert third_party <= set(imported), f"imported but not mapped to a distribution: {third_party - set(imported)}"
  assert {imported[name] for name in third_party} <= required, sorted({imported[n] for n in third_party} - required)
