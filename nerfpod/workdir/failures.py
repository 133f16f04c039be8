"""What a failed read or write of a workdir was: a full disk (disk_full), a storage client's failure to reach or
hear from its service (storage_failure), and why, in one line (reason).

Told by error numbers and exception types; what only a message tells (tensorstore's errors) is read through
nerfpod.workdir.library_texts.
"""
import errno
import os
import sys

from nerfpod.workdir import library_texts

_DISK_FULL = (errno.ENOSPC, errno.EDQUOT)  # the disk, or the user's quota
# How the OS words them, in an error's message or a log line that carries no error.
_DISK_FULL_WORDS = tuple(os.strerror(number) for number in _DISK_FULL)

# tensorstore's status codes of a request that did not get through.
_UNREACHED_CODES = ("UNAVAILABLE", "DEADLINE_EXCEEDED", "ABORTED", "UNAUTHENTICATED", "PERMISSION_DENIED")


def chain(error: BaseException | None):
  """`error` and the errors it was raised from (its causes and contexts), each once."""
  seen = set()
  while error is not None and id(error) not in seen:
    seen.add(id(error))
    yield error
    error = error.__cause__ or error.__context__


def says_disk_full(text: str) -> bool:
  """Whether a message (an error's, or a log line's) says the disk (or the user's quota) is full."""
  return library_texts.os_error_number(text) in _DISK_FULL or any(words in text for words in _DISK_FULL_WORDS)


def disk_full(error: BaseException | None) -> bool:
  """Whether `error`, or an error it was raised from, says the disk (or the user's quota) is full: an OSError's
  errno, or the OS's error number in a tensorstore error."""
  return any((isinstance(e, OSError) and e.errno in _DISK_FULL) or says_disk_full(str(e)) for e in chain(error))


def _storage_error_types() -> tuple:
  """The exception types of the storage clients' failures to reach or hear from their services."""
  kinds = [ConnectionError, TimeoutError]
  for module, names in (("aiohttp", ("ClientError",)), ("requests.exceptions", ("RequestException",)),
                        ("google.api_core.exceptions", ("GoogleAPIError",)),
                        ("google.auth.exceptions", ("TransportError", "RefreshError")),
                        ("gcsfs.retry", ("HttpError",)), ("fsspec.exceptions", ("FSTimeoutError",))):
    found = sys.modules.get(module)  # (a client not imported raised nothing)
    kinds += [getattr(found, name) for name in names if found is not None and hasattr(found, name)]
  return tuple(kinds)


def storage_failure(error: BaseException | None) -> bool:
  """Whether `error`, or an error it was raised from, is a storage client's failure to reach or hear from its
  service (a connection refused, reset or timed out, an HTTP error, a tensorstore request given up)."""
  kinds = _storage_error_types()
  return any(isinstance(e, kinds) or (isinstance(e, ValueError)
                                      and library_texts.status_code(e) in _UNREACHED_CODES)
             for e in chain(error))


def reason(error: BaseException) -> str:
  """Why a read failed, in one line: the innermost cause's message (orbax wraps tensorstore's error, which
  names the file and what is wrong with it, in one that names neither)."""
  while error.__cause__ is not None:
    error = error.__cause__
  return " ".join(str(error).split())[:300] or type(error).__name__
