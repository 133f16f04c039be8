"""The one harness for tests that start processes: real nerfpod runs of N processes x M simulated CPU devices
on 127.0.0.1, started directly or through launch/local.py, and stand-in processes for launcher tests.

    with procs.Run(workdir, overrides, num_processes=2, devices_per_process=4) as run:
      run.wait_ok(timeout)                 # or wait_for(...), signal(...), kill(...)
    result = procs.run_main(*args)         # one process to its end: a CompletedProcess (stdout, stderr)

Run as a script, this file is one such process: `python tests/procs.py <nerfpod.main flags>` runs
nerfpod.main and, when NERFPOD_TEST_RECORD is set to a folder, also records which rays the data pipeline
loaded on this process (process_<index>.npz there), and when NERFPOD_TEST_STALL_AT_STEP is set to a step, stalls
its data pipeline before that step's batch (a run that stops training there, to be killed at a known point,
after the checkpoints before it), and when NERFPOD_TEST_STEP_SECONDS is set to FROM:SECONDS, makes each batch
from step FROM on take SECONDS longer (a run slow enough to be signalled between two checkpoints); with
NERFPOD_TEST_STAND_IN set it is a stand-in that only prints what it was given and does what that variable says
(launcher tests, no JAX).
"""
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parent.parent

# JAX's persistent compilation cache, shared by the test processes and the test session itself: a process
# that runs a program another one (or the session) compiled before skips the compilation (seconds each on a
# small CPU). conftest.py sets JAX_COMPILATION_CACHE_DIR to a folder of the session; this is the fallback
# when procs.py runs without it.
DEFAULT_COMPILATION_CACHE = pathlib.Path(tempfile.gettempdir()) / f"nerfpod-test-jax-cache-{os.getuid()}"
# XLA's flags in every test process (the session's own too, tests/conftest.py). A test compiles far more than it
# runs (most programs run a few steps; most of a test's programs are single operations run eagerly), so:
# - LLVM's optimisation level 0 instead of 2 for the CPU kernels (`xla_backend_optimization_level=0`): a
#   single-operation program compiles in about two thirds of the time (40 -> 27 ms) and the quick loop takes
#   about a quarter less CPU (docs/results.md). Fast-math stays off at every level, so each kernel computes
#   IEEE float arithmetic, but LLVM's optimiser is what turns two programs that differ only in structure
#   (an option switched off, a value kept in memory) into the same machine arithmetic: a claim that two different programs give the same bits is a claim about the
#   optimised kernels, and those tests compile their programs with OPTIMIZED_KERNELS (level 1, as every test
#   did before: the same bits as level 2 on the golden tests);
# - XLA:CPU's loop emitters instead of its newer fusion emitters (`xla_cpu_use_fusion_emitters=false`): a
#   single-operation program compiles in half the time (29 -> 15 ms) and the whole suite takes ~20% less
#   CPU. Elementwise operations and dots give the same bits; some fused reductions add in another order (in
#   the smoke job's first step only the biases' gradients, sums over the batch, differ: by up to 1e-5
#   relative in a component), so results differ in their last bits (the smoke job's held-out PSNR after 20
#   steps by 1e-9 relative, 10,000 times inside the golden test's rtol).
# Every test process compiles alike, so what tests compare between runs is compared under one compiler, and
# tests/test_golden.py also runs the smoke job under users' own flags (XLA's defaults) against the same
# recorded values. docs/results.md has the figures.
# jaxlib 0.12 has no loop emitters (nor the flag: an unknown flag in XLA_FLAGS aborts the process), so from
# jaxlib 0.11 on, the flag is kept only where a probe process accepts it (once per test session: the answer
# travels to its processes in NERFPOD_TEST_XLA_FLAGS).
LOOP_EMITTERS = "--xla_cpu_use_fusion_emitters=false"


def _test_xla_flags() -> str:
  flags = f"--xla_backend_optimization_level=0 {LOOP_EMITTERS}"
  known = os.environ.get("NERFPOD_TEST_XLA_FLAGS")
  if known is not None:
    return known
  from importlib import metadata
  if tuple(int(p) for p in metadata.version("jaxlib").split(".")[:2]) >= (0, 11):
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.jit(lambda x: x + 1)(1)"], capture_output=True,
                           text=True, env=dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu"), timeout=120)
    if f"Unknown flag in XLA_FLAGS: {LOOP_EMITTERS}" in probe.stderr:
      flags = flags.replace(f" {LOOP_EMITTERS}", "")
  os.environ["NERFPOD_TEST_XLA_FLAGS"] = flags
  return flags


TEST_XLA_FLAGS = _test_xla_flags()
# XLA's options for a program whose bits a test compares with another program's (jax.jit(compiler_options=...),
# step.Options(compiler_options=...)): LLVM's optimisation level 1, under which programs that compute the same
# thing give the same bits (see TEST_XLA_FLAGS).
OPTIMIZED_KERNELS = {"xla_backend_optimization_level": "1"}
# Multi-process runs in tests: quick to notice a dead peer, quick to exit.
FAST_FAILURE_FLAGS = ("--heartbeat_timeout_seconds=30", "--shutdown_timeout_seconds=20",
                      "--initialization_timeout=60")


def overrides_to_flags(overrides: dict) -> list[str]:
  return [f"--config.{key}={value}" for key, value in overrides.items()]


def environment(devices_per_process: int, **extra: str) -> dict:
  """The environment of a test process: simulated CPU devices, the shared compilation cache, the repo on
  the path, and none of the multi-process variables of whoever runs the tests."""
  env = dict(os.environ, JAX_NUM_CPU_DEVICES=str(devices_per_process), JAX_PLATFORMS="cpu",
             PYTHONUNBUFFERED="1", PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / "tests")]),
             JAX_COMPILATION_CACHE_DIR=os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(DEFAULT_COMPILATION_CACHE),
             JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
  env["XLA_FLAGS"] = TEST_XLA_FLAGS  # none of the caller's (a host device count of its own, ...)
  for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID",
               "NERFPOD_TEST_RECORD", "NERFPOD_TEST_STAND_IN", "NERFPOD_TEST_COMPILES", "NERFPOD_TEST_STALL_AT_STEP",
               "NERFPOD_TEST_STEP_SECONDS",
               # set by storage.bound_clients where the session itself ran a job: each process sets its own
               "TENSORSTORE_CURL_LOW_SPEED_TIME_SECONDS", "TENSORSTORE_CURL_LOW_SPEED_LIMIT_BYTES"):
    env.pop(name, None)
  env.update(extra)
  return env


def run_main(*args: str, devices_per_process: int = 1, timeout: float = 300,
             env: dict | None = None) -> subprocess.CompletedProcess:
  """`python -m nerfpod.main ARGS` as one process in the repo root, to its end; stdout and stderr apart."""
  return subprocess.run([sys.executable, "-m", "nerfpod.main", *args], cwd=REPO,
                        env=environment(devices_per_process, **(env or {})), capture_output=True, text=True,
                        timeout=timeout)


# Runs nerfpod.main.run() once per argv (JSON on stdin) in a child forked from one interpreter that has
# imported nerfpod.main (absl, ml_collections, the schema; not JAX): each child parses its flags from scratch,
# as `python -m nerfpod.main` would, without paying for the interpreter and the imports again.
_FORKED = r"""
import json, os, sys, tempfile
IMPORTS
results = []
for argv in json.loads(sys.stdin.read()):
  with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
      os.dup2(out.fileno(), 1)
      os.dup2(err.fileno(), 2)
      code = 0
      try:
        CALL
      except SystemExit as e:
        if isinstance(e.code, str):
          print(e.code, file=sys.stderr)
        code = e.code if isinstance(e.code, int) else int(e.code is not None)
      except BaseException:
        import traceback
        traceback.print_exc()
        code = 1
      sys.stdout.flush()
      sys.stderr.flush()
      os._exit(code)
    _, status = os.waitpid(pid, 0)
    out.seek(0)
    err.seek(0)
    results.append([os.waitstatus_to_exitcode(status), out.read().decode(), err.read().decode()])
print(json.dumps(results))
"""


def run_forked_each(imports: str, call: str, argvs: list[list[str]], env: dict,
                    timeout: float = 300) -> list[tuple[int, str, str]]:
  """(exit code, stdout, stderr) of `call` (one line of Python run with `argv` bound) for each argv, each in a
  child forked from one interpreter that has run `imports` (lines of Python) once: the commands' own parsing and
  refusals, without paying for the interpreter and the imports again."""
  import json
  script = _FORKED.replace("IMPORTS", imports).replace("CALL", call)
  done = subprocess.run([sys.executable, "-c", script], input=json.dumps(argvs), cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=timeout)
  if done.returncode != 0:
    raise RuntimeError(f"the forking interpreter failed (exit {done.returncode}): {done.stderr[-3000:]}")
  return [tuple(result) for result in json.loads(done.stdout.strip().splitlines()[-1])]


def run_main_each(argvs: list[list[str]], timeout: float = 300) -> list[subprocess.CompletedProcess]:
  """What run_main(*argv) gives for each argv, for commands refused before any JAX work (bad flags or config
  values): one interpreter imports nerfpod.main and forks a child per argv (run_forked_each). Not for --help
  and its kin: absl lists the `__main__` module's flags, which here is the forking script (run_forked_each)."""
  results = run_forked_each("from nerfpod import main", "sys.argv = [main.__file__, *argv]; main.run()", argvs,
                            environment(1), timeout)
  return [subprocess.CompletedProcess(["nerfpod.main", *argv], code, out, err)
          for argv, (code, out, err) in zip(argvs, results, strict=True)]


class Run:
  """One run of `num_processes` processes; a context manager that kills whatever still runs on exit."""

  def __init__(self, workdir, overrides: dict | None = None, num_processes: int = 1,
               devices_per_process: int = 8, extra_flags=(), record_dir=None, log_dir=None,
               config="configs/default.py:smoke", via_launcher: bool = False, launcher_flags=(),
               stand_in: str | None = None, compiles_dir=None, env: dict | None = None):
    """Starts the processes.

    via_launcher: through launch/local.py (one child here, the launcher, whose output is process 0's),
    else each process directly (so that a test can signal any one of them). stand_in: the processes are
    stand-ins doing what it says, comma-separated per process: 'exit:N' or 'wait' (until SIGTERM, then
    exit 0; 'wait:N': exit N); `config`, `overrides` and `workdir` are then only passed on. compiles_dir:
    each process records the devices of every program it compiles there (tests/compiles.py). env: more
    environment variables for the processes (e.g. a storage emulator's). A workdir may be a URL (gs://...);
    then `log_dir` must be given.
    """
    import portpicker
    self.workdir = workdir if "://" in str(workdir) else pathlib.Path(workdir)  # pathlib would drop a '/'
    self.log_dir = pathlib.Path(log_dir or self.workdir.parent / f"{self.workdir.name}-logs")
    self.log_dir.mkdir(parents=True, exist_ok=True)
    self.procs: list[subprocess.Popen] = []
    self.logs: list[pathlib.Path] = []
    self.started = time.monotonic()
    flags = [f"--config={config}", f"--workdir={self.workdir}", *overrides_to_flags(overrides or {})]
    if num_processes > 1 and not via_launcher:
      port = portpicker.pick_unused_port()
      flags += [f"--coordinator_address=127.0.0.1:{port}", f"--num_processes={num_processes}"]
    if num_processes > 1 and stand_in is None:
      flags += FAST_FAILURE_FLAGS
    flags += list(extra_flags)  # last, so that they win over the above
    extra = dict(env or {})
    if record_dir is not None:
      extra["NERFPOD_TEST_RECORD"] = str(record_dir)
    if stand_in is not None:
      extra["NERFPOD_TEST_STAND_IN"] = stand_in
    if compiles_dir is not None:
      extra["NERFPOD_TEST_COMPILES"] = str(compiles_dir)
    env = environment(devices_per_process, **extra)
    attempt = len(list(self.log_dir.glob("run*_process_0.log")))
    self.launcher_log_dir = self.log_dir / f"run{attempt}"  # via the launcher: processes 1..'s logs
    if via_launcher:
      argvs = [[sys.executable, str(REPO / "launch" / "local.py"), "--module=procs",
                f"--num_processes={num_processes}", f"--devices_per_process={devices_per_process}",
                f"--log_dir={self.launcher_log_dir}", "--grace_s=10", *launcher_flags, "--", *flags]]
    else:
      argvs = [[sys.executable, str(REPO / "tests" / "procs.py"), *flags]
               + ([f"--process_id={index}"] if num_processes > 1 else []) for index in range(num_processes)]
    for index, argv in enumerate(argvs):
      log = self.log_dir / f"run{attempt}_process_{index}.log"
      self.logs.append(log)
      with open(log, "wb") as out:
        self.procs.append(subprocess.Popen(argv, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT,
                                           start_new_session=True))

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.kill()

  def kill(self, index: int | None = None, sig=signal.SIGKILL) -> None:
    """Signals every process (or one), all before waiting for any: a pod that dies at once."""
    hit = [proc for i, proc in enumerate(self.procs) if (index is None or i == index) and proc.poll() is None]
    for proc in hit:
      proc.send_signal(sig)
    if sig == signal.SIGKILL:
      for proc in hit:
        proc.wait()

  def signal(self, index: int, sig) -> None:
    if self.procs[index].poll() is None:
      self.procs[index].send_signal(sig)

  def output(self, index: int = 0) -> str:
    return self.logs[index].read_text(errors="replace")

  def launched_log(self, index: int) -> str:
    """Via the launcher: process `index`'s output (process 0's is the launcher's own, output(0))."""
    path = self.launcher_log_dir / f"process_{index}.log"
    return path.read_text(errors="replace") if path.exists() else ""

  def wait(self, timeout: float) -> list[int]:
    """Return codes of all processes; fails (after killing them all) if any runs past `timeout` seconds."""
    deadline = time.monotonic() + timeout
    try:
      for proc in self.procs:
        proc.wait(timeout=max(0.1, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
      self.kill()
      raise AssertionError(f"processes still running after {timeout} s; logs:\n" + self.tails())
    return [proc.returncode for proc in self.procs]

  def wait_ok(self, timeout: float) -> None:
    codes = self.wait(timeout)
    assert codes == [0] * len(codes), f"exit codes {codes}; logs:\n" + self.tails()

  def wait_for(self, predicate, timeout: float, what: str) -> None:
    """Polls until predicate() holds; fails if it does not within `timeout` s or a process exits first."""
    deadline = time.monotonic() + timeout
    while not predicate():
      if any(proc.poll() is not None for proc in self.procs):
        raise AssertionError(f"a process exited before {what}; logs:\n" + self.tails())
      if time.monotonic() > deadline:
        self.kill()
        raise AssertionError(f"no {what} after {timeout} s; logs:\n" + self.tails())
      time.sleep(0.05)

  def tails(self, lines: int = 25) -> str:
    out = []
    for i, log in enumerate(self.logs):
      text = [l for l in log.read_text(errors="replace").splitlines()
              if not l.startswith(("I1", "I0", "[Gloo]"))]
      out.append(f"--- process {i} ({log}) ---\n" + "\n".join(text[-lines:]))
    return "\n".join(out)


def _record_loaded_rays(folder: str) -> None:
  """Wraps the pipeline's per-step map so that this process's loaded rays are saved at exit."""
  import atexit

  import numpy as np

  from nerfpod import data
  loaded = {}
  original = data.LocalRayBatch.map

  def map_and_record(self, step):
    out = original(self, step)
    loaded[int(step)] = {k: np.asarray(out[k]) for k in ("ray_ids", "origins", "directions", "rgb")}
    return out

  index = next((a.split("=", 1)[1] for a in sys.argv if a.startswith("--process_id=")), "0")

  def save():
    if loaded:
      steps = sorted(loaded)
      np.savez(os.path.join(folder, f"process_{index}.npz"), steps=np.array(steps),
               **{k: np.stack([loaded[s][k] for s in steps]) for k in loaded[steps[0]]})

  data.LocalRayBatch.map = map_and_record
  atexit.register(save)


def _stall_at_step(stall: int) -> None:
  """Makes the data pipeline wait (an hour) before the batch of step `stall`: training stops there."""
  from nerfpod import data
  original = data.LocalRayBatch.map

  def map_or_stall(self, step):
    if int(step) == stall:
      time.sleep(3600)
    return original(self, step)

  data.LocalRayBatch.map = map_or_stall


def _slow_from_step(first: int, seconds: float) -> None:
  """Makes the data pipeline take `seconds` longer for each batch from step `first` on."""
  from nerfpod import data
  original = data.LocalRayBatch.map

  def map_slowly(self, step):
    if int(step) >= first:
      time.sleep(seconds)
    return original(self, step)

  data.LocalRayBatch.map = map_slowly


def _cache_every_process() -> None:
  """Lets every process of a test run write JAX's persistent compilation cache, not only process 0.

  On a CPU each process's executables carry its process index, so each process has cache keys of its own;
  JAX writes entries from process 0 only (against write contention on shared filesystems), so every other
  process compiled every program in every run: about 10 s of a 2-process smoke run's 18, during which
  process 0 waits for it. Here the disk is local and the keys differ per process: no contention. A cached
  executable is the one compiling it would give, so runs compute the same bits either way."""
  from jax._src import compilation_cache, compiler, config
  original = compiler._cache_write

  def write(cache_key, compile_time_secs, module_name, backend, executable, *rest):
    # (JAX 0.10 passes the program's host callbacks last, which it does not cache; JAX 0.12 no longer does.)
    if (compiler.distributed.global_state.process_id in (None, 0) or any(rest)
        or compile_time_secs < config.persistent_cache_min_compile_time_secs.value):
      return original(cache_key, compile_time_secs, module_name, backend, executable, *rest)
    compilation_cache.put_executable_and_time(cache_key, module_name, executable, backend, int(compile_time_secs))

  compiler._cache_write = write


def _stand_in(actions: str) -> None:
  """A stand-in for nerfpod.main in launcher tests (no JAX): prints what it was given, then does what
  `actions` (comma-separated, one per process) says for its process id: 'exit:N' or 'wait' (until SIGTERM,
  then exit 0; 'wait:N': then exit N)."""
  index = int(next((a.split("=", 1)[1] for a in sys.argv if a.startswith("--process_id=")), "0"))
  action = actions.split(",")[index]
  print(f"stand-in process {index} ready: JAX_NUM_CPU_DEVICES={os.environ.get('JAX_NUM_CPU_DEVICES')} "
        f"args={' '.join(sys.argv[1:])}", flush=True)
  if action.startswith("exit:"):
    sys.exit(int(action.split(":")[1]))
  code = int(action.split(":")[1]) if action.startswith("wait:") else 0
  signal.signal(signal.SIGTERM, lambda *_: sys.exit(code))
  time.sleep(60)
  sys.exit(9)


if __name__ == "__main__":
  if os.environ.get("NERFPOD_TEST_STAND_IN"):
    _stand_in(os.environ["NERFPOD_TEST_STAND_IN"])
  sys.path.insert(0, str(REPO))
  if os.environ.get("NERFPOD_TEST_RECORD"):
    _record_loaded_rays(os.environ["NERFPOD_TEST_RECORD"])
  if os.environ.get("NERFPOD_TEST_STALL_AT_STEP"):
    _stall_at_step(int(os.environ["NERFPOD_TEST_STALL_AT_STEP"]))
  if os.environ.get("NERFPOD_TEST_STEP_SECONDS"):
    first, seconds = os.environ["NERFPOD_TEST_STEP_SECONDS"].split(":")
    _slow_from_step(int(first), float(seconds))
  if os.environ.get("NERFPOD_TEST_COMPILES"):
    import compiles
    index = next((a.split("=", 1)[1] for a in sys.argv if a.startswith("--process_id=")), "0")
    compiles.install(os.path.join(os.environ["NERFPOD_TEST_COMPILES"], f"compiles_process_{index}.jsonl"))
  _cache_every_process()
  from nerfpod import main
  sys.argv[0] = "nerfpod.main"
  main.run()


def in_process(run, program: str, capsys, monkeypatch, cwd, flag_values=()):
  """A function call(*args) that runs a command's entry point `run(argv)` in this process, as `program ARGS`
  (sys.argv set: ml_collections reads --config's overrides off it), from `cwd`: its exit code, stdout and
  stderr as a process's (subprocess.CompletedProcess). For claims about a command's parsing, help and
  refusals, which end before any work (no process of its own needed). The flags ml_collections defines as a
  call parses --config.* overrides (one per override) are removed after it, from absl's FLAGS and from
  `flag_values` (a command's own FlagValues), as a process starts without them: two calls may override the same
  field."""
  from absl import flags
  monkeypatch.chdir(cwd)
  held = [flags.FLAGS, *flag_values]

  def call(*args):
    monkeypatch.setattr(sys, "argv", [program, *args])
    capsys.readouterr()
    defined = [set(values) for values in held]
    try:
      run(list(args))
      code = 0
    except SystemExit as e:
      code = e.code if isinstance(e.code, int) else int(e.code is not None)
    finally:  # the overrides' flags (`config.train.num_steps`: a config flag's name, a dot, the field's path)
      for values, names in zip(held, defined):
        for name in [name for name in values if name not in names and name.split(".")[0] in names]:
          delattr(values, name)
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess([program, *args], code, out, err)
  return call
