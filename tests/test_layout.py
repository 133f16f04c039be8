"""The house: calls flow one way, downward through the layers the README's layout section shows, with no
import circle; every module imports on its own."""
import ast
import re
import subprocess
import sys

import pytest

from conftest import REPO

# The house by floors: each top-level module or package of nerfpod and its floor. A module may import only
# from lower floors, or from its own package (where the module graph has no circle either). Adding a module
# to a package takes no edit here; a new top-level module or package does (docs/architecture.md).
FLOORS = {
    "errors": 0, "text": 0,
    "nerf": 1, "storage": 1, "distributed": 1, "config_util": 1, "prepare": 1,
    "scenes": 2, "render": 2, "monitor": 2,
    "schema": 3, "data": 3,
    "workdir": 4,
    "run": 5,
    "pod": 6, "export": 6, "view": 6, "bench": 6,
    "main": 7,
    "cli": 8,
}
PACKAGES = ("nerf", "scenes", "prepare", "render", "monitor", "workdir", "run", "export", "pod")
MAX_TOP_LEVEL_MODULES = 12


def _modules() -> dict:
  package = REPO / "nerfpod"
  out = {}
  for path in sorted(package.rglob("*.py")):
    parts = path.relative_to(package).with_suffix("").parts
    name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
    out[name or "__init__"] = path
  out.pop("__init__")
  return out


def _unit(module: str) -> str:
  return module.split(".")[0]


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


def test_every_top_level_module_and_package_has_a_floor_and_the_top_level_stays_small():
  units = {_unit(name) for name in _modules()}
  assert units == set(FLOORS)
  top_level = sorted(p.stem for p in (REPO / "nerfpod").glob("*.py") if p.stem != "__init__")
  assert len(top_level) <= MAX_TOP_LEVEL_MODULES, top_level
  assert {p.name for p in (REPO / "nerfpod").iterdir() if (p / "__init__.py").exists()} == set(PACKAGES)


def test_calls_flow_downward_only_and_there_is_no_circle():
  modules = _modules()
  graph = {name: _imports(path) - {name} for name, path in modules.items()}
  upward = [f"{name} (floor {FLOORS[_unit(name)]}) imports {other} (floor {FLOORS[_unit(other)]})"
            for name, others in graph.items() for other in sorted(others)
            if _unit(other) != _unit(name) and FLOORS[_unit(other)] >= FLOORS[_unit(name)]]
  assert upward == []
  # Within a package the floors say nothing: no circle among all modules, packages' insides included.
  remaining = dict(graph)
  while remaining:
    leaves = [n for n, deps in remaining.items() if not (deps & set(remaining)) - {n}]
    assert leaves, f"import circle among {sorted(remaining)}"
    for n in leaves:
      del remaining[n]


@pytest.mark.parametrize("package", PACKAGES)
def test_each_package_says_what_lives_in_it(package):
  """Its __init__'s docstring names every module of the package: the door says what is behind it."""
  doc = ast.get_docstring(ast.parse((REPO / "nerfpod" / package / "__init__.py").read_text())) or ""
  modules = sorted(p.stem for p in (REPO / "nerfpod" / package).glob("*.py") if not p.stem.startswith("__"))
  unnamed = [m for m in modules if not re.search(rf"\b{m}\b", doc)]
  assert unnamed == [], f"nerfpod/{package}/__init__.py does not name {unnamed}"


def test_the_schema_imports_no_jax():
  """Checking a config must not start JAX (a mistake is refused before any process waits for a peer)."""
  code = "import sys; from nerfpod import schema; assert 'jax' not in sys.modules, sorted(sys.modules)"
  subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=60)


# Imports each module of the package in a child forked from a process that has loaded only third-party
# packages: no module of nerfpod is loaded before the one under test, so an import circle or a missing
# import between nerfpod's modules fails as in a fresh process, without paying each child's imports of JAX,
# Pallas' TPU module, grain and tensorstore (half of what a child took).
_IMPORT_ALONE = """
import importlib, os, sys, traceback
for heavy in ("numpy", "jax", "jax.numpy", "flax.linen", "optax", "orbax.checkpoint", "ml_collections",
              "absl.flags", "absl.app", "jax.experimental.pallas.tpu", "grain", "tensorstore", "PIL.Image",
              "imageio.v3", "tensorboardX"):
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


def _lines_matching(pattern: str, allowed: tuple[str, ...]) -> list[str]:
  """'path:line' of each line of nerfpod/ matching `pattern`, outside the files `allowed` (paths under nerfpod/)."""
  return [f"{path.relative_to(REPO)}:{n}" for path in sorted((REPO / "nerfpod").rglob("*.py"))
          if str(path.relative_to(REPO / "nerfpod")) not in allowed
          for n, line in enumerate(path.read_text().splitlines(), 1) if re.search(pattern, line)]


def test_one_storage_layer_makes_the_bucket_clients():
  """google-cloud-storage's clients and gcsfs's file systems are made in storage.py only, so that every bucket
  request has its endpoint (STORAGE_EMULATOR_HOST), its credentials' sentence and its bounds."""
  assert _lines_matching(r"\bClient\(|GCSFileSystem\(", ("storage.py",)) == []


def test_one_restore_door_reads_the_checkpoints_of_a_trained_workdir():
  """Evaluation, rendering, the viewer and the exports restore through run/trained.py, never checkpoints'
  read-only restore directly."""
  assert _lines_matching(r"restore_newest\(", ("workdir/checkpoints.py", "run/trained.py")) == []


def test_libraries_are_quieted_in_one_place_and_warnings_by_their_category():
  """Log filters and the unraisable hook are installed by workdir/quiet.py only (the texts it still matches
  live in workdir/library_texts.py, each pinned by tests/test_library_texts.py); a warning is filtered by its
  category and module, never by its text."""
  assert _lines_matching(r"addFilter\(|sys\.unraisablehook\s*=", ("workdir/quiet.py",)) == []
  assert _lines_matching(r"filterwarnings\([^)]*message=", ()) == []
