"""Exports an orbit archive to videos and a contact sheet.

    python -m tools.export WORKDIR_OR_ARCHIVE [--out DIR] [--fps 30] [--formats mp4,gif,png]

WORKDIR_OR_ARCHIVE is a training workdir (its renders/orbit.zarr is used) or an archive folder. Writes
PREFIX_{rgb,depth,acc,disparity}.{mp4,gif} and PREFIX_sheet.png, PREFIX being the archive's name without
.zarr ("orbit"), into --out (default: the folder holding the archive). Depth and disparity are colour-mapped
(turbo, near warm); acc is grey. An archive that misses frames is refused with the list of them.
"""
import argparse
import os
import sys

from nerfpod import archive, video
from nerfpod.errors import UserError


def find_archive(path: str) -> str:
  """The archive that `path` names: the folder itself, or a workdir's renders/orbit.zarr."""
  if archive.is_url(path):  # gs://...: no cheap existence checks; a workdir unless it names a .zarr
    return path if path.rstrip("/").endswith(".zarr") else archive.join(path, archive.ORBIT)
  in_workdir = os.path.join(path, archive.ORBIT)
  if not os.path.exists(os.path.join(path, "zarr.json")) and os.path.isdir(in_workdir):
    return in_workdir
  if not os.path.exists(path):
    raise UserError(f"{path} does not exist; pass a training workdir or an orbit archive (.zarr folder).")
  return path


def write_files(path: str, out_dir: str | None = None, fps: float | None = None,
                formats=("mp4", "gif", "png")) -> list[str]:
  """Exports the archive at (or in the workdir) `path` (archive.Archive.export); returns the files' paths."""
  try:
    formats = video.check_formats(formats)
  except ValueError as e:
    raise UserError(f"{e}.") from e
  if fps is not None and fps <= 0:
    raise UserError(f"--fps={fps} must be a positive number of frames per second.")
  files, _ = archive.Archive.open(find_archive(path)).export(out_dir, fps, formats)
  return files


def parse_args(argv):
  parser = argparse.ArgumentParser(prog="nerfpod-export", description=__doc__.split("\n\n")[0])
  parser.add_argument("path", metavar="WORKDIR_OR_ARCHIVE",
                      help="a training workdir (uses renders/orbit.zarr) or an orbit archive folder")
  parser.add_argument("--out", default=None, help="output folder (default: the folder holding the archive)")
  parser.add_argument("--fps", type=float, default=None,
                      help="frames per second (default: the archive's, from orbit.fps)")
  parser.add_argument("--formats", default="mp4,gif,png", help="comma-separated: mp4, gif, png")
  return parser.parse_args(argv)


def run(argv=None) -> None:
  """Console-script entry point (`nerfpod-export`)."""
  args = parse_args(sys.argv[1:] if argv is None else argv)
  try:
    files = write_files(args.path, args.out, args.fps, args.formats.split(","))
  except UserError as e:
    print(f"nerfpod-export: error: {e}", file=sys.stderr, flush=True)
    sys.exit(2)
  for path in files:
    print(path)


if __name__ == "__main__":
  run()
