"""`python -m nerfpod.export KIND ...`: the same command as `nerfpod export KIND ...`."""
from nerfpod.export import run

if __name__ == "__main__":
  run()
