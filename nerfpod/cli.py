"""The `nerfpod` command: one entry point, a subcommand per thing a user does.

    nerfpod train --config=configs/default.py --workdir=DIR     (= python -m nerfpod.main ...)
    nerfpod eval|render --config=... --workdir=DIR               (= python -m nerfpod.main --mode=eval|render)
    nerfpod view|prepare|export|aot|bench ...

Each subcommand is a module's `run(argv)`, imported only when asked for (so `nerfpod --help` starts no JAX
and needs no optional extra). Every one reads its absl flags through errors.parse_flags: `nerfpod NAME --help`
lists that subcommand's flags, and a bad flag is one `nerfpod: error:` sentence with exit code 2. `nerfpod --config=... --workdir=...` without a subcommand trains, as the
command did before it had subcommands.
"""
import importlib
import sys

from nerfpod.errors import fail

# name -> (module, what it does, whether the module's run() takes the program name as argv[0] (absl))
SUBCOMMANDS = {
    "train": ("nerfpod.main", "train (resuming from the workdir), evaluate the held-out views, render the orbit",
              True),
    "eval": ("nerfpod.main", "evaluate the workdir's newest checkpoint -> eval/metrics.json", True),
    "render": ("nerfpod.main", "render (or finish) the orbit of the workdir's newest checkpoint, and its videos",
               True),
    "view": ("nerfpod.view", "a live web viewer of a workdir (training may still be running)", False),
    "prepare": ("nerfpod.prepare", "photos or a video -> a posed capture folder (COLMAP structure from motion)",
                False),
    "export": ("nerfpod.export", "what a trained run gives other tools: video, pointcloud, mesh, cameras, depth",
               False),
    "aot": ("nerfpod.pod.aot", "compile a config for a TPU pod topology here, and report memory and time",
            True),
    "bench": ("nerfpod.bench", "benchmark a config: throughput, FLOP/s against the peak, time to quality", True),
}
_MODES = ("train", "eval", "render")


def usage() -> str:
  width = max(len(name) for name in SUBCOMMANDS)
  lines = ["usage: nerfpod SUBCOMMAND [flags]   (nerfpod SUBCOMMAND --help: its flags)", "",
           "Neural Radiance Fields in JAX, from one CPU to a TPU pod.", "", "subcommands:"]
  lines += [f"  {name:<{width}}  {line}" for name, (_, line, _) in SUBCOMMANDS.items()]
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
  module_name, _, takes_program_name = SUBCOMMANDS[name]
  if name in _MODES:
    if any(a == "--mode" or a.startswith("--mode=") for a in rest):
      fail(f"`nerfpod {name}` sets the mode itself; leave out --mode (or use `python -m nerfpod.main "
           f"--mode=...`).")
    rest = [*rest, f"--mode={name}"]
  try:
    module = importlib.import_module(module_name)
  except ImportError as e:
    fail(f"`nerfpod {name}` could not start ({e}); reinstall nerfpod with pip install -c constraints.txt -e . "
         f"(and the extra the message names).")
  if takes_program_name:
    sys.argv[:] = [f"nerfpod {name}", *rest]  # absl parses sys.argv; the name shows in its messages
    module.run()
  else:
    module.run(rest)


if __name__ == "__main__":
  run()
