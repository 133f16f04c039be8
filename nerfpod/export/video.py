"""`nerfpod export video`: the orbit archive to videos and a contact sheet.

--workdir is a training workdir (its renders/orbit.zarr is used) or an archive folder itself. Writes
PREFIX_{rgb,depth,acc,disparity}.{mp4,gif} and PREFIX_sheet.png, PREFIX being the archive's name without
.zarr ("orbit"), into --out (default: the folder holding the archive). Depth and disparity are colour-mapped
(turbo, near warm); acc is grey. An archive that misses frames is refused with the list of them.
"""
import os

from absl import flags

from nerfpod import storage
from nerfpod.render import archive, video
from nerfpod.errors import UserError

ABOUT = "the orbit archive (renders/orbit.zarr) to videos and a contact sheet"


def find_archive(path: str) -> str:
  """The archive that `path` names: the folder itself, or a workdir's renders/orbit.zarr."""
  if storage.is_url(path):  # gs://...: no cheap existence checks; a workdir unless it names a .zarr
    return path if path.rstrip("/").endswith(".zarr") else storage.join(path, archive.ORBIT)
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


def define_flags(flag_values) -> None:
  flags.DEFINE_string("workdir", None, "A training workdir (uses renders/orbit.zarr) or an orbit archive folder.",
                      flag_values=flag_values)
  flags.DEFINE_string("out", None, "Output folder (default: the folder holding the archive).",
                      flag_values=flag_values)
  flags.DEFINE_float("fps", None, "Frames per second (default: the archive's, from orbit.fps).",
                     flag_values=flag_values)
  flags.DEFINE_list("formats", ["mp4", "gif", "png"], "Comma-separated: mp4, gif, png.", flag_values=flag_values)


def export(args) -> list[str]:
  return write_files(args.workdir, args.out, args.fps, args.formats)
