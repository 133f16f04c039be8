"""How a sink's trouble is said: one warning line on stderr (warn), an error in one line (reason). A sink that
fails warns once and the run goes on."""
import sys


def warn(message: str) -> None:
  print(f"nerfpod: warning: {message}", file=sys.stderr, flush=True)


def reason(error: Exception) -> str:
  return " ".join(str(error).split())[:300] or type(error).__name__
