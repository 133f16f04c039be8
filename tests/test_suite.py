"""The suite's selections: the gate that CI runs is the README's test command, and the extended set that the
gate leaves out is made of slow tests only, each taken out by an entry of conftest.EXTENDED."""
import re
import subprocess
import sys

import conftest
from conftest import REPO


def _pytest_words(line: str) -> list[str]:
  """The words after `pytest` in a command line, its quotes removed."""
  words = re.findall(r'"[^"]*"|\S+', line.split("pytest", 1)[1])
  return [w.strip('"') for w in words]


def test_ci_runs_exactly_the_readmes_test_command():
  readme = (REPO / "README.md").read_text()
  start = readme.split("```bash", 1)[1].split("```", 1)[0]
  (readme_line,) = [line for line in start.splitlines() if "pytest" in line]
  (ci_line,) = [line for line in (REPO / ".ci" / "run").read_text().splitlines() if "pytest" in line]
  assert _pytest_words(ci_line) == _pytest_words(readme_line) == ["-q", "-n", "2", "-m", "not extended", "tests"]
  # The install before it, too (CI's quietly).
  install = [line.split("&&")[0].split("pip", 1)[1].split() for line in (readme_line, ci_line)]
  assert install[0] == [w for w in install[1] if w != "-q"]


def _collect(*args) -> set[str]:
  done = subprocess.run([sys.executable, "-m", "pytest", "-q", "--collect-only", "-p", "no:cacheprovider", *args,
                         "tests"], cwd=REPO, capture_output=True, text=True, timeout=300)
  assert done.returncode in (0, 5), done.stdout[-2000:] + done.stderr[-2000:]  # 5: none selected
  return {line.split("tests/", 1)[1] for line in done.stdout.splitlines() if "::" in line}


def test_the_extended_set_is_slow_tests_that_an_entry_names_and_the_gate_keeps_the_rest():
  extended = _collect("-m", "extended")
  assert not _collect("-m", "extended and not slow")  # so the quick loop lies inside the gate
  for test in extended:
    file, name = test.split("::")
    assert ({file, f"{file}::{name}", f"{file}::{name.split('[')[0]}"} & set(conftest.EXTENDED)), test
  assert "test_golden.py::test_the_default_job_gives_the_readmes_headline_metrics" in extended
  assert "test_chaos.py::test_sigkill_at_random_moments_and_a_sigterm_lose_nothing" in extended
  # The gate's own slow checks, and quick tests of files that EXTENDED names whole.
  for kept in ("test_multiprocess.py::test_two_processes_as_two_slices_and_one_device_follow_the_same_trajectory",
               "test_golden.py::test_under_users_own_compiler_flags_the_smoke_job_gives_the_same_recorded_values",
               "test_step.py::test_microbatches_accumulate_to_the_same_step",
               "test_view.py::test_the_viewer_builds_every_scene_kind_from_config_json_alone[procedural]"):
    assert kept not in extended
