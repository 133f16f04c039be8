"""A user's mistake: the one exception type for it, and the one way every command ends on it."""
import sys
from typing import NoReturn


class UserError(Exception):
  """Bad input (data, config, workdir). The message names the problem and the fix."""


def fail(problem: "UserError | str", program: str = "nerfpod", code: int = 2) -> NoReturn:
  """Ends a command on a user's mistake: each of its messages (a ConfigError has several) as one line of
  stderr, `PROGRAM: error: MESSAGE`, whitespace folded, no traceback; then exit `code` (2: bad input)."""
  for message in getattr(problem, "messages", None) or [str(problem)]:
    print(f"{program}: error: {' '.join(str(message).split())}", file=sys.stderr, flush=True)
  sys.exit(code)
