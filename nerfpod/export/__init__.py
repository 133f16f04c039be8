"""`nerfpod export KIND`: what a trained run gives to other tools.

    nerfpod export video --workdir=DIR [--out=DIR] [--fps=30] [--formats=mp4,gif,png]
    nerfpod export pointcloud --workdir=DIR [--out=FILE.ply] [--num_points=1000000] [--normalized]
    nerfpod export mesh --workdir=DIR [--out=FILE.ply|.obj] [--resolution=256] [--level=25] [--normalized]
    nerfpod export cameras --workdir=DIR [--out=DIR/transforms.json] [--normalized]
    nerfpod export depth --workdir=DIR [--out=DIR] [--split=train] [--format=png|npy] [--normalized]

video reads the orbit archive; the others restore the workdir's newest checkpoint read-only (local or gs://,
training may still run) and render or query it on every device of every host (on a pod, run the command on
every host, as training; process 0 writes). Their outputs default to DIR/exports/. Each kind is a module
here (video, pointcloud, mesh, cameras, depth) with ABOUT, add_arguments(parser), check(args) and export();
trained restores a workdir for them, ply writes PLY files.
"""
import argparse
import importlib
import sys

from nerfpod.errors import UserError, fail
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


def parse_args(argv):
  parser = argparse.ArgumentParser(prog="nerfpod export", description=__doc__.split("\n\n")[0])
  kinds = parser.add_subparsers(dest="kind", required=True, metavar="KIND")
  for kind, about in KINDS.items():
    sub = kinds.add_parser(kind, help=about, description=_module(kind).__doc__.split("\n\n")[0])
    if kind == "video":
      _module(kind).add_arguments(sub)
      continue
    sub.add_argument("--workdir", required=True, help="the training run's workdir (local or gs://)")
    sub.add_argument("--out", default=None, help="where to write (default: under WORKDIR/exports/)")
    sub.add_argument("--normalized", action="store_true",
                     help="write the normalised scene's coordinates, not the capture's own")
    _module(kind).add_arguments(sub)
  return parser.parse_args(argv)


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
  from nerfpod.workdir import checkpoints
  checkpoints.quiet_library_reports()  # orbax's reports of what nerfpod asked for, or said already
  distributed.keep_off_absent_tpu()
  distributed.initialize()  # several hosts (a TPU pod, JAX_* variables) render together; else one process
  from nerfpod.export import trained as trained_lib
  from nerfpod.run import trained as run_trained
  run_trained.check(args.workdir)  # no config.json or checkpoint: refused before --out is made
  default, kind = _default_out(module, args)
  out = trained_lib.output_path(args.out, default, args.workdir, kind)
  module.export(args, run_trained.restore(args.workdir), out)
  return [out]


def run(argv=None) -> None:
  """`nerfpod export KIND ...` (argv: the arguments after `export`)."""
  argv = list(sys.argv[1:] if argv is None else argv)
  if argv and not argv[0].startswith("-") and argv[0] not in KINDS:
    print(f"nerfpod export: error: unknown kind {argv[0]!r}; choose one of {', '.join(KINDS)} "
          f"(nerfpod export --help says what each writes).", file=sys.stderr, flush=True)
    sys.exit(2)
  args = parse_args(argv)
  from absl import logging
  logging.set_verbosity(logging.WARNING)  # orbax and grain log at INFO; warnings (e.g. a scene's) stay shown
  try:
    files = export(args)
  except UserError as e:
    fail(e, "nerfpod export")
  if args.kind == "video":
    for path in files:
      print(path)


if __name__ == "__main__":
  run()
