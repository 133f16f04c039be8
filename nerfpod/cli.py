"""The `nerfpod` command: one entry point, a subcommand per thing a user does.

    nerfpod train --config=configs/default.py --workdir=DIR     (= python -m nerfpod.main ...)
    nerfpod eval|render --config=... --workdir=DIR               (= python -m nerfpod.main --mode=eval|render)
    nerfpod view|prepare|export|aot|bench ...

Each subcommand is a module's `run(argv)` (argv: the words after its name), imported only when asked for (so
`nerfpod --help` starts no JAX and needs no optional extra); the modes (train, eval, render: nerfpod.run.MODES)
are nerfpod.main's, told which one. Every one starts and ends as errors.Command.run does: `nerfpod NAME --help`
lists that subcommand's flags, a bad flag is one `nerfpod: error:` sentence with exit code 2, Ctrl-C exit code
130. `nerfpod --config=... --workdir=...` without a subcommand trains, as the command did before it had
subcommands.
"""
import importlib
import sys

from nerfpod.errors import fail
from nerfpod.run import MODES

# name -> (the module whose run(argv) it is, what it does: its line in `nerfpod --help` and its own --help's)
SUBCOMMANDS = {
    **{name: ("nerfpod.main", mode.about) for name, mode in MODES.items()},
    "view": ("nerfpod.view", "a live web viewer of a workdir (training may still be running)"),
    "prepare": ("nerfpod.prepare", "photos or a video -> a posed capture folder (COLMAP structure from motion)"),
    "export": ("nerfpod.export", "what a trained run gives other tools: video, pointcloud, mesh, cameras, depth"),
    "aot": ("nerfpod.pod.aot", "compile a config for a TPU pod topology here, and report memory and time"),
    "bench": ("nerfpod.bench", "benchmark a config: throughput, FLOP/s against the peak, time to quality"),
}


def usage() -> str:
  width = max(len(name) for name in SUBCOMMANDS)
  lines = ["usage: nerfpod SUBCOMMAND [flags]   (nerfpod SUBCOMMAND --help: its flags)", "",
           "Neural Radiance Fields in JAX, from one CPU to a TPU pod.", "", "subcommands:"]
  lines += [f"  {name:<{width}}  {line}" for name, (_, line) in SUBCOMMANDS.items()]
  lines += ["", "Start with: nerfpod train --config=configs/default.py --workdir=runs/default"]
  return "\n".join(lines)


def run(argv=None) -> None:
  """Console-script entry point."""
  argv = list(sys.argv[1:] if argv is None else argv)
  if not argv or argv[0] in ("-h", "--help", "help"):
    print(usage(), file=sys.stdout if argv else sys.stderr)
    sys.exit(0 if argv else 2)
  if argv[0].startswith("-"):  # flags without a subcommand: the run, as before subcommands
    argv = ["train", *argv]
  name, rest = argv[0], argv[1:]
  if name not in SUBCOMMANDS:
    fail(f"unknown subcommand {name!r}; choose one of {', '.join(SUBCOMMANDS)} (nerfpod --help says what each "
         f"does).")
  module_name, _ = SUBCOMMANDS[name]
  try:
    module = importlib.import_module(module_name)
  except ImportError as e:
    fail(f"`nerfpod {name}` could not start ({e}); reinstall nerfpod with pip install -c constraints.txt -e . "
         f"(and the extra the message names).")
  if name in MODES:
    module.run(rest, mode=name)  # nerfpod.main: the mode is the subcommand
  else:
    module.run(rest)


if __name__ == "__main__":
  run()
