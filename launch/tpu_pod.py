#!/usr/bin/env python3
"""Trains on a Cloud TPU VM pod: compile the job for the pod here first (preflight), create (or reuse) the
pod, copy this project to every worker, set up a supported Python there with the pinned versions, check
that every worker sees its TPU chips, start the same command on all workers, and stream worker 0's log
until the run ends. With --gke, the same job runs as a Kubernetes JobSet on a GKE TPU slice instead.

    python launch/tpu_pod.py --name=nerf-pod --zone=us-central2-b --accelerator-type=v4-32 \
        --workdir=gs://my-bucket/lego -- --config=configs/blender.py:scene=lego

Preflight (launch/preflight.py) compiles the train step for the pod's topology on this machine (it needs
the `tpu` extra here), prints the predicted per-chip memory and time, and refuses a job that does not fit
a chip's HBM; --skip-preflight launches without it. The workers' images are Ubuntu 22.04 (Python 3.10),
which today's JAX no longer supports: each worker gets Python --python (3.11) through uv, in a virtual
environment (~/nerfpod-venv) holding the versions of constraints.txt and the TPU runtime of that JAX.

Everything after `--` goes to `python -m nerfpod.main` on every worker. The workdir must be a gs:// bucket
that every worker can write (orbax, tensorstore and tensorboardX write gs:// themselves); the bucket is
created in the pod's region if it does not exist. On the workers jax.distributed finds its peers by itself.

Multi-slice (--slices=N, N > 1): N slices of --accelerator-type joined by the data-centre network, as one
job (docs/scale.md#multi-slice). On TPU VMs they are one queued resource of N nodes (`gcloud compute tpus
queued-resources create NAME --node-count=N --node-prefix=NAME ...`, the form multi-slice needs), whose nodes
are reached together (`queued-resources scp/ssh --node=all --worker=all`); the TPU service gives every host
the MEGASCALE_* variables JAX reads. With --gke, one Job per slice with those variables set.

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
import re
import shlex
import subprocess
import sys
import tempfile

import gke
import pack
import preflight
from _cli import split_forwarded  # launch/ is on sys.path: these run as scripts

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
from nerfpod.pod import chips  # noqa: E402  (standard library only: the pods' names and sizes)

REMOTE_DIR = "nerfpod"  # under each worker's home
VENV = "~/nerfpod-venv"  # each worker's virtual environment, of Python --python
# The TPU VM software images Google lists for JAX, per generation.
RUNTIME_IMAGES = {"v4": "tpu-ubuntu2204-base", "v5e": "v2-alpha-tpuv5-lite", "v5p": "v2-alpha-tpuv5",
                  "v6e": "v2-alpha-tpuv6e"}
LOG = f"~/{REMOTE_DIR}/run.log"
PID = f"~/{REMOTE_DIR}/run.pid"
STATUS = f"~/{REMOTE_DIR}/run.status"
# nerfpod's exit status after saving a step and stopping early (checkpoint.preempted_exit_code's default).
PREEMPTED_EXIT_CODE = 75


class _Parser(argparse.ArgumentParser):
  """argparse, with a mistake said in one line (no usage block), exit 2."""

  def error(self, message):
    print(f"launch/tpu_pod.py: error: {message} (--help lists the options)", file=sys.stderr, flush=True)
    sys.exit(2)


# A TPU VM's or JobSet's name: an RFC 1035 label (what Compute Engine and Kubernetes both take).
NAME = re.compile(r"[a-z]([-a-z0-9]*[a-z0-9])?")
ZONE = re.compile(r"[a-z]+-[a-z]+[0-9]+-[a-z]")  # e.g. us-central2-b, europe-west4-a
BUCKET = re.compile(r"[a-z0-9][a-z0-9._-]{1,61}[a-z0-9]")
PYTHON = re.compile(r"3\.(\d+)(\.\d+)?")
MIN_PYTHON = (3, 11)  # pyproject.toml's requires-python
# Options that only one way of launching uses: given to the other, they would be ignored without a word.
GKE_ONLY = ("manifest", "image", "max_restarts")
VM_ONLY = ("spot", "version", "skip_setup")


def parse(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
  """(options, nerfpod.main arguments), every value checked: a mistake is refused in one sentence (exit 2)
  before anything runs, including what Compute Engine or Kubernetes would refuse only later."""
  own, forwarded = split_forwarded(argv)
  p = _Parser(description=__doc__.split("\n\n")[0],
              usage="%(prog)s --name=NAME --zone=ZONE --workdir=gs://... [options] -- [nerfpod.main flags]")
  p.add_argument("--name", required=True, help="TPU VM name (created if it does not exist), or the JobSet's "
                                               "with --gke: lowercase letters, digits and hyphens")
  p.add_argument("--zone", required=True, help="e.g. us-central2-b")
  p.add_argument("--project", default="", help="GCP project; default: gcloud's configured one")
  p.add_argument("--accelerator-type", default="v4-32", help="for a new pod, e.g. v4-32, v5litepod-16")
  p.add_argument("--slices", type=int, default=1, help="multi-slice: this many slices of --accelerator-type "
                                                       "joined by the data-centre network (default 1)")
  p.add_argument("--version", default=None, help="for a new pod: the TPU VM software version (default: the "
                                               "image Google lists for the generation, e.g. v2-alpha-tpuv5-lite)")
  p.add_argument("--spot", action="store_true", default=None,
                 help="for a new pod: a Spot VM (cheaper, may be preempted); not with --gke, where the node "
                      "pool decides")
  p.add_argument("--workdir", required=True, help="gs://bucket/path shared by all workers")
  p.add_argument("--skip-setup", action="store_true", default=None,
                 help="do not copy and install the project again")
  p.add_argument("--python", default="3.11", help="the Python version set up on every worker (3.11 or newer)")
  p.add_argument("--skip-preflight", action="store_true", help="launch without compiling the job here first")
  p.add_argument("--gke", action="store_true", help="run as a JobSet on a GKE TPU slice (kubectl's current "
                                                    "cluster) instead of on TPU VMs")
  p.add_argument("--manifest", default=None, help="--gke: where to write the JobSet manifest (default: "
                                                  "NAME-jobset.yaml here)")
  p.add_argument("--image", default=None, help="--gke: the container image (a Python >= 3.11; default "
                                               "python:3.11-slim)")
  p.add_argument("--max-restarts", type=int, default=None, help="--gke: JobSet restarts (each resumes from the "
                                                                "newest checkpoint) before it is declared failed "
                                                                "(default 10)")
  p.add_argument("--dry-run", action="store_true", help="print every command instead of running it")
  args = p.parse_args(own)
  pod = chips.lookup(args.accelerator_type)
  if pod is None:
    p.error(f"--accelerator-type={args.accelerator_type} is not a pod this script knows; known: "
            f"{', '.join(chips.known_names())}")
  if args.slices < 1:
    p.error(f"--slices={args.slices} must be 1 (one slice) or more (slices joined by the data-centre network)")
  if not NAME.fullmatch(args.name) or len(args.name) > 63:
    p.error(f"--name={args.name!r} must be lowercase letters, digits and hyphens, start with a letter, end with a "
            f"letter or digit and have at most 63 characters (Compute Engine and Kubernetes take no other)")
  if not ZONE.fullmatch(args.zone):
    p.error(f"--zone={args.zone} is not a Google Cloud zone (region-zone, e.g. us-central2-b or europe-west4-a)")
  bucket = args.workdir[len("gs://"):].split("/")[0] if args.workdir.startswith("gs://") else ""
  if not bucket:
    p.error(f"--workdir={args.workdir} must be a gs:// path: every worker writes checkpoints into it")
  if not BUCKET.fullmatch(bucket) or ".." in bucket:
    p.error(f"--workdir={args.workdir}: {bucket!r} is not a Cloud Storage bucket name (3-63 lowercase letters, "
            f"digits, dots, hyphens and underscores, starting and ending with a letter or digit)")
  version = PYTHON.fullmatch(args.python)
  if not version or (3, int(version.group(1))) < MIN_PYTHON:
    p.error(f"--python={args.python}: nerfpod needs Python {'.'.join(map(str, MIN_PYTHON))} or newer (e.g. "
            f"--python=3.11 or 3.12)")
  if args.gke:
    given = [f"--{name.replace('_', '-')}" for name in VM_ONLY if getattr(args, name) is not None]
    if given:
      p.error(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} for TPU VMs and would be ignored with --gke "
              f"(a GKE slice's node pool decides Spot and the software; the project is always uploaded); "
              f"leave {'it' if len(given) == 1 else 'them'} out")
    args.image = "python:3.11-slim" if args.image is None else args.image
    args.max_restarts = 10 if args.max_restarts is None else args.max_restarts
    problem = gke.check(args, pod)
    if problem:
      p.error(problem)
  else:
    given = [f"--{name.replace('_', '-')}" for name in GKE_ONLY if getattr(args, name) is not None]
    if given:
      p.error(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} for --gke and would be ignored on TPU VMs; "
              f"add --gke or leave {'it' if len(given) == 1 else 'them'} out")
  args.spot, args.skip_setup = bool(args.spot), bool(args.skip_setup)
  if not args.version:
    args.version = RUNTIME_IMAGES[pod.generation]
  if any(a.startswith(("--workdir", "--coordinator_address", "--num_processes", "--process_id"))
         for a in forwarded):
    p.error("pass --workdir to this script, not after `--`; on TPU the processes find each other by themselves")
  forwarded, problem = check_config(forwarded)
  if problem:
    p.error(problem)
  return args, forwarded


def check_config(forwarded: list[str]) -> tuple[list[str], str | None]:
  """(the nerfpod.main arguments, with an absolute --config inside the project made relative to it, as the
  workers see it), or a problem: no --config, or a config file the workers would not have."""
  configs = [i for i, a in enumerate(forwarded) if a.startswith("--config=")]
  if not configs:
    return forwarded, ("the workers need at least --config=CONFIG after `--` (e.g. -- "
                       "--config=configs/blender.py:scene=lego); nothing after `--` names one")
  index = configs[-1]
  value = forwarded[index][len("--config="):]
  path, colon, arg = value.partition(":")
  full = os.path.normpath(os.path.join(REPO, path))
  if not os.path.isfile(full):
    return forwarded, (f"--config={value}: {full} does not exist (a relative path is from the project folder, "
                       f"{REPO}, where the workers run)")
  relative = os.path.relpath(full, REPO)
  if relative.startswith(".."):
    return forwarded, (f"--config={value} is outside the project ({REPO}); the workers get the project's files "
                       f"only: move it into configs/")
  forwarded = list(forwarded)
  forwarded[index] = f"--config={relative.replace(os.sep, '/')}{colon}{arg}"
  return forwarded, None


def config_file(forwarded: list[str]) -> str:
  """The run's config file, relative to the project (after check_config)."""
  value = next(a for a in reversed(forwarded) if a.startswith("--config="))[len("--config="):]
  return value.partition(":")[0]


def pack_step(tarball: str, forwarded: list[str]) -> tuple[str, list[str]]:
  """The packing step: the project's own files (launch/pack.py) listed next to the tarball, and tar."""
  files = pack.project_files(REPO, extra=(config_file(forwarded),))
  list_path = tarball + ".files"
  pack.write_list(files, list_path)
  return f"pack the project's {len(files)} files (launch/pack.py; not runs/, data or caches)", \
      pack.tar_command(REPO, tarball, list_path)


def _multislice(args) -> bool:
  return getattr(args, "slices", 1) > 1


def _tpu(args, verb: str, *rest: str) -> list[str]:
  """A gcloud TPU command: on the TPU VM (tpu-vm), or on the queued resource of a multi-slice job's slices."""
  kind = "queued-resources" if _multislice(args) else "tpu-vm"
  cmd = ["gcloud", "compute", "tpus", kind, verb, *rest, f"--zone={args.zone}"]
  return cmd + ([f"--project={args.project}"] if args.project else [])


def _on_workers(args, command: str, worker: str = "all") -> list[str]:
  """ssh to every worker (or one) of the pod; multi-slice: of every slice (node) at once, or slice 0's."""
  nodes = [f"--node={'all' if worker == 'all' else '0'}"] if _multislice(args) else []
  return _tpu(args, "ssh", args.name, *nodes, f"--worker={worker}", f"--command={command}")


def create_command(args) -> list[str]:
  """The pod's creation: a TPU VM, or for several slices one queued resource of --slices nodes (NAME-0,
  NAME-1, ...), the form multi-slice needs; the TPU service sets each host's MEGASCALE_* variables."""
  if _multislice(args):
    return _tpu(args, "create", args.name, f"--node-count={args.slices}", f"--node-prefix={args.name}",
                f"--accelerator-type={args.accelerator_type}", f"--runtime-version={args.version}") + (
                    ["--spot"] if args.spot else [])
  return _tpu(args, "create", args.name, f"--accelerator-type={args.accelerator_type}",
              f"--version={args.version}") + (["--spot"] if args.spot else [])


def wait_until_active(args) -> list[str]:
  """A queued resource is granted when capacity allows: wait for ACTIVE (refusing FAILED or SUSPENDED)."""
  state = shlex.join(_tpu(args, "describe", args.name, "--format=value(state.state)"))
  return ["sh", "-c", f'while :; do s=$({state}); case "$s" in ACTIVE) exit 0;; FAILED|SUSPENDED) '
                      f'echo "queued resource {args.name} is $s" >&2; exit 1;; esac; sleep 30; done']


def plan(args, forwarded: list[str], tarball: str) -> list[tuple[str, list[str], bool]]:
  """(what, command, may fail) in order. Commands that may fail only tell what exists already."""
  bucket = "/".join(args.workdir.split("/")[:3])
  region = args.zone.rsplit("-", 1)[0]
  project = [f"--project={args.project}"] if args.project else []
  create = create_command(args)
  train = shlex.join([f"{VENV}/bin/python", "-m", "nerfpod.main", *forwarded, f"--workdir={args.workdir}"])
  train = train.replace(f"'{VENV}/bin/python'", f"{VENV}/bin/python")  # let the worker's shell expand ~
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
  if _multislice(args):
    steps += [(f"wait until its {args.slices} slices are ACTIVE", wait_until_active(args), False)]
  nodes = ["--node=all"] if _multislice(args) else []
  if not args.skip_setup:
    steps += [
        (*pack_step(tarball, forwarded), False),
        ("copy it to every worker", _tpu(args, "scp", tarball, f"{args.name}:~/nerfpod-src.tar.gz",
                                         *nodes, "--worker=all"), False),
        ("unpack it and set up Python " + args.python + " with the pinned versions on every worker",
         _on_workers(args, f"mkdir -p ~/{REMOTE_DIR} && tar -xzf ~/nerfpod-src.tar.gz -C ~/{REMOTE_DIR} && "
                           f"cd ~/{REMOTE_DIR} && {setup_commands(args.python)}"), False),
    ]
  steps += [
      ("check that every worker sees its TPU chips", _on_workers(
          args, f"cd ~/{REMOTE_DIR} && " + device_check(chips.lookup(args.accelerator_type), "python",
                                                        args.slices).replace(
              "python", f"{VENV}/bin/python", 1)), False),
  ]
  steps += [
      ("start the same command on every worker", _on_workers(args, start), False),
      ("stream worker 0's log until the run ends", _on_workers(args, follow, worker="0"), False),
  ]
  return steps


def setup_commands(python: str) -> str:
  """Shell commands (in the unpacked project) that give a worker Python `python` in a virtual environment
  with exactly the versions of constraints.txt, the TPU runtime matched to that JAX (the `tpu` extra) and
  the Cloud Storage clients (the `gcs` extra: gcsfs, through which scenes are read and epath and orbax write
  gs://, and google-cloud-storage, tensorboardX's). The TPU VM images' own Python is
  3.10, which today's JAX does not support: uv (installed for the user with the image's pip) fetches a
  standalone build of `python`."""
  uv = "~/.local/bin/uv"
  return (f"python3 -m pip install -q --user -U uv && {uv} python install {python} && "
          f"{uv} venv -q --allow-existing --python {python} {VENV} && "
          f"{uv} pip install -q --python {VENV}/bin/python -c constraints.txt -e '.[tpu,gcs]'")


def device_check(pod, python: str, slices: int = 1) -> str:
  """The shell command (in the unpacked project) that fails in one sentence unless a host sees its chips (and
  the job all of its slices' chips)."""
  return shlex.join([python, "launch/check_devices.py", f"--pod={pod.name}", f"--chips={pod.num_chips * slices}",
                     f"--per-host={pod.num_chips // pod.num_hosts}"])


def main(argv: list[str]) -> int:
  args, forwarded = parse(argv)
  if not args.skip_preflight:
    code = preflight.run(forwarded, args.accelerator_type, args.dry_run, "launch/tpu_pod.py", args.slices)
    if code:
      return code
  tarball = os.path.join(tempfile.gettempdir(), "nerfpod-src.tar.gz")
  if args.gke:
    pod = chips.lookup(args.accelerator_type)
    return gke.launch(args, forwarded, pack_step(tarball, forwarded), pod, device_check(pod, "python", args.slices))
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
