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


# Prints, after collection (the conftest's marks added), each test's id and its marks among slow and extended.
_REPORT_MARKS = """
import sys, pytest
class Marks:
  def pytest_collection_finish(self, session):
    for item in session.items:
      marks = [m for m in ("slow", "extended") if item.get_closest_marker(m)]
      print("MARKS", item.nodeid, *marks)
sys.exit(pytest.main(["-q", "--collect-only", "-p", "no:cacheprovider", "tests"], plugins=[Marks()]))
"""


# How many tests the extended set holds (tests that the gate leaves out), counted on 2026-12-06: 51 after the
# region step's gradient clip joined the gate, then the restore through a refusing bucket and pose refinement
# end to end (test_storage_away, test_per_frame) and prepare's same capture twice on the horns (test_prepare)
# joined the extended set; 55 with the split by weights' 2 x 4 step (test_region_split, 2026-12-07).
EXTENDED_SIZE = 55


def _marks(config) -> dict[str, set[str]]:
  """Every test of the suite (its id from tests/) and its marks among slow and extended: this session's
  collection where it collected every test file (conftest.COLLECTED: the gate, the quick loop), else one
  collection in a process of its own."""
  collected = config.stash.get(conftest.COLLECTED, None)
  files = {f"tests/{path.name}" for path in (REPO / "tests").glob("test_*.py")}
  if collected is not None and {nodeid.split("::")[0] for nodeid in collected} == files:
    return {nodeid.split("tests/", 1)[1]: set(marks) for nodeid, marks in collected.items()}
  done = subprocess.run([sys.executable, "-c", _REPORT_MARKS], cwd=REPO, capture_output=True, text=True, timeout=300)
  assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
  lines = [line.split()[1:] for line in done.stdout.splitlines() if line.startswith("MARKS ")]
  return {words[0].split("tests/", 1)[1]: set(words[1:]) for words in lines}


def test_the_extended_set_is_slow_tests_that_an_entry_names_and_the_gate_keeps_the_rest(pytestconfig):
  marks = _marks(pytestconfig)
  extended = {test for test, its in marks.items() if "extended" in its}
  assert len(marks) > 900 and "test_suite.py::test_ci_runs_exactly_the_readmes_test_command" in marks
  assert all("slow" in marks[test] for test in extended)  # so the quick loop lies inside the gate
  # Pinned: a slow test added to a file that EXTENDED names whole would leave the gate without a word. Where
  # that is meant, raise the count here (and say beside the entry what the gate checks instead).
  assert len(extended) == EXTENDED_SIZE, sorted(extended)
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
