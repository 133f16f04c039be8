"""nerfpod's entry point: `python -m nerfpod.main --config=configs/default.py --workdir=DIR`.

Parses flags, checks the whole config (nerfpod.schema) before JAX starts, starts the multi-host runtime where
there is one, and runs the mode (nerfpod.run.modes): `train` (the default: train_and_evaluate, which trains,
evaluates and renders the orbit), `eval` or `render` (from the workdir's newest checkpoint). A user's
mistake is printed as one sentence per problem with exit code 2. Exit codes: 0 finished; 2 bad input (or
training diverged); checkpoint.preempted_exit_code (75) stopped early at a saved step (SIGTERM, preemption, a
first Ctrl-C): run the same command again; 69 (EX_UNAVAILABLE) a gs:// workdir's bucket stopped answering (or
failed) mid-run, for checkpoint.storage_timeout_s: run the same command again once storage is back; 130
interrupted outside training's steps.

`nerfpod train|eval|render ...` (nerfpod.cli) is this entry point with the mode set (nerfpod.run.MODES, the
one table of the modes); the other subcommands (`nerfpod view`, `prepare`, `export`, `aot`, `bench`) are modules
of their own. Every one starts and ends as errors.Command.run does: one --help, one sentence and exit 2 for a bad
flag or config, exit 130 for Ctrl-C.
"""
import sys

from absl import flags, logging
from ml_collections import config_flags

from nerfpod import schema
from nerfpod.errors import Command, fail
from nerfpod.run import MODES

# Where a run's flags live: absl's own FLAGS (its --verbosity and kin are a run's flags too).
config_flags.DEFINE_config_file(
    "config", None, "Config file, e.g. configs/default.py[:arg]; a field is overridden as "
    "--config.section.name=value "
    "(`python -m nerfpod.schema` lists every field, its default, range and meaning).",
    lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Where checkpoints, TensorBoard events, metrics and renders go.")
_COORDINATOR = flags.DEFINE_string("coordinator_address", None,
                                   "host:port of process 0, for multi-process runs off TPU "
                                   "(else JAX_COORDINATOR_ADDRESS).")
_NUM_PROCESSES = flags.DEFINE_integer("num_processes", None, "Processes in the run (else JAX_NUM_PROCESSES).")
_PROCESS_ID = flags.DEFINE_integer("process_id", None, "This process's index (else JAX_PROCESS_ID).")
_HEARTBEAT = flags.DEFINE_integer("heartbeat_timeout_seconds", 100,
                                  "Multi-process runs: a process whose peer sent no heartbeat for this long "
                                  "stops with an error instead of waiting for it forever.")
_SHUTDOWN = flags.DEFINE_integer("shutdown_timeout_seconds", 300,
                                 "Multi-process runs: how long a finished process waits for the others at exit "
                                 "(process 0 may still be exporting videos).")
_INIT_TIMEOUT = flags.DEFINE_integer("initialization_timeout", 300,
                                     "Multi-process runs: how long a process waits for all to connect at start.")
_MODE = flags.DEFINE_enum("mode", "train", list(MODES),
                          "; ".join(f"{name}: {mode.about}" for name, mode in MODES.items()) + ".")


def check(config) -> None:
  """Every mistake in the config, before JAX starts (no process waits for a peer in vain): the schema's rules,
  and an optional extra the config asks for that is not installed."""
  schema.validate(config)
  missing = schema.package_rules(schema.flatten(config))
  if missing:
    raise schema.ConfigError(missing)


def main(config) -> int | None:
  """The run of a checked config: JAX's backend and multi-process runtime, then the mode (nerfpod.run.modes)."""
  if not flags.FLAGS["verbosity"].present:  # orbax and grain log every save at INFO: keep the console readable
    logging.set_verbosity(logging.WARNING)
  from nerfpod import distributed  # imports jax; no JAX call happens before initialize
  distributed.keep_off_absent_tpu()
  distributed.initialize(_COORDINATOR.value, _NUM_PROCESSES.value, _PROCESS_ID.value,
                         heartbeat_timeout_seconds=_HEARTBEAT.value,
                         shutdown_timeout_seconds=_SHUTDOWN.value, initialization_timeout=_INIT_TIMEOUT.value)
  from nerfpod.run import compilation, modes
  from nerfpod.workdir import quiet
  quiet.quiet_library_reports()  # orbax's reports of what nerfpod asked for, or said already
  compilation.tune_host(config)  # process-wide (glibc's malloc on a CPU): here, where the process starts
  result = getattr(modes, MODES[_MODE.value].function)(config, _WORKDIR.value)
  if _MODE.value == "train" and result is None:  # stopped early at a saved step: "run me again"
    return config.checkpoint.preempted_exit_code
  return None


def run(argv=None, mode: str | None = None) -> None:
  """`python -m nerfpod.main ...` (`argv`: the words after it; None: sys.argv[1:]) and `nerfpod MODE ...`
  (nerfpod.cli, `mode` set: the command is named `nerfpod MODE`, and sets --mode itself)."""
  argv = list(sys.argv[1:] if argv is None else argv)
  if mode is not None:
    if any(a == "--mode" or a.startswith("--mode=") for a in argv):
      fail(f"`nerfpod {mode}` sets the mode itself; leave out --mode (or use `python -m nerfpod.main "
           f"--mode=...`).")
    argv.append(f"--mode={mode}")
  chosen = mode or next((a.split("=", 1)[1] for a in reversed(argv) if a.startswith("--mode=")), "train")
  Command(f"nerfpod {mode}" if mode else "python -m nerfpod.main", MODES.get(chosen, MODES["train"]).about,
          flags.FLAGS, required=("config", "workdir"), check=check,
          examples={"config": "configs/default.py", "workdir": "runs/default", "num_processes": "2",
                    "process_id": "0", "coordinator_address": "10.0.0.2:8476"},
          after_ctrl_c="the same command resumes from the newest checkpoint").run(argv, main)


if __name__ == "__main__":
  run()
