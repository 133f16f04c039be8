"""nerfpod's entry point: `python -m nerfpod.main --config=configs/default.py --workdir=DIR`.

Parses flags, checks the whole config (nerfpod.schema) before JAX starts, starts the multi-host runtime where
there is one, and runs the mode (nerfpod.run.modes): `train` (the default: train_and_evaluate, which trains,
evaluates and renders the orbit), `eval` or `render` (from the workdir's newest checkpoint). A user's
mistake is printed as one sentence per problem with exit code 2. Exit codes: 0 finished; 2 bad input (or
training diverged); checkpoint.preempted_exit_code (75) stopped early at a saved step (SIGTERM, preemption, a
first Ctrl-C): run the same command again; 69 (EX_UNAVAILABLE) a gs:// workdir's bucket stopped answering (or
failed) mid-run, for checkpoint.storage_timeout_s: run the same command again once storage is back; 130
interrupted outside training's steps.

`nerfpod train|eval|render ...` (nerfpod.cli) is this entry point with --mode set; the other subcommands
(`nerfpod view`, `prepare`, `export`, `aot`, `bench`) are modules of their own. Every one reads its flags
through errors.parse_flags: one --help, one sentence and exit 2 for a bad flag.
"""
import signal
import sys

from absl import app, flags, logging
from ml_collections import config_flags

from nerfpod import schema
from nerfpod.errors import UserError, fail, parse_flags

# What each mode does: the one line of its --help (nerfpod.cli lists the same lines).
MODES = {"train": "train (resuming from the workdir), evaluate the held-out views, render the orbit",
         "eval": "evaluate the workdir's newest checkpoint -> eval/metrics.json",
         "render": "render (or finish) the orbit of the workdir's newest checkpoint, and its videos"}
_CONFIG = config_flags.DEFINE_config_file(
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
                          "train: train (resuming), evaluate, render the orbit; eval: evaluate the workdir's "
                          "newest checkpoint; render: render (or finish) its orbit and export the videos.")


def main(argv):
  del argv  # [the program's name]: _flags_parser refuses anything else
  if not flags.FLAGS["verbosity"].present:  # orbax and grain log every save at INFO: keep the console readable
    logging.set_verbosity(logging.WARNING)
  try:
    try:
      config = _CONFIG.value
      config.keys()  # the value is a lazy proxy until first touched
    except OSError as e:  # ml_collections reports a config file that failed to load on first access
      raise UserError(f"could not load the --config file ({' '.join(str(e).split())}).") from None
    schema.validate(config)  # every mistake, before JAX starts: no process waits for a peer in vain
    missing = schema.package_rules(schema.flatten(config))  # an optional extra the config asks for
    if missing:
      raise schema.ConfigError(missing)
    from nerfpod import distributed  # imports jax; no JAX call happens before initialize
    distributed.keep_off_absent_tpu()
    distributed.initialize(_COORDINATOR.value, _NUM_PROCESSES.value, _PROCESS_ID.value,
                           heartbeat_timeout_seconds=_HEARTBEAT.value,
                           shutdown_timeout_seconds=_SHUTDOWN.value, initialization_timeout=_INIT_TIMEOUT.value)
    from nerfpod.run import compilation, modes
    from nerfpod.workdir import checkpoints
    checkpoints.quiet_library_reports()  # orbax's reports of what nerfpod asked for, or said already
    compilation.tune_host(config)  # process-wide (glibc's malloc on a CPU): here, where the process starts
    result = {"train": modes.train_and_evaluate, "eval": modes.evaluate_workdir,
              "render": modes.render_workdir}[_MODE.value](config, _WORKDIR.value)
  except UserError as e:
    fail(e)
  except KeyboardInterrupt:  # Ctrl-C outside training's steps (start-up, evaluation, the orbit)
    print("nerfpod: interrupted; the same command resumes from the newest checkpoint", file=sys.stderr,
          flush=True)
    sys.exit(128 + signal.SIGINT)
  if _MODE.value == "train" and result is None:  # stopped early at a saved step: "run me again"
    sys.exit(config.checkpoint.preempted_exit_code)


def _flags_parser(argv):
  """The shared parsing (errors.parse_flags) of absl's FLAGS, where the flags of this module are; argv[0] is
  `nerfpod MODE` (nerfpod.cli) or this file's path (python -m nerfpod.main)."""
  mode = next((a.split("=", 1)[1] for a in reversed(argv) if a.startswith("--mode=")), "train")
  command = argv[0] if argv[0].startswith("nerfpod ") else "python -m nerfpod.main"
  parse_flags(command, MODES.get(mode, MODES["train"]), flags.FLAGS, argv[1:], required=("config", "workdir"),
              examples={"config": "configs/default.py", "workdir": "runs/default", "num_processes": "2",
                        "process_id": "0", "coordinator_address": "10.0.0.2:8476"})
  return argv[:1]


def run():
  """`python -m nerfpod.main ...` and `nerfpod train|eval|render ...` (nerfpod.cli)."""
  app.run(main, flags_parser=_flags_parser)


if __name__ == "__main__":
  run()
