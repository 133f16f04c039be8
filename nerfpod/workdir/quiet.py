"""Keeps what orbax, asyncio, tensorstore and the storage clients report about nerfpod's own doing out of a
process's output, and lets every other report through.

nerfpod asks for what it can by the libraries' settings (a read-only manager's options, the absl logger's level
around what nerfpod does on purpose: nerfpod.workdir.checkpoints). What is left is dropped here, each report by
its level and its error (failures.disk_full, failures.storage_failure), or, where nothing else tells it, by the
words nerfpod.workdir.library_texts holds:

    _DiskFullIsReported        orbax's error logs of a save that failed on a full disk (the run says it in one
                               sentence: nerfpod.run.modes)
    _StorageFailureIsReported  those of orbax's save threads and gcsfs's retries on storage that failed (the run
                               says it in one sentence: nerfpod.workdir.watchdog)
    _AbandonedReadTasks        asyncio's logs of the reads orbax abandons when a restore fails
    quiet_abandoned_reads      sys.unraisablehook, less the same reads' reports (Python has no other way to them)

The entry points call quiet_library_reports (nerfpod.main, the exports, the viewer), once per process; calling it
again changes nothing.
"""
import logging
import sys
import traceback

from nerfpod.workdir import failures, library_texts


class _DiskFullIsReported(logging.Filter):
  """Drops orbax's error logs (each with its traceback, up to 24 of them) of a save that failed on a full disk:
  the run stops on it with one sentence (nerfpod.run.modes)."""

  def filter(self, record: logging.LogRecord) -> bool:
    if record.levelno < logging.ERROR:
      return True
    return not (failures.disk_full(record.exc_info[1] if record.exc_info else None)
                or failures.says_disk_full(record.getMessage()))


class _StorageFailureIsReported(logging.Filter):
  """Drops the error logs, each with its traceback, of orbax's save threads and of gcsfs's retries whose error
  is a storage client's failure to reach or hear from its service (a connection refused, reset or timed out,
  an HTTP error, a tensorstore request given up): the error itself reaches the caller, and a run whose bucket
  fails says so in one sentence (nerfpod.workdir.watchdog; storage._call for what a scene reads)."""

  def filter(self, record: logging.LogRecord) -> bool:
    return not (record.levelno >= logging.ERROR and record.exc_info
                and failures.storage_failure(record.exc_info[1]))


class _AbandonedReadTasks(logging.Filter):
  """Drops asyncio's "... exception was never retrieved" for orbax's reads (an abandoned read that failed
  too, reported when its task, or the future gathering several, is collected: a traceback per array), and
  its "Task was destroyed but it is pending" for those still under way at exit. A task's line names the
  coroutine's file; a gathering future's names none, so its exception's traceback is read too; a future
  tensorstore itself failed has no traceback: its status-code message tells."""

  def filter(self, record):
    message = record.getMessage()
    if message.startswith(library_texts.DESTROYED_PENDING):  # one cut off before it failed
      return not library_texts.in_orbax(message)
    if library_texts.NEVER_RETRIEVED not in message:
      return True
    error = record.exc_info[1] if record.exc_info else None
    return not (library_texts.in_orbax(message) or _raised_in_orbax(error) or _tensorstore_status(error))


def _tensorstore_status(error) -> bool:
  """Whether `error` is one tensorstore set on a future from its C++ code (no Python frame, a status-code
  message): a read orbax started and abandoned, where nothing else in a process awaits tensorstore futures
  without their results."""
  return error is not None and error.__traceback__ is None and library_texts.status_code(error) is not None


def _raised_in_orbax(error) -> bool:
  """Whether `error`, or an error it was raised from, passed through orbax's code."""
  return any(library_texts.in_orbax(frame.filename)
             for e in failures.chain(error) for frame in traceback.extract_tb(e.__traceback__))


def _add_once(logger: logging.Logger, kind) -> None:
  if not any(isinstance(f, kind) for f in logger.filters):
    logger.addFilter(kind())


def quiet_library_reports() -> None:
  """Installs this module's filters (absl's logger: orbax's reports; gcsfs's and fsspec's, whose records reach
  the root's handler, absl's, without absl's) and quiet_abandoned_reads, once per process. Each filter drops
  only its reports; every other report passes."""
  absl_log = logging.getLogger("absl")
  for quiet in (_DiskFullIsReported, _StorageFailureIsReported):
    _add_once(absl_log, quiet)
  for name in ("gcsfs", "fsspec"):
    _add_once(logging.getLogger(name), _StorageFailureIsReported)
  sys.unraisablehook = quiet_abandoned_reads(sys.unraisablehook)


def quiet_abandoned_reads(hook):
  """`hook` (sys.unraisablehook), less the reports of the reads orbax abandons when a restore fails (a
  damaged step): orbax stops at the first failed read and closes its event loop with the other reads still
  under way, so each of those later reports "Event loop is closed" (from tensorstore's thread) or, at exit,
  an unfinished coroutine: up to hundreds of lines after the one warning line that says what happened.
  Every other report goes to `hook`. Also quiets asyncio's log of those reads that failed in turn (a logging
  filter, installed once). A hook that is already one of these is returned as it is."""
  if getattr(hook, "quiets_abandoned_reads", False):
    return hook
  _add_once(logging.getLogger("asyncio"), _AbandonedReadTasks)

  def quiet(unraisable):
    error, trace = unraisable.exc_value, unraisable.exc_traceback
    closed_loop = (isinstance(error, RuntimeError) and str(error) == library_texts.CLOSED_LOOP
                   and trace is not None
                   and trace.tb_frame.f_code.co_name == "call_soon_threadsafe")  # called from no Python frame
    code = getattr(unraisable.object, "cr_code", None)
    abandoned_read = code is not None and library_texts.in_orbax(code.co_filename)
    if not (closed_loop or abandoned_read):
      hook(unraisable)
  quiet.quiets_abandoned_reads = True
  return quiet
