"""The project's own files, packed for the workers: what `pip install -e` and `python -m nerfpod.main` need
there, and nothing of a user's (runs/ with checkpoints, data, virtual environments, caches).

The files are those of INCLUDE: in a git checkout, the ones git does not ignore there (tracked, or new and
not ignored: a config file a user has just written goes along); elsewhere (an unpacked source archive), every
file under them but caches. The run's --config file is added where it lies in the project outside INCLUDE.
Standard library only.
"""
import os
import subprocess

# What a worker needs: the package's metadata (pyproject.toml names README.md), the pinned versions, the
# package, the configs, and the launch scripts it runs (check_devices.py).
INCLUDE = ("pyproject.toml", "constraints.txt", "README.md", "nerfpod", "configs", "launch")
_SKIPPED_DIRS = {"__pycache__", ".git", ".pytest_cache"}
_SKIPPED_SUFFIXES = (".pyc", ".pyo")


def _is_git_checkout(repo: str) -> bool:
  try:
    top = subprocess.run(["git", "-C", repo, "rev-parse", "--show-toplevel"], capture_output=True, text=True,
                         timeout=30)
  except (OSError, subprocess.TimeoutExpired):
    return False
  return top.returncode == 0 and os.path.realpath(top.stdout.strip()) == os.path.realpath(repo)


def _git_files(repo: str) -> list[str]:
  out = subprocess.run(["git", "-C", repo, "ls-files", "-z", "--cached", "--others", "--exclude-standard", "--",
                        *INCLUDE], capture_output=True, check=True, timeout=60)
  return [f for f in out.stdout.decode().split("\0") if f]


def _walked_files(repo: str) -> list[str]:
  files = []
  for name in INCLUDE:
    path = os.path.join(repo, name)
    if os.path.isfile(path):
      files.append(name)
      continue
    for folder, dirs, names in os.walk(path):
      dirs[:] = sorted(d for d in dirs if d not in _SKIPPED_DIRS and not d.endswith(".egg-info"))
      files += [os.path.relpath(os.path.join(folder, n), repo) for n in sorted(names)
                if not n.endswith(_SKIPPED_SUFFIXES)]
  return files


def project_files(repo: str, extra: tuple[str, ...] = ()) -> list[str]:
  """The files to pack, relative to `repo`, sorted; `extra` (relative paths, e.g. the run's config file)
  added. Files git still lists but the checkout lacks (deleted, not yet committed) are left out."""
  files = _git_files(repo) if _is_git_checkout(repo) else _walked_files(repo)
  files = {f.replace(os.sep, "/") for f in files} | {e.replace(os.sep, "/") for e in extra}
  return sorted(f for f in files if os.path.isfile(os.path.join(repo, f)))


def tar_command(repo: str, tarball: str, list_path: str) -> list[str]:
  """The tar command packing the files listed (NUL-separated) in `list_path`, relative to `repo`."""
  return ["tar", "-czf", tarball, "-C", repo, "--null", f"--files-from={list_path}"]


def write_list(files: list[str], list_path: str) -> None:
  with open(list_path, "w") as f:
    f.write("\0".join(files) + "\0")
