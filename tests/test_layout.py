"""The house: calls flow one way, downward through the layers the README's layout section shows, with no
import circle; every module imports on its own."""
import ast
import subprocess
import sys

import pytest

from conftest import REPO

# Each module of the package and its floor: a module may import only modules on lower floors. (The
# README's layout section draws the same house.)
FLOORS = {
    "errors": 0,
    "nerf": 0, "nerf.cameras": 1, "nerf.sampling": 1, "nerf.stepfun": 1, "nerf.encodings": 1,
    "nerf.compositing": 1, "nerf.coord": 1, "nerf.paths": 2, "nerf.poses": 1, "nerf.pose_correction": 1,
    "nerf.keyframes": 2,
    "nerf.fields": 2, "nerf.model": 3,
    "pod": 0, "pod.chips": 1, "pod.hlo_cost": 2,
    "finite": 1, "metrics": 1, "compilation": 1, "config_util": 1, "preemption": 1,
    "scenes.base": 2, "scenes.procedural": 3, "scenes.tiny": 3, "scenes.blender": 3, "scenes": 4,
    "scenes.capture": 2, "scenes.llff": 3, "scenes.colmap": 3, "scenes.nerfstudio": 3,
    "schema": 5, "video": 2, "monitor": 1,
    "distributed": 2, "camera_path": 2, "data": 5, "archive": 3, "render": 3,
    "workdir_files": 6, "checkpoints": 6, "workdir_lock": 1, "profiling": 1, "storage": 1,
    "components": 7,
    "step": 8,
    "train": 9, "evaluate": 9, "orbit": 9, "view": 9, "export.video": 9,
    "export.ply": 1, "lpips": 3, "export.trained": 8,
    "export.pointcloud": 9, "export.mesh": 9, "export.cameras": 9, "export.depth": 9, "export": 10,
    "export.__main__": 11,
    "modes": 10, "bench": 10, "pod.aot": 10,
    "prepare.progress": 1, "prepare.sfm": 2, "prepare.capture": 2, "prepare.frames": 3, "prepare": 10,
    "prepare.__main__": 11,
    "main": 11,
    "cli": 12,
}


def _modules() -> dict:
  package = REPO / "nerfpod"
  out = {}
  for path in sorted(package.rglob("*.py")):
    parts = path.relative_to(package).with_suffix("").parts
    name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
    out[name or "__init__"] = path
  out.pop("__init__")
  return out


def _is_module(dotted: str) -> bool:
  path = REPO / dotted.replace(".", "/")
  return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def _imports(path) -> set[str]:
  """nerfpod modules that the file imports anywhere (top level or inside functions), without 'nerfpod.'."""
  found = set()
  for node in ast.walk(ast.parse(path.read_text())):
    if isinstance(node, ast.Import):
      found |= {a.name for a in node.names if a.name.startswith("nerfpod.")}
    elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "nerfpod":
      # `from nerfpod.x import y` imports module x.y where y is a module, else module x.
      found |= {f"{node.module}.{a.name}" if _is_module(f"{node.module}.{a.name}") else node.module
                for a in node.names}
  return {name.removeprefix("nerfpod.") for name in found if name != "nerfpod"}


def test_every_module_has_a_floor():
  assert set(_modules()) == set(FLOORS)


def test_calls_flow_downward_only_and_there_is_no_circle():
  modules = _modules()
  graph = {name: _imports(path) - {name} for name, path in modules.items()}
  upward = [f"{name} (floor {FLOORS[name]}) imports {other} (floor {FLOORS[other]})"
            for name, others in graph.items() for other in sorted(others)
            if other in FLOORS and FLOORS[other] >= FLOORS[name] and not name.startswith(other + ".")]
  assert upward == []
  # Strictly decreasing floors along every import make a circle impossible; say so independently too.
  remaining = dict(graph)
  while remaining:
    leaves = [n for n, deps in remaining.items() if not (deps & set(remaining)) - {n}]
    assert leaves, f"import circle among {sorted(remaining)}"
    for n in leaves:
      del remaining[n]


def test_the_schema_imports_no_jax():
  """Checking a config must not start JAX (a mistake is refused before any process waits for a peer)."""
  code = "import sys; from nerfpod import schema; assert 'jax' not in sys.modules, sorted(sys.modules)"
  subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=60)


# Imports each module of the package in a child forked from a process that has loaded only third-party
# packages: no module of nerfpod is loaded before the one under test, so an import circle or a missing
# import between nerfpod's modules fails as in a fresh process, without paying each child's JAX import.
_IMPORT_ALONE = """
import importlib, os, sys, traceback
for heavy in ("numpy", "jax", "jax.numpy", "flax.linen", "optax", "orbax.checkpoint", "ml_collections",
              "absl.flags", "absl.app"):
  importlib.import_module(heavy)
assert not [m for m in sys.modules if m.split(".")[0] == "nerfpod"]
for name in sys.argv[1:]:
  read, write = os.pipe()
  pid = os.fork()
  if pid == 0:
    os.close(read)
    try:
      importlib.import_module("nerfpod." + name)
      os._exit(0)
    except BaseException:
      os.write(write, traceback.format_exc()[-1000:].encode())
      os._exit(1)
  os.close(write)
  with os.fdopen(read) as pipe:
    error = pipe.read()
  _, status = os.waitpid(pid, 0)
  if status != 0:
    print(f"nerfpod.{name}: {error or status}", flush=True)
"""


def test_every_module_imports_on_its_own():
  result = subprocess.run([sys.executable, "-c", _IMPORT_ALONE, *sorted(_modules())], cwd=REPO,
                          capture_output=True, text=True, timeout=600)
  assert result.returncode == 0 and result.stdout == "", (result.stdout, result.stderr[-3000:])
