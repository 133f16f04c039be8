#!/usr/bin/env python3
"""Trains on a Cloud TPU VM pod: create (or reuse) the pod, copy this project to every worker, install it,
start the same command on all workers, and stream worker 0's log until the run ends.

    python launch/tpu_pod.py --name=nerf-pod --zone=us-central2-b --accelerator-type=v4-32 \
        --workdir=gs://my-bucket/lego -- --config=configs/blender.py:scene=lego

Everything after `--` goes to `python -m nerfpod.main` on every worker. The workdir must be a gs:// bucket
that every worker can write (orbax, tensorstore and tensorboardX write gs:// themselves); the bucket is
created in the pod's region if it does not exist. On the workers jax.distributed finds its peers by itself.

The run is started detached (it survives a dropped connection); following the log again, or stopping the
run, is one gcloud command each, printed at the start. Maintenance or preemption sends every worker
SIGTERM: nerfpod saves a checkpoint at a step all workers agree on and exits with status 75 (EX_TEMPFAIL;
the run's checkpoint.preempted_exit_code), as does this script, so that a scheduler requeues it; run this
script again with the same arguments and it resumes from that checkpoint. 0 means the run finished.

`--dry-run` prints every command instead of running it. Needs the gcloud CLI, logged in, and for a new pod
the TPU quota; standard library only.
"""
import argparse
import os
import shlex
import subprocess
import sys
import tempfile

from _cli import split_forwarded  # launch/ is on sys.path: these run as scripts

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REMOTE_DIR = "nerfpod"  # under each worker's home
LOG = f"~/{REMOTE_DIR}/run.log"
PID = f"~/{REMOTE_DIR}/run.pid"
STATUS = f"~/{REMOTE_DIR}/run.status"
# nerfpod's exit status after saving a step and stopping early (checkpoint.preempted_exit_code's default).
PREEMPTED_EXIT_CODE = 75


def parse(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
  own, forwarded = split_forwarded(argv)
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                              usage="%(prog)s --name=NAME --zone=ZONE --workdir=gs://... [options] -- "
                                    "[nerfpod.main flags]")
  p.add_argument("--name", required=True, help="TPU VM name (created if it does not exist)")
  p.add_argument("--zone", required=True, help="e.g. us-central2-b")
  p.add_argument("--project", default="", help="GCP project; default: gcloud's configured one")
  p.add_argument("--accelerator-type", default="v4-32", help="for a new pod, e.g. v4-32, v5litepod-16")
  p.add_argument("--version", default="tpu-ubuntu2204-base", help="for a new pod: the TPU VM software version")
  p.add_argument("--spot", action="store_true", help="for a new pod: a Spot VM (cheaper, may be preempted)")
  p.add_argument("--workdir", required=True, help="gs://bucket/path shared by all workers")
  p.add_argument("--skip-setup", action="store_true", help="do not copy and install the project again")
  p.add_argument("--jax-spec", default="jax[tpu]", help="pip requirement for JAX with its TPU runtime")
  p.add_argument("--dry-run", action="store_true", help="print every command instead of running it")
  args = p.parse_args(own)
  if not args.workdir.startswith("gs://") or len(args.workdir) <= len("gs://"):
    p.error(f"--workdir={args.workdir} must be a gs:// path: every worker writes checkpoints into it")
  if any(a.startswith(("--workdir", "--coordinator_address", "--num_processes", "--process_id"))
         for a in forwarded):
    p.error("pass --workdir to this script, not after `--`; on TPU the processes find each other by themselves")
  return args, forwarded


def _tpu(args, verb: str, *rest: str) -> list[str]:
  cmd = ["gcloud", "compute", "tpus", "tpu-vm", verb, *rest, f"--zone={args.zone}"]
  return cmd + ([f"--project={args.project}"] if args.project else [])


def _on_workers(args, command: str, worker: str = "all") -> list[str]:
  return _tpu(args, "ssh", args.name, f"--worker={worker}", f"--command={command}")


def plan(args, forwarded: list[str], tarball: str) -> list[tuple[str, list[str], bool]]:
  """(what, command, may fail) in order. Commands that may fail only tell what exists already."""
  bucket = "/".join(args.workdir.split("/")[:3])
  region = args.zone.rsplit("-", 1)[0]
  project = [f"--project={args.project}"] if args.project else []
  create = _tpu(args, "create", args.name, f"--accelerator-type={args.accelerator_type}",
                f"--version={args.version}") + (["--spot"] if args.spot else [])
  train = shlex.join(["python3", "-m", "nerfpod.main", *forwarded, f"--workdir={args.workdir}"])
  # Detached, so that it outlives this ssh session; its exit status is kept for the log follower.
  detached = shlex.quote(f"{train} > {LOG} 2>&1; echo $? > {STATUS}")
  start = (f"cd ~/{REMOTE_DIR} && rm -f {STATUS} && "
           f"(nohup sh -c {detached} > /dev/null 2>&1 & echo $! > {PID})")
  follow = (f"tail --pid=$(cat {PID}) -n +1 -F {LOG} 2>/dev/null; "
            f"exit $(cat {STATUS} 2>/dev/null || echo 1)")
  steps = [
      ("is the bucket there?", ["gcloud", "storage", "buckets", "describe", bucket, *project], True),
      ("if not, create it next to the pod", ["gcloud", "storage", "buckets", "create", bucket,
                                             f"--location={region}", *project], False),
      ("is the pod there?", _tpu(args, "describe", args.name), True),
      ("if not, create it", create, False),
  ]
  if not args.skip_setup:
    steps += [
        ("pack the project", ["tar", "-czf", tarball, "--exclude=.git", "--exclude=__pycache__",
                              "-C", REPO, "."], False),
        ("copy it to every worker", _tpu(args, "scp", tarball, f"{args.name}:~/nerfpod-src.tar.gz",
                                         "--worker=all"), False),
        ("unpack and install on every worker", _on_workers(
            args, f"mkdir -p ~/{REMOTE_DIR} && tar -xzf ~/nerfpod-src.tar.gz -C ~/{REMOTE_DIR} && "
                  f"cd ~/{REMOTE_DIR} && python3 -m pip install -q -U '{args.jax_spec}' -e . gcsfs "
                  f"google-cloud-storage"), False),
    ]
  steps += [
      ("start the same command on every worker", _on_workers(args, start), False),
      ("stream worker 0's log until the run ends", _on_workers(args, follow, worker="0"), False),
  ]
  return steps


def main(argv: list[str]) -> int:
  args, forwarded = parse(argv)
  tarball = os.path.join(tempfile.gettempdir(), "nerfpod-src.tar.gz")
  steps = plan(args, forwarded, tarball)
  print(f"launch/tpu_pod.py: follow the log again: "
        f"{shlex.join(_on_workers(args, f'tail -n 50 -F {LOG}', worker='0'))}", flush=True)
  print(f"launch/tpu_pod.py: stop the run (it saves a checkpoint first): "
        f"{shlex.join(_on_workers(args, f'kill -TERM $(cat {PID})'))}", flush=True)
  skip_next = False
  for what, cmd, probe in steps:
    if args.dry_run:
      print(f"# {what}\n{shlex.join(cmd)}", flush=True)
      continue
    if skip_next:
      skip_next = False
      continue
    print(f"launch/tpu_pod.py: {what}\n  {shlex.join(cmd)}", flush=True)
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL} if probe else {}
    code = subprocess.call(cmd, **quiet)
    if probe:
      skip_next = code == 0  # it exists: skip its creation
    elif code == PREEMPTED_EXIT_CODE and what.startswith("stream"):
      print(f"launch/tpu_pod.py: the run stopped at a checkpoint (preempted, exit status {code}); run this "
            f"script again with the same arguments to resume", file=sys.stderr, flush=True)
      return code
    elif code != 0:
      print(f"launch/tpu_pod.py: failed ({what}) with exit status {code}", file=sys.stderr, flush=True)
      return code
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv[1:]))
