#!/usr/bin/env python3
"""Runs a simulated pod on this machine: N nerfpod processes with M simulated CPU devices each.

    python launch/local.py --num_processes=2 --devices_per_process=4 -- \
        --config=configs/default.py:smoke --workdir=/tmp/pod

Everything after `--` goes to `python -m nerfpod.main` unchanged; the launcher adds
--coordinator_address=127.0.0.1:<free port>, --num_processes and --process_id, and sets JAX_NUM_CPU_DEVICES
and JAX_PLATFORMS=cpu (with --platform=gpu instead: JAX_PLATFORMS=cuda and each process its own GPUs, through
CUDA_VISIBLE_DEVICES). Process 0's output streams here; the others' goes to --log_dir.

SIGTERM, and a first Ctrl-C, reach every process as SIGTERM, which is what a TPU VM gets before
maintenance: the processes agree on a step, checkpoint it and exit with the preempted status (75 unless
--preempted_exit_code says otherwise; it must match the run's checkpoint.preempted_exit_code); the same
command resumes from there. A second Ctrl-C kills them. When one process fails, the others get --grace_s
seconds to stop by themselves (the distributed runtime notices a missing peer) and are then killed. The
launcher exits 0 if all processes did; the preempted status if all stopped at a checkpoint (some may have
finished); else the status of the first that failed (killed by signal N: 128 + N). Standard library only:
it starts fast.
"""
import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time

from _cli import split_forwarded  # launch/ is on sys.path: these run as scripts

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def free_port() -> int:
  """A TCP port nobody listens on right now (the coordinator binds it a moment later)."""
  with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def parse(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
  """(launcher options, nerfpod.main arguments): the two sides of the `--` separator."""
  own, forwarded = split_forwarded(argv)
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                   usage="%(prog)s [options] -- [nerfpod.main flags]")
  parser.add_argument("--num_processes", type=int, default=2, help="processes (simulated hosts) to start")
  parser.add_argument("--devices_per_process", type=int, default=4, help="simulated CPU devices per process")
  parser.add_argument("--port", type=int, default=0, help="coordinator port on 127.0.0.1; 0: pick a free one")
  parser.add_argument("--log_dir", default="", help="where processes 1.. write their output; default: a "
                      "new temporary folder")
  parser.add_argument("--grace_s", type=float, default=30.0, help="seconds the other processes get to "
                      "stop by themselves after one failed, before they are killed")
  parser.add_argument("--platform", choices=("cpu", "gpu"), default="cpu", help="cpu: simulated CPU devices "
                      "(--devices_per_process each); gpu: process i sees the machine's GPUs i*M .. i*M+M-1 "
                      "(M = --devices_per_process), through CUDA_VISIBLE_DEVICES")
  parser.add_argument("--module", default="nerfpod.main", help="Python module each process runs")
  parser.add_argument("--preempted_exit_code", type=int, default=75, help="the processes' exit status after "
                      "stopping at a checkpoint (their checkpoint.preempted_exit_code): not a failure; the "
                      "launcher then exits with it too, so that a scheduler requeues the run")
  args = parser.parse_args(own)
  if args.num_processes < 1 or args.devices_per_process < 1:
    parser.error("--num_processes and --devices_per_process must be at least 1")
  return args, forwarded


def commands(args: argparse.Namespace, forwarded: list[str], port: int) -> list[tuple[list[str], dict]]:
  """(argv, environment) of each process."""
  out = []
  for index in range(args.num_processes):
    if args.platform == "cpu":
      env = dict(os.environ, JAX_NUM_CPU_DEVICES=str(args.devices_per_process), JAX_PLATFORMS="cpu",
                 PYTHONUNBUFFERED="1")
    else:
      first = index * args.devices_per_process
      env = dict(os.environ, JAX_PLATFORMS="cuda", PYTHONUNBUFFERED="1", CUDA_VISIBLE_DEVICES=",".join(
          str(first + i) for i in range(args.devices_per_process)))
      env.pop("JAX_NUM_CPU_DEVICES", None)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [REPO, os.environ.get("PYTHONPATH", "")]))
    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
      env.pop(name, None)  # the flags below say it all; stale variables would only confuse
    argv = [sys.executable, "-m", args.module, *forwarded, f"--coordinator_address=127.0.0.1:{port}",
            f"--num_processes={args.num_processes}", f"--process_id={index}"]
    out.append((argv, env))
  return out


def _die_with_parent() -> None:
  """In a child before exec (Linux): be killed when the launcher dies, so that no process is left over."""
  try:
    import ctypes
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
  except (OSError, AttributeError):
    pass


def exit_status(returncode: int) -> int:
  """A child's return code as a shell would report it (killed by signal N -> 128 + N)."""
  return 128 - returncode if returncode < 0 else returncode


def main(argv: list[str]) -> int:
  args, forwarded = parse(argv)
  port = args.port or free_port()
  log_dir = args.log_dir or tempfile.mkdtemp(prefix="nerfpod-local-")
  os.makedirs(log_dir, exist_ok=True)
  print(f"launch/local.py: {args.num_processes} process(es) x {args.devices_per_process} CPU device(s), "
        f"coordinator 127.0.0.1:{port}, logs of processes 1.. in {log_dir}", file=sys.stderr, flush=True)

  children: list[subprocess.Popen] = []
  logs = []

  interrupts = []

  def forward(signum, _frame):
    """SIGTERM, and a first Ctrl-C, reach every process as SIGTERM (they checkpoint an agreed step and
    exit with the preempted status); a second Ctrl-C kills them."""
    if signum == signal.SIGINT:
      interrupts.append(signum)
      if len(interrupts) == 1:
        print("launch/local.py: stopping at a checkpoint; Ctrl-C again to kill", file=sys.stderr, flush=True)
    kill = len(interrupts) > 1
    for child in children:
      if child.poll() is None:
        child.kill() if kill else child.send_signal(signal.SIGTERM)

  signal.signal(signal.SIGTERM, forward)
  signal.signal(signal.SIGINT, forward)
  try:
    for index, (child_argv, env) in enumerate(commands(args, forwarded, port)):
      if index == 0:
        out = None  # inherits this terminal
      else:
        out = open(os.path.join(log_dir, f"process_{index}.log"), "wb")
        logs.append(out)
      # Own process group: a Ctrl-C in the terminal reaches the children once, through `forward`.
      children.append(subprocess.Popen(child_argv, env=env, cwd=os.getcwd(), stdout=out,
                                       stderr=subprocess.STDOUT if out else None, start_new_session=True,
                                       preexec_fn=_die_with_parent if sys.platform == "linux" else None))
    first_failure = None  # (index, status) of the first process that failed by itself
    deadline = None
    while None in [child.poll() for child in children]:  # a list, so that every child is polled
      failed = [i for i, child in enumerate(children)
                if child.returncode not in (None, 0, args.preempted_exit_code)]
      if failed and first_failure is None:
        first_failure = (failed[0], exit_status(children[failed[0]].returncode))
        deadline = time.monotonic() + args.grace_s
        print(f"launch/local.py: process {first_failure[0]} exited with status {first_failure[1]}; the "
              f"others get {args.grace_s:g} s to stop", file=sys.stderr, flush=True)
      if deadline is not None and time.monotonic() > deadline:
        for child in children:
          if child.poll() is None:
            child.kill()
        break
      time.sleep(0.2)
    for child in children:
      child.wait()
    if first_failure is None:  # they all ended between two polls
      failed = [i for i, child in enumerate(children) if child.returncode not in (0, args.preempted_exit_code)]
      if failed:
        first_failure = (failed[0], exit_status(children[failed[0]].returncode))
  finally:
    for child in children:
      if child.poll() is None:
        child.kill()
        child.wait()
    for log in logs:
      log.close()
  statuses = [exit_status(child.returncode) for child in children]
  if first_failure is None and args.preempted_exit_code in statuses:
    print(f"launch/local.py: stopped at a checkpoint (exit status {args.preempted_exit_code}); the same command "
          f"resumes from there", file=sys.stderr, flush=True)
    return args.preempted_exit_code
  if first_failure is None:
    return 0
  print(f"launch/local.py: exit statuses {statuses}; logs of processes 1.. in {log_dir}", file=sys.stderr,
        flush=True)
  return first_failure[1]


if __name__ == "__main__":
  sys.exit(main(sys.argv[1:]))
