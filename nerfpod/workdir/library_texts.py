"""The words of other libraries' reports that nerfpod still reads, in one place.

Where a library tells its reports apart by an error number, an exception type, a logger or a setting, nerfpod
uses that (nerfpod.workdir.failures, nerfpod.workdir.quiet); what is left has no such handle, and is matched
here by its text, each with the library that words it and the version it was taken from.
tests/test_library_texts.py makes each library say each one and checks that the pattern here still matches it,
so that a version that words it otherwise fails there rather than letting a report through unseen.

    orbax        the temporary folder of a save under way (is_cut_off_save) and its files (in_orbax)
                 (orbax-checkpoint 0.12.8)
    tensorstore  an error raised in its C++ code: its message begins with an absl status code (status_code) and
                 ends with the OS's error number, [os_error_code='N'] (os_error_number) (tensorstore 0.1.86)
    asyncio      a failed task that nobody awaited (NEVER_RETRIEVED), one still pending when collected
                 (DESTROYED_PENDING), a call into a closed event loop (CLOSED_LOOP) (CPython 3.11)
"""
import os
import re

# orbax's temporary folder of a save under way: STEP.orbax-checkpoint-tmp, or with -TIMESTAMP after it.
_CUT_OFF_SAVE = re.compile(r"\.orbax-checkpoint-tmp(-\d+)?$")

# The absl status codes, one of which begins the message of an error raised in tensorstore's C++ code.
STATUS_CODES = ("CANCELLED", "UNKNOWN", "INVALID_ARGUMENT", "DEADLINE_EXCEEDED", "NOT_FOUND", "ALREADY_EXISTS",
                "PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION", "ABORTED", "OUT_OF_RANGE",
                "UNIMPLEMENTED", "INTERNAL", "UNAVAILABLE", "DATA_LOSS", "UNAUTHENTICATED")
_OS_ERROR_CODE = re.compile(r"os_error_code='(\d+)'")

# asyncio's log lines (its logger "asyncio", level ERROR).
NEVER_RETRIEVED = "exception was never retrieved"  # "Task exception ...", "Future exception ...", ...
DESTROYED_PENDING = "Task was destroyed but it is pending"
CLOSED_LOOP = "Event loop is closed"  # a RuntimeError's whole message


def is_cut_off_save(name: str) -> bool:
  """Whether `name` is the name of orbax's temporary folder of a save that has not finished."""
  return _CUT_OFF_SAVE.search(name) is not None


def in_orbax(text: str) -> bool:
  """Whether `text` (a file name, or a report naming one) names a file of orbax's."""
  return f"{os.sep}orbax{os.sep}" in text


def status_code(error: BaseException | None) -> str | None:
  """The absl status code that begins `error`'s message (one of STATUS_CODES: an error of tensorstore's), or
  None."""
  if error is None:
    return None
  code = str(error).split(":", 1)[0]
  return code if code in STATUS_CODES else None


def os_error_number(text: str) -> int | None:
  """The OS's error number (errno) that an error of tensorstore's carries in its message, or None."""
  found = _OS_ERROR_CODE.search(text)
  return int(found.group(1)) if found else None
