"""`python -m nerfpod.prepare ...`: the same command as `nerfpod prepare ...`."""
import sys

from nerfpod.prepare import run

if __name__ == "__main__":
  sys.exit(run())
