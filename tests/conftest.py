"""Test set-up: 8 simulated CPU devices (before any JAX call), a compilation cache for the session, the shared
real data, tiny configs."""
import gc
import os
import pathlib
import sys
import tempfile

import jax

import gcs  # (imports no JAX; sets gcsfs's settings before any test imports it)
import procs  # (imports no JAX)

# The test processes' XLA flags (procs.TEST_XLA_FLAGS: the same bits, compiled in less time), set before JAX
# starts its backend, which reads them; XLA_FLAGS of the caller's own are replaced, as in every test process.
os.environ["XLA_FLAGS"] = procs.TEST_XLA_FLAGS
jax.config.update("jax_num_cpu_devices", 8)
jax.config.update("jax_platforms", "cpu")  # CPU only, also where libtpu (the `tpu` extra) is installed
# The training loop's host <-> device transfers must all be explicit (jax.device_get / device_put): an implicit
# one fails the test (nerfpod.run.train.TRANSFER_GUARD), here and in the processes the tests start.
os.environ["NERFPOD_LOOP_TRANSFER_GUARD"] = "disallow"

# JAX's persistent compilation cache in a folder of this session (removed at its end): a program that an
# earlier test compiled, here or in a process a test started (procs.environment passes the folder on), is
# read back instead of compiled again (seconds each on a small CPU); the same executable, so the same
# results. JAX_COMPILATION_CACHE_DIR set by whoever runs the tests (e.g. a cache kept between runs) wins.
if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
  _CACHE = tempfile.TemporaryDirectory(prefix="nerfpod-test-jax-cache-")
  os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE.name
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # every program (most take < 1 s)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
# No source locations in the programs the tests lower (JAX 0.10 keeps up to 100 frames of each operation's
# traceback): they are what XLA's error messages and profiles point at, which no test reads; building them was
# about 3% of the tracing, lowering and compiling of the region and model tests. Here and, through the
# environment, in every process a test starts; users' runs keep JAX's default.
os.environ["JAX_TRACEBACK_IN_LOCATIONS_LIMIT"] = "0"
jax.config.update("jax_traceback_in_locations_limit", 0)

import pytest  # noqa: E402

# Python's cycle collector at a 50,000-allocation pace instead of 700: a test session keeps hundreds of
# thousands of objects alive (JAX's traces and caches, every module imported), which each full collection
# walks; at the default pace the collector took 6% of a worker's time (3.9 s of 65 in the step's tests),
# at this one 2.7% (1.75 s). Objects are freed by their counts as before; only cycles wait longer.
gc.set_threshold(50_000, 20, 100)


def pytest_configure(config):
  """NERFPOD_TEST_TIMINGS=PREFIX: each test's seconds in tracing, lowering, compiling and the rest, and the
  compilation cache's hits, written to PREFIX.<worker>.jsonl (tests/timings.py, which also prints the table)."""
  if os.environ.get("NERFPOD_TEST_TIMINGS"):
    import timings
    config.pluginmanager.register(timings.Recorder(os.environ["NERFPOD_TEST_TIMINGS"]), "nerfpod-timings")

REPO = pathlib.Path(__file__).resolve().parent.parent
DATA = pathlib.Path(os.environ.get("NERFPOD_TEST_DATA", REPO.parent / "shared" / "data"))
TINY_NPZ = DATA / "tiny_nerf_data.npz"
LEGO = DATA / "lego_400"


def require(path: pathlib.Path):
  """Skips the test, saying why, where the real data is absent (a user's clone has no ../shared)."""
  if not path.exists():
    pytest.skip(f"real data {path} is absent (set NERFPOD_TEST_DATA to a folder holding it)")
  return path


def damage_checkpoint(step_dir: pathlib.Path):
  """Truncates the largest file of a checkpoint step's train state to half its size (a disk or a copy cut
  off): the step no longer reads back whole."""
  largest = max((p for p in (step_dir / "state").rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
  with open(largest, "r+b") as f:
    f.truncate(largest.stat().st_size // 2)


# What orbax's reads, abandoned by a failed restore, would print after a command's one sentence (a report per
# array) where nerfpod did not quiet them (workdir.quiet.quiet_abandoned_reads).
ABANDONED_READ_REPORTS = ("Traceback", "Event loop is closed", "Exception ignored", "never retrieved",
                          "Task was destroyed")


def smoke_config(**overrides):
  """configs/default.py:smoke with dotted overrides, e.g. smoke_config(**{"train.num_steps": 5})."""
  from nerfpod.config_util import override
  return override(load_config("default", "smoke"), **overrides)


_SHARED_MODELS: dict = {}


def shared_model(config, num_frames: int = 0):
  """components.make_model(config, num_frames=num_frames), one object per config in a test process:
  train_state.initial_state traces and compiles its init once per (model, optimiser) pair, so the tests that
  start from the same config (and the same optimiser object) share that program rather than tracing it again.
  Models are immutable: the object may be shared."""
  from nerfpod.run import components
  key = (config.to_json(), num_frames)
  if key not in _SHARED_MODELS:
    _SHARED_MODELS[key] = components.make_model(config, num_frames=num_frames)
  return _SHARED_MODELS[key]


def load_config(name: str, arg: str | None = None):
  """The config that --config=configs/<name>.py:<arg> gives, e.g. load_config("llff", "scene=horns")."""
  from nerfpod.config_util import sibling_module
  return sibling_module(str(REPO / "configs" / f"{name}.py"), name).get_config(arg)


# The smoke job's settings for the shared run below: logging every step, no preview images and no orbit
# change nothing that training or evaluation compute, only what is written and shown.
SMOKE_RUN_OVERRIDES = {"train.log_every": 1, "train.image_every": 0, "orbit.render_after_training": False}
# The shared run also measures LPIPS (the smoke config leaves it out), so that evaluation's LPIPS is tested
# on a real run's checkpoint (tests/test_evaluate.py).
SMOKE_RUN_EVAL = {"eval.lpips_net": "alex"}


@pytest.fixture
def run_start_held(monkeypatch):
  """For a test that runs a run's start-up (nerfpod.main.main) in this process, to a refusal: what the start-up
  sets for its whole process goes back after the test (absl's verbosity; the filters of the loggers and
  sys.unraisablehook: quiet.quiet_library_reports; tensorstore's variables: storage.bound_clients, whose other
  settings are those every run in this process sets), and glibc's malloc is left as it is (compilation.tune_host
  not applied: tests/test_host_memory.py checks it in processes of their own)."""
  import logging as python_logging

  from absl import logging
  from nerfpod.run import compilation
  verbosity = logging.get_verbosity()
  monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)
  for name in ("absl", "asyncio", "gcsfs", "fsspec"):
    logger = python_logging.getLogger(name)
    monkeypatch.setattr(logger, "filters", list(logger.filters))
  for name in ("TENSORSTORE_CURL_LOW_SPEED_TIME_SECONDS", "TENSORSTORE_CURL_LOW_SPEED_LIMIT_BYTES"):
    was = os.environ.get(name)
    monkeypatch.setenv(name, was or "")  # restored after the test: to `was`, or to no variable at all
    if was is None:
      monkeypatch.delenv(name)
  monkeypatch.setattr(compilation, "tune_host", lambda config: None)
  yield
  logging.set_verbosity(verbosity)


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory):
  """The smoke job (configs/default.py:smoke: 20 steps on the 8 devices) trained and evaluated once per
  session through nerfpod.run.modes.train_and_evaluate with SMOKE_RUN_OVERRIDES: a namespace of `workdir` (its
  checkpoints, config.json, scene.json, eval/metrics.json, events), `losses` ({step: training loss} of
  every step) and `metrics` (what eval/metrics.json holds). Tests that write into the workdir copy it first."""
  import types

  from nerfpod import monitor
  from nerfpod.run import modes
  losses = {}

  class Recording(monitor.Monitor):
    def scalars(self, step, metrics, lr):
      losses[step] = float(metrics["loss"])
      super().scalars(step, metrics, lr)

  workdir = tmp_path_factory.mktemp("smoke_run")
  with pytest.MonkeyPatch.context() as patch:
    patch.setattr(monitor, "Monitor", Recording)
    metrics = modes.train_and_evaluate(smoke_config(**SMOKE_RUN_OVERRIDES, **SMOKE_RUN_EVAL), str(workdir))
  return types.SimpleNamespace(workdir=workdir, losses=losses, metrics=metrics)


@pytest.fixture(scope="session")
def default_run(tmp_path_factory):
  """The main job as the README's first command runs it (`configs/default.py`, one CPU device, XLA's default
  flags: no XLA_FLAGS), without its orbit (which computes nothing that training or evaluation do), trained
  once per session in a process of its own: a namespace of `workdir` and `result` (the CompletedProcess).
  Its readers (the README's headline metrics, the exports' surfaces) check result.returncode themselves."""
  import types

  import procs
  workdir = tmp_path_factory.mktemp("default_run") / "run"
  result = procs.run_main("--config=configs/default.py", f"--workdir={workdir}",
                          "--config.orbit.render_after_training=False", devices_per_process=1,
                          env={"XLA_FLAGS": ""}, timeout=900)
  return types.SimpleNamespace(workdir=workdir, result=result)


@pytest.fixture(scope="module")
def emulator(tmp_path_factory):
  """tests/gcs.py's Cloud Storage emulator (skips, saying why, where the test extra lacks it), with this
  process's environment pointing every storage client at it."""
  with gcs.Emulator(tmp_path_factory.mktemp("emulator") / "emulator.log") as server:
    with pytest.MonkeyPatch.context() as patch:
      for name, value in server.env.items():
        patch.setenv(name, value)
      import gcsfs
      gcsfs.GCSFileSystem.clear_instance_cache()  # one made for another emulator keeps its address
      yield server
      gcsfs.GCSFileSystem.clear_instance_cache()


# The longest test files, with their seconds in a whole run on the 2-core machine (2026-11-25, commit 8c2adbc,
# `--durations=0` summed per file, less the tests removed since; docs/results.md): run first, so that with
# `-n 2` (pytest-xdist: whole files per worker in this order, pytest_xdist_make_scheduler below,
# --no-loadscope-reorder) the two workers end together instead of one finishing a long file alone. The order
# of tests does not change what they check.
LONGEST_FILES = {"test_multiprocess": 265, "test_step": 105, "test_export": 75, "test_aot": 124, "test_chaos": 85,
                 "test_view": 84, "test_benchmark": 84, "test_per_frame": 83, "test_wandb": 70, "test_pod_sweep": 59,
                 "test_resilience": 56, "test_prepare": 55, "test_shards": 49, "test_model": 44,
                 "test_multislice": 41, "test_real_configs": 36, "test_workdir_lock": 34, "test_bucket": 34,
                 "test_whole_slice": 33,
                 "test_device_check": 50,  # (added 2026-11-27: about 80 s on that day's slower EPYC)
                 # (added 2026-11-27 on the EPYC, shared: the whole default job, 225 s, and the smoke job under
                 # XLA's defaults; test_multiprocess's 265 is 195 and its runs under XLA's defaults, 70 s)
                 "test_golden": 250,
                 "test_storage_away": 130,  # (added 2026-11-27: the file alone, -n 0, on the shared 2 cores)
                 # (added 2026-11-27 on the shared 2-core machine: model.regions' 4 whole runs, and its steps)
                 "test_region_multiprocess": 270, "test_region_step": 140,
                 # (added 2026-12-07: the quick loop's seconds of files it ran last, in alphabetical order, so that
                 # one worker still ran test_region_capacity while the other had finished; their slow tests
                 # make the gate's figures larger, so in the gate these still sort no later than before)
                 "test_region_capacity": 40, "test_region_export": 16, "test_components": 14,
                 "test_workdir_lock_gcs": 13, "test_hashgrid_layout": 10, "test_layout": 10,
                 "test_region_split": 19}  # (added 2026-12-07: its worker-seconds in the quick loop)


# The files that read the session's smoke run (smoke_run above) or its default job (default_run: test_golden,
# test_export, test_eval_protocols) go to one worker, which trains each once.
SMOKE_RUN_FILES = ("test_evaluate", "test_export", "test_golden", "test_view", "test_eval_protocols")


# The gate and the extended set. The README's test command, which CI runs (.ci/run), is the gate,
# `-m "not extended"`: every quick test and the slow ones that no entry below names (7 to 8 minutes on the
# 2-core Xeon and the EPYC; docs/results.md). The slow tests of each entry (a file, or one test function with
# all its cases; the entry's quick tests stay in the gate) are marked `extended`: checks of whole programs whose
# claim the gate checks more cheaply elsewhere (said beside each) or that guard one feature's long path.
# `-m extended` runs them; no -m runs everything (21 to 32 minutes there). Run them before landing a change to
# what they guard: the run loop, checkpoints, storage, the pod tool, the regions, prepare or the viewer. An
# entry that names no slow test fails the collection (a renamed test would otherwise drop back into the gate).
EXTENDED = (
    # The whole default job (1,500 steps) and the two tests that read its model. The gate checks the smoke
    # job's recorded losses and metrics to a relative 1e-5 (test_golden.RTOL: 40 times what summation order
    # changes, 10 times under a 1% learning-rate change), in-process and under users' own XLA flags.
    "test_golden.py::test_the_default_job_gives_the_readmes_headline_metrics",
    "test_export.py",  # its surfaces (the exports' quick tests stay)
    "test_eval_protocols.py",  # the pose fit on its model (the protocols' quick tests stay)
    # Exactness across topologies and kills: the gate keeps 2 x 4 (as two slices) = 1 x 8 with multi-host
    # evaluation, one SIGKILL and restart, and the preemptions (test_multiprocess); these repeat them under
    # XLA's default flags, at random moments, on another topology, or for one host's death.
    "test_multiprocess.py::test_under_xlas_default_flags_two_hosts_and_a_killed_then_resumed_run_end_at_one_"
    "processs_bits",
    "test_multiprocess.py::test_sigterm_to_one_host_saves_an_agreed_step_then_resumes_on_another_topology",
    "test_multiprocess.py::test_a_dead_process_stops_the_others_within_the_heartbeat_timeout",
    "test_chaos.py",
    "test_orbit_multiprocess.py",  # (test_whole_slice renders an orbit over 2 processes in the gate)
    "test_shards.py",  # image shards over 2 processes
    "test_wandb.py::test_a_killed_and_resumed_run_continues_one_wandb_run_and_its_steps_never_go_back",
    "test_wandb.py::test_a_two_process_run_writes_one_wandb_run_from_process_0",  # (the offline run stays)
    # Faults beyond a kill, each with quick tests of its path in the gate: a second writer at random moments,
    # a full RAM disk, the smoke job killed and resumed in the emulator's bucket, a bucket that goes silent.
    "test_workdir_lock.py",
    "test_resilience.py::test_a_full_disk_is_one_sentence_naming_the_safe_checkpoint_and_a_rerun_with_space_"
    "resumes",
    "test_bucket.py",
    "test_storage_away.py::test_a_bucket_that_stops_answering_stops_the_run_in_one_sentence_and_the_rerun_"
    "resumes_exactly",
    "test_storage_away.py::test_a_sigterm_while_the_bucket_does_not_answer_ends_the_run_within_the_bound",
    "test_storage_away.py::test_a_bucket_that_refuses_connections_while_a_run_restores_is_the_same_sentence",
    # Whole TPU compiles: 7 pods, 512 chips, the launcher's preflight, libtpu beside a CPU run, the region
    # step (the gate compiles v4-8's evaluation and two v5e-4 slices' step, and the sweep's refusals).
    "test_pod_sweep.py::test_every_program_compiles_for_a_pod_of_every_generation_and_host_class",
    "test_aot.py::test_two_slices_of_v5e_256_compile_every_program_of_the_default_config",
    "test_aot.py::test_a_cpu_run_with_libtpu_installed_behaves_as_without_it",
    "test_aot.py::test_the_launchers_preflight_refuses_a_job_too_large_for_the_chips_with_the_figures",
    "test_aot_regions.py",
    # The region model's 2-process runs and other layouts (the gate keeps its (2, 4) step and two composites).
    "test_region_multiprocess.py", "test_regions.py",
    "test_region_step.py::test_each_device_share_of_the_regions_composites_to_the_whole_model",
    "test_region_step.py::test_sharded_regions_step_matches_the_whole_model_on_one_device",  # (its 2 x 4 is quick)
    # (test_region_step's gradient clip over every region's gradients stays in the gate, 12 s.)
    # The split by weights on 2 x 4 (the gate keeps its rendering against dense models and the length split's step).
    "test_region_split.py::test_the_weighted_split_step_on_a_region_mesh_is_the_one_devices",
    # pycolmap on the cup's photos, the horns' photos twice and the horns' video (prepare's quick tests run it on
    # synthetic photos), the fox through the command line (test_real_configs trains the cup and the horns).
    "test_prepare.py",
    "test_captures.py::test_a_distorted_capture_trains_evaluates_and_renders_through_the_command_line",
    # The browser's other pages (the gate keeps the page's rendering and a drag, and the Ctrl-C exit).
    "test_view.py::test_camera_set_through_viser_gives_that_view_and_the_other_channels",
    "test_view.py::test_a_checkpoint_written_while_the_page_is_open_appears",
    "test_view.py::test_a_path_saved_from_the_page_holds_the_keyframes_path",
    "test_view.py::test_bad_workdirs_and_a_busy_port_are_one_sentence",
    "test_view.py::test_the_viewer_builds_every_scene_kind_from_config_json_alone[tiny]",
    "test_view.py::test_the_viewer_builds_every_scene_kind_from_config_json_alone[blender]",
    # Second layouts and variants of steps whose first the quick loop checks; VGG's LPIPS (AlexNet's stays);
    # the benchmark's modes (the device check in the gate runs `nerfpod bench`).
    "test_step.py", "test_per_frame.py", "test_lpips.py",
    "test_benchmark.py::test_throughput_report_and_flops_that_count_every_micro_batch",
    "test_benchmark.py::test_mixed_precision_is_also_measured_against_the_bfloat16_peak",
    "test_benchmark.py::test_quality_mode_reports_thresholds_and_the_samples_that_matter",
)


def _extended_entry(item) -> str | None:
  """The EXTENDED entry that takes this slow test out of the gate, if any."""
  if item.get_closest_marker("slow") is None:
    return None
  name = item.path.name
  for entry in (f"{name}::{item.name}", f"{name}::{item.originalname}", name):
    if entry in EXTENDED:
      return entry
  return None


@pytest.hookimpl(tryfirst=True)  # before pytest's own -m selection reads the marks
def pytest_collection_modifyitems(config, items):
  items.sort(key=lambda item: -LONGEST_FILES.get(item.path.stem, 0))  # stable: within a file, as written
  used = set()
  for item in items:
    entry = _extended_entry(item)
    if entry is not None:
      item.add_marker(pytest.mark.extended)
      used.add(entry)
  # Checked where the run collected whole folders (the gate, the whole suite), not a chosen file or test.
  whole = all(pathlib.Path(arg.split("::")[0]).is_dir() for arg in config.args)
  stale = [entry for entry in EXTENDED if entry not in used]
  if whole and stale:
    raise pytest.UsageError(f"tests/conftest.py EXTENDED names no slow test: {', '.join(stale)}")
  if whole:
    config.stash[COLLECTED] = {item.nodeid: {m for m in ("slow", "extended") if item.get_closest_marker(m)}
                               for item in items}


# Every test a session that collected whole folders found, with its marks among slow and extended (those above
# added), before -m, -k or --deselect chose among them: tests/test_suite.py reads the suite's marks here rather
# than collecting the suite again in a process of its own (every pytest-xdist worker collects it all).
COLLECTED = pytest.StashKey[dict]()


def _work_unit(nodeid: str) -> str:
  """What one worker runs whole: a test file (so that its module fixtures are built once), or the smoke run's
  files together (so that the session's smoke run is trained once)."""
  stem = nodeid.split("::")[0].rsplit("/", 1)[-1].removesuffix(".py")
  return "smoke_run" if stem in SMOKE_RUN_FILES else stem


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook: without the plugin, never called
def pytest_xdist_make_scheduler(config, log):
  """With -n: whole work units (_work_unit) per worker, in collection order. (pytest-xdist's own loadgroup
  marks no longer group anything with pytest 9.2, which keeps a test's id where xdist 3.8 no longer writes.)"""
  from xdist.scheduler import LoadScopeScheduling

  class ByWorkUnit(LoadScopeScheduling):
    def _split_scope(self, nodeid):
      return _work_unit(nodeid)

  return ByWorkUnit(config, log)

