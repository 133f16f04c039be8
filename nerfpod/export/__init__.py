"""`nerfpod export KIND`: what a trained run gives to other tools.

    nerfpod export video --workdir=DIR [--out=DIR] [--fps=30] [--formats=mp4,gif,png]
    nerfpod export pointcloud --workdir=DIR [--out=FILE.ply] [--num_points=1000000] [--normalized]
    nerfpod export mesh --workdir=DIR [--out=FILE.ply|.obj] [--resolution=256] [--level=25] [--normalized]
    nerfpod export cameras --workdir=DIR [--out=DIR/transforms.json] [--normalized]
    nerfpod export depth --workdir=DIR [--out=DIR] [--split=train] [--format=png|npy] [--normalized]

video reads the orbit archive; the others restore the workdir's newest checkpoint read-only (local or gs://,
training may still run) and render or query it on every device of every host (on a pod, run the command on
every host, as training; process 0 writes). Their outputs default to DIR/exports/. Each kind is a module
here (video, pointcloud, mesh, cameras, depth) with ABOUT, define_flags(flag_values), check(args) and
export(); nerfpod.run.trained restores a workdir for them, shared holds what they share (the field and the
renderer over the whole device mesh, the output path's check, progress lines), ply writes PLY files. Each
kind's absl flags are defined when that kind is asked for, in a FlagValues of its own, and read as every
subcommand reads them (errors.parse_flags: `nerfpod export KIND --help`, one sentence and exit 2 for a
mistake).
"""
import importlib
import sys
import types

from absl import flags

from nerfpod.errors import HELP_WORDS, Command, fail, parse_flags
from nerfpod.export.video import write_files  # noqa: F401 (the earlier nerfpod.export.write_files)

KINDS = {
    "video": "the orbit archive (renders/orbit.zarr) to videos and a contact sheet",
    "pointcloud": "a coloured point cloud (PLY) from the training views' rendered depth",
    "mesh": "a coloured triangle mesh (PLY or OBJ) by marching cubes on the density",
    "cameras": "the cameras, poses and images as a nerfstudio transforms.json",
    "depth": "per-view depth maps of a split (16-bit PNG with their scale, or .npy)",
}


def _module(kind: str):
  return importlib.import_module(f"nerfpod.export.{kind}")


def kind_flags(kind: str) -> flags.FlagValues:
  """The flags of `nerfpod export KIND`, defined now (the kinds share names with other meanings: --out, --split)."""
  flag_values = flags.FlagValues()
  if kind != "video":
    flags.DEFINE_string("workdir", None, "The training run's workdir (local or gs://).", flag_values=flag_values)
    flags.DEFINE_string("out", None, "Where to write (default: under WORKDIR/exports/).", flag_values=flag_values)
    flags.DEFINE_bool("normalized", False, "Write the normalised scene's coordinates, not the capture's own.",
                      flag_values=flag_values)
  _module(kind).define_flags(flag_values)
  return flag_values


def usage() -> str:
  """`nerfpod export --help`: the kinds, one line each."""
  width = max(len(kind) for kind in KINDS)
  return "\n".join(["usage: nerfpod export KIND [flags]   (nerfpod export KIND --help: its flags)", "",
                    __doc__.split("\n\n")[0].split(": ", 1)[1], "", "kinds:",
                    *[f"  {kind:<{width}}  {about}" for kind, about in KINDS.items()]])


def command(argv) -> Command:
  """The command `nerfpod export KIND` that `argv` (KIND, then its flags) names: --help before a kind lists the
  kinds; no kind or an unknown one is one sentence, exit 2."""
  argv = list(argv)
  if not argv or argv[0].startswith("-"):
    if any(word in HELP_WORDS for word in argv):
      print(usage())
      sys.exit(0)
    fail(f"name what to export first: nerfpod export KIND, KIND one of {', '.join(KINDS)} (nerfpod export --help "
         f"says what each writes).")
  kind = argv[0]
  if kind not in KINDS:
    fail(f"unknown kind {kind!r}; choose one of {', '.join(KINDS)} (nerfpod export --help says what each writes).")
  return Command(f"nerfpod export {kind}", KINDS[kind], kind_flags(kind), required=("workdir",),
                 examples={"workdir": "runs/mine", "fps": "30"})


def parse_args(argv) -> types.SimpleNamespace:
  """`KIND --flag=value ...` -> the kind and its flags' values (attributes); --help and every mistake end here
  (errors.parse_flags)."""
  chosen = command(argv)
  parse_flags(chosen.name, chosen.about, chosen.flag_values, list(argv)[1:], chosen.required, chosen.examples)
  return _args(chosen)


def _args(chosen: Command) -> types.SimpleNamespace:
  """The parsed flags of `nerfpod export KIND`, with the kind."""
  return types.SimpleNamespace(kind=chosen.name.split()[-1], **chosen.flag_values.flag_values_dict())


def _default_out(module, args) -> tuple[str, str]:
  """(default path under WORKDIR/exports/, 'file' or 'folder')."""
  if hasattr(module, "default_out"):
    return module.default_out(args), "folder"
  return module.DEFAULT_OUT, "file"


def export(args) -> list[str] | dict:
  """Runs one parsed `nerfpod export` command; a user's mistake is a UserError."""
  module = _module(args.kind)
  if args.kind == "video":
    return module.export(args)
  module.check(args)
  from nerfpod import distributed  # import JAX: only for the kinds that need it
  from nerfpod.workdir import quiet
  quiet.quiet_library_reports()  # orbax's reports of what nerfpod asked for, or said already
  distributed.keep_off_absent_tpu()
  distributed.initialize()  # several hosts (a TPU pod, JAX_* variables) render together; else one process
  from nerfpod.export import shared
  from nerfpod.run import trained
  trained.check(args.workdir)  # no config.json or checkpoint: refused before --out is made
  default, kind = _default_out(module, args)
  out = shared.output_path(args.out, default, args.workdir, kind)
  module.export(args, trained.restore(args.workdir), out)
  return [out]


def run(argv=None) -> None:
  """`nerfpod export KIND ...` and `python -m nerfpod.export KIND ...` (argv: the words after `export`; None:
  sys.argv[1:])."""
  argv = sys.argv[1:] if argv is None else list(argv)
  chosen = command(argv)

  def work():
    from absl import logging
    logging.set_verbosity(logging.WARNING)  # orbax and grain log at INFO; warnings (e.g. a scene's) stay shown
    args = _args(chosen)
    files = export(args)
    if args.kind == "video":
      for path in files:
        print(path)
  chosen.run(argv[1:], work)


if __name__ == "__main__":
  run()
