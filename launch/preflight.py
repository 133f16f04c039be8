"""Preflight: compile the job for the pod it is launched on, here, before any pod is created or used.

Runs `python -m nerfpod.pod.aot` (the pod compile tool, `nerfpod aot`: the run's real programs, the train
step, the evaluation renderer and the orbit renderer, each over the whole pod, compiled for the pod's TPU
topology on this machine) with the job's --config and overrides, prints the predicted per-chip memory and
time, and refuses a job with a program the TPU compiler refuses (the tool's one sentence) or one that does
not fit in a chip's HBM, with the figures and the ways to make it fit.
Standard library only (the tool runs in its own process, with this interpreter).
"""
import json
import os
import shlex
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Every program a run compiles (train, evaluate, render the orbit): one the pod refuses would stop the run.
PROGRAMS = ("step", "eval", "orbit")
_CHUNKS = {"eval": ("the evaluation renderer", "eval.chunk"), "orbit": ("the orbit renderer", "orbit.chunk")}


def config_args(forwarded: list[str]) -> list[str]:
  """The nerfpod.main arguments that shape the program: --config and its overrides."""
  return [a for a in forwarded if a.startswith("--config")]


def command(forwarded: list[str], accelerator_type: str, json_path: str, slices: int = 1) -> list[str]:
  return [sys.executable, "-m", "nerfpod.pod.aot", *config_args(forwarded), f"--topology={accelerator_type}",
          *([f"--slices={slices}"] if slices > 1 else []), f"--what={','.join(PROGRAMS)}", f"--json={json_path}"]


def _gib(n: float) -> str:
  return f"{n / 2**30:.2f} GiB"


def _duration(seconds: float) -> str:
  if seconds >= 3600:
    return f"{seconds / 3600:.1f} h"
  if seconds >= 60:
    return f"{seconds / 60:.1f} min"
  return f"{seconds:.3g} s"


def summary(report: dict) -> str:
  step = report["step"]
  memory = step["memory"]
  slices = report.get("slices", 1)
  pod = report["pod"] if slices == 1 else f"{slices} x {report['pod']}"
  if step["seconds"] is None:  # XLA refused it: more temporaries than a chip's HBM
    return (f"{pod} ({report['chips']} chips, {report['hosts']} hosts): per chip the step needs "
            f"{_gib(memory['peak_bytes'])} of temporaries, XLA has {_gib(memory['xla_available_bytes'])} of a chip's "
            f"{_gib(report['chip']['hbm_bytes'])} HBM for them")
  return (f"{pod} ({report['chips']} chips, {report['hosts']} hosts): per chip {_gib(memory['peak_bytes'])} "
          f"of {_gib(report['chip']['hbm_bytes'])} HBM (arguments {_gib(memory['argument_bytes'])}, temporaries "
          f"{_gib(memory['temp_bytes'])}); step {_duration(step['seconds'])}, {step['rays_per_s']:,.0f} rays/s; "
          f"{report['num_steps']} steps in about {_duration(step['run_seconds'])} (XLA cost-model estimate, "
          f"not a measurement)")


def refusal(report: dict) -> str | None:
  """One sentence when a program does not fit a chip's HBM, with the figures and the fixes; else None."""
  step = report["step"]
  memory = step["memory"]
  if step["fits_hbm"]:
    for name, (what, field) in _CHUNKS.items():
      program = report.get(name)
      if program is not None and not program["fits_hbm"]:
        return (f"{what} needs {_gib(program['memory']['peak_bytes'])} per chip on {report['pod']} for "
                f"{program['rays']:,} rays a call but a chip has {_gib(report['chip']['hbm_bytes'])} of HBM; "
                f"use a smaller --config.{field}.")
    return None
  return (f"the train step needs {_gib(memory['peak_bytes'])} per chip on {report['pod']} (temporaries "
          f"{_gib(memory['temp_bytes'])}, arguments {_gib(memory['argument_bytes'])}) but a chip has "
          f"{_gib(report['chip']['hbm_bytes'])} of HBM; split each chip's {report['rays_per_chip']} rays into "
          f"more micro-batches (--config.train.microbatches={2 * max(1, report['microbatches'])} or more), use a smaller "
          f"--config.train.batch_size, or a pod with more chips.")


def run(forwarded: list[str], accelerator_type: str, dry_run: bool, prefix: str, slices: int = 1) -> int:
  """Runs the preflight (for `slices` slices of the pod: multi-slice where more than one); returns 0 when the
  job may go on, else the exit status to stop with."""
  with tempfile.TemporaryDirectory() as tmp:
    path = os.path.join(tmp, "preflight.json")
    cmd = command(forwarded, accelerator_type, path, slices)
    target = accelerator_type if slices == 1 else f"{slices} slices of {accelerator_type}"
    print(f"{'# ' if dry_run else ''}{prefix}: preflight: compiling the step for {target} here\n"
          f"{'' if dry_run else '  '}{shlex.join(cmd)}", flush=True)
    result = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if result.returncode != 0 or not os.path.exists(path):
      errors = [line for line in result.stderr.splitlines() if "error:" in line] or result.stderr.splitlines()[-3:]
      print(f"{prefix}: preflight failed: {' '.join(errors) or 'exit status ' + str(result.returncode)} "
            f"(--skip-preflight launches without it).", file=sys.stderr, flush=True)
      return 2
    with open(path) as f:
      report = json.load(f)
  print(f"{prefix}: preflight: {summary(report)}", flush=True)
  problem = refusal(report)
  if problem:
    print(f"{prefix}: error: {problem}", file=sys.stderr, flush=True)
    return 2
  return 0
