"""The `nerfpod` command: its subcommands, their help, one sentence for a mistake; and the wheel, whose only
top-level package is nerfpod."""
import os
import subprocess
import sys
import zipfile

import pytest

import procs
from conftest import REPO
from nerfpod import cli


@pytest.fixture
def nerfpod(capsys, monkeypatch):
  """`nerfpod ARGS` in this process (nerfpod.cli.run, as the console script calls it; procs.in_process)."""
  return procs.in_process(cli.run, "nerfpod", capsys, monkeypatch, REPO)


def test_help_lists_every_subcommand_with_one_line_each(nerfpod):
  done = nerfpod("--help")
  assert done.returncode == 0, done.stderr
  listed = [line.split()[0] for line in done.stdout.splitlines() if line.startswith("  ")]
  assert listed == ["train", "eval", "render", "view", "prepare", "export", "aot", "bench"]
  assert list(cli.SUBCOMMANDS) == listed


def test_no_subcommand_prints_the_usage_and_exits_2(nerfpod):
  done = nerfpod()
  assert done.returncode == 2 and "subcommands:" in done.stderr and done.stdout == ""


def test_an_unknown_subcommand_is_one_sentence_naming_the_known_ones(nerfpod):
  done = nerfpod("trian")
  assert done.returncode == 2
  assert done.stderr.count("\n") == 1 and "unknown subcommand 'trian'" in done.stderr
  assert "train, eval, render, view, prepare, export, aot, bench" in done.stderr


@pytest.mark.parametrize("name,flag", [("train", "--workdir"), ("eval", "--config"), ("bench", "quality"),
                                       ("view", "--workdir"), ("export", "video")])
def test_each_subcommand_has_its_own_help(nerfpod, name, flag):
  done = nerfpod(name, "--help")
  assert done.returncode == 0, done.stderr
  assert flag in done.stdout and "Traceback" not in done.stderr


def test_train_eval_render_set_the_mode_and_refuse_another(nerfpod):
  done = nerfpod("eval", "--mode=train", "--config=configs/default.py", "--workdir=/nonexistent")
  assert done.returncode == 2 and "sets the mode itself" in done.stderr and done.stderr.count("\n") == 1


def test_train_checks_the_config_before_anything_runs(nerfpod, tmp_path):
  """`nerfpod train` is nerfpod.main: a config mistake is its one sentence and exit 2, nothing written."""
  done = nerfpod("train", "--config=configs/default.py:smoke", "--config.train.log_every=0",
                  f"--workdir={tmp_path / 'run'}")
  assert done.returncode == 2, done.stderr
  assert done.stderr.startswith("nerfpod: error: train.log_every=0 is not valid") and "Traceback" not in done.stderr
  assert not (tmp_path / "run").exists()


def test_eval_of_a_workdir_without_a_checkpoint_is_refused(nerfpod, run_start_held, tmp_path):
  """Refused by the run's start-up, after JAX has started (here, the test process's 8 CPU devices), before
  anything is restored or written."""
  done = nerfpod("eval", "--config=configs/default.py:smoke", f"--workdir={tmp_path}")
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
              "jax_plugins": "jax",  # (the namespace JAX finds its PJRT plugins in, e.g. a GPU's)
              "google": "google-cloud-storage"}  # (google.cloud.storage, and google.auth that it brings)
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


# Every subcommand (each kind of export too): the words that make its command line whole, flags of its own that
# its --help lists, flags of other subcommands that it must not list, and a flag given a value it refuses.
_CONFIG = "--config=configs/default.py:smoke"
_COMMANDS = {
    "train": (["train", _CONFIG, "--workdir=/nonexistent"], ["--workdir", "--mode", "--num_processes"],
              ["--topology", "--port", "--matching"], "--num_processes=two"),
    "eval": (["eval", _CONFIG, "--workdir=/nonexistent"], ["--config", "--process_id"], ["--quality", "--fps"],
             "--process_id=first"),
    "render": (["render", _CONFIG, "--workdir=/nonexistent"], ["--config", "--heartbeat_timeout_seconds"],
               ["--slices", "--num_points"], "--heartbeat_timeout_seconds=soon"),
    "view": (["view", "--workdir=/nonexistent"], ["--workdir", "--port", "--poll_seconds"],
             ["--config", "--topology", "--input"], "--port=70000"),
    "prepare": (["prepare", "--input=/nonexistent", "--out=/nonexistent/capture"], ["--input", "--matching",
                "--num_frames"], ["--workdir", "--config", "--port"], "--matching=best"),
    "export video": (["export", "video", "--workdir=/nonexistent"], ["--workdir", "--formats", "--fps"],
                     ["--num_points", "--normalized", "--config"], "--fps=fast"),
    "export pointcloud": (["export", "pointcloud", "--workdir=/nonexistent"], ["--num_points", "--normalized"],
                          ["--formats", "--resolution", "--port"], "--num_points=many"),
    "export mesh": (["export", "mesh", "--workdir=/nonexistent"], ["--resolution", "--level", "--normalized"],
                    ["--num_points", "--formats"], "--resolution=big"),
    "export cameras": (["export", "cameras", "--workdir=/nonexistent"], ["--workdir", "--out", "--normalized"],
                       ["--num_points", "--resolution", "--min_opacity"], "--normalized=maybe"),
    "export depth": (["export", "depth", "--workdir=/nonexistent"], ["--split", "--format", "--min_opacity"],
                     ["--num_points", "--resolution"], "--min_opacity=half"),
    "aot": (["aot", _CONFIG, "--topology=v5e-8"], ["--topology", "--slices", "--what"],
            ["--workdir", "--port", "--steps"], "--slices=two"),
    "bench": (["bench", _CONFIG], ["--quality", "--steps", "--targets"], ["--workdir", "--topology", "--slices"],
              "--steps=0"),
}


def _case_argv(name: str, case: str) -> list[str]:
  """The words after `nerfpod` of one case of a subcommand (_COMMANDS): --help, an unknown flag, a bad value, or
  the required flags left out."""
  argv, _, _, bad = _COMMANDS[name]
  words = argv[:len(name.split())]
  return {"help": [*words, "--help"], "unknown": [*argv, "--bogus=1"], "bad": [*argv, bad], "missing": words}[case]


_CASES = ("help", "unknown", "bad", "missing")


@pytest.fixture(scope="module")
def modes_command_lines():
  """{(mode, case): (exit code, stdout, stderr)} of each case of the modes (train, eval, render: nerfpod.main),
  each in a child forked from one interpreter that has imported nerfpod.cli and nerfpod.main only (no JAX),
  as the `nerfpod` command's process has: the modes' flags are absl's global FLAGS, whose --help and unknown-flag
  sentence list the flags of every module the process imported (procs.run_forked_each)."""
  from nerfpod.run import MODES
  cases = [(name, case) for name in _COMMANDS if name in MODES for case in _CASES]
  results = procs.run_forked_each("from nerfpod import cli, main", "cli.run(argv)",
                                  [_case_argv(*case) for case in cases], dict(os.environ, JAX_PLATFORMS="cpu"))
  return dict(zip(cases, results, strict=True))


@pytest.fixture
def command_lines(nerfpod, modes_command_lines):
  """The case's (exit code, stdout, stderr) through nerfpod.cli.run: the modes' from their forked children
  (modes_command_lines); the other subcommands', whose flags are their own (a FlagValues each), in this process."""
  def result(name: str, case: str) -> tuple[int, str, str]:
    if (name, case) in modes_command_lines:
      return modes_command_lines[name, case]
    done = nerfpod(*_case_argv(name, case))
    return done.returncode, done.stdout, done.stderr
  return result


def _the_one_error(result) -> str:
  """A mistake's result: exit code 2, nothing on stdout, one `nerfpod: error:` line on stderr and nothing else."""
  code, out, err = result
  assert code == 2 and out == "", result
  lines = err.splitlines()
  assert len(lines) == 1 and lines[0].startswith("nerfpod: error: ") and "Traceback" not in err, result
  return lines[0]


@pytest.mark.parametrize("name", _COMMANDS)
def test_every_subcommands_help_lists_its_own_flags_only(command_lines, name):
  _, own, others, _ = _COMMANDS[name]
  code, out, err = command_lines(name, "help")
  assert code == 0 and err == "", (code, err)
  assert out.startswith(f"usage: nerfpod {name} [flags]\n\n"), out
  about = out.split("\n")[2]
  assert about and about == (cli.SUBCOMMANDS.get(name, (None, about))[1]), about  # its one line
  listed = {line.split(":")[0].strip().replace("--[no]", "--") for line in out.splitlines()
            if line.startswith("  --")}
  assert set(own) <= listed, (own, listed)
  assert not set(others) & listed, (others, listed)


@pytest.mark.parametrize("name", _COMMANDS)
def test_every_subcommands_unknown_flag_is_one_sentence_and_exit_2(command_lines, name):
  line = _the_one_error(command_lines(name, "unknown"))
  assert line.startswith("nerfpod: error: unknown flag --bogus; ") and f"`nerfpod {name} --help`" in line, line
  for flag in _COMMANDS[name][1]:  # the flags it does take, named
    assert flag in line, line


@pytest.mark.parametrize("name", _COMMANDS)
def test_every_subcommands_bad_value_is_one_sentence_naming_the_flag_and_a_valid_value(command_lines, name):
  bad = _COMMANDS[name][3]
  line = _the_one_error(command_lines(name, "bad"))
  flag = bad.split("=")[0]
  assert line.startswith(f"nerfpod: error: {bad}") or line.startswith(f"nerfpod: error: {flag}="), line
  assert f"e.g. {flag}=" in line or f"a yes/no flag is given as {flag} or --no{flag[2:]}" in line, line


@pytest.mark.parametrize("name", _COMMANDS)
def test_every_subcommands_required_flags_are_named_with_an_example(command_lines, name):
  line = _the_one_error(command_lines(name, "missing"))
  assert " required, e.g. --" in line, line


def test_the_modes_are_the_subcommands_that_run_nerfpod_main(nerfpod):
  """One table of the modes (nerfpod.run.MODES): each is a subcommand with its line, a --mode value, and the
  function of run.modes that it runs."""
  from nerfpod import main
  from nerfpod.run import MODES, modes
  assert {mode: cli.SUBCOMMANDS[mode] for mode in MODES} == {m: ("nerfpod.main", v.about) for m, v in MODES.items()}
  assert main.flags.FLAGS["mode"].parser.enum_values == list(MODES)
  assert all(callable(getattr(modes, mode.function)) for mode in MODES.values())
  for name, mode in MODES.items():
    assert nerfpod(name, "--help").stdout.split("\n")[2] == mode.about


def test_export_without_a_kind_lists_the_kinds_or_asks_for_one(nerfpod):
  done = nerfpod("export", "--help")
  assert done.returncode == 0 and "kinds:" in done.stdout and "nerfpod export KIND --help" in done.stdout
  for words in (["export"], ["export", "--workdir=/nonexistent"]):
    done = nerfpod(*words)
    assert done.returncode == 2 and done.stdout == "", done
    assert done.stderr.startswith("nerfpod: error: name what to export first") and done.stderr.count("\n") == 1


def test_a_mistyped_nested_config_field_is_named_with_its_whole_path(nerfpod):
  done = nerfpod("train", "--config=configs/default.py:smoke", "--config.model.hashgrid.nmu_levels=4",
                  "--workdir=/nonexistent/never")
  assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
  assert done.stderr == ("nerfpod: error: --config.model.hashgrid.nmu_levels: config section model.hashgrid has no "
                         "field 'nmu_levels' (did you mean model.hashgrid.num_levels?); `python -m nerfpod.schema` "
                         "lists every field, its values and what it means.\n")
