"""`python -m tools.aot ...`, kept for existing scripts: the pod compile tool, nerfpod.pod.aot (`nerfpod aot`)."""
from nerfpod.pod.aot import run

if __name__ == "__main__":
  run()
