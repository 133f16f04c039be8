"""The same job as a Kubernetes JobSet on a GKE TPU slice: `launch/tpu_pod.py --gke ...`.

Google steers new TPU work to GKE (the Cloud TPU VM API is no longer developed and does not serve TPU7x).
This writes a JobSet (jobset.x-k8s.io/v1alpha2; the JobSet controller must be installed in the cluster,
as GKE's TPU guides do) of one Job per slice (one replicated job with --slices replicas) whose Indexed
pods are the slice's hosts, one process per host:

- each pod lands on a node of one TPU node pool of the pod's type and topology
  (`cloud.google.com/gke-tpu-accelerator`, `cloud.google.com/gke-tpu-topology`, the
  `alpha.jobset.sigs.k8s.io/exclusive-topology` annotation) and asks for that host's chips
  (`google.com/tpu`);
- it fetches this project from the workdir's bucket (uploaded there first), installs it with the pinned
  versions and the `tpu` extra into the image's Python (>= 3.11), checks that it sees its TPU chips, and
  runs the same `python -m nerfpod.main ... --workdir=gs://...` as on TPU VMs; jax.distributed finds the
  peers from the variables GKE sets on TPU pods;
- multi-slice (--slices > 1): each Job is one slice (its own node pool: the exclusive-topology annotation
  puts each Job on a node pool of its own), and every pod gets the variables multi-slice JAX and libtpu read
  (jax/_src/clusters/cloud_tpu_cluster.py): MEGASCALE_NUM_SLICES, MEGASCALE_SLICE_ID (the Job's index, from
  JobSet's `jobset.sigs.k8s.io/job-index` annotation) and MEGASCALE_COORDINATOR_ADDRESS (the first host of
  slice 0, by the DNS name JobSet gives it); the process id is then the host's index in its slice plus the
  slice's index times the hosts per slice;
- preemption as on TPU VMs: the pod gets SIGTERM and `terminationGracePeriodSeconds` to save a checkpoint;
  a failed or lost host restarts the whole JobSet (up to --max-restarts), which resumes from the newest
  checkpoint. Running the script again resumes the same way.

Standard library only: the manifest is written as YAML by the small emitter below.
"""
import json
import os
import shlex
import subprocess
import sys

# GKE's node labels of each TPU generation's slices.
ACCELERATOR_LABELS = {"v4": "tpu-v4-podslice", "v5e": "tpu-v5-lite-podslice", "v5p": "tpu-v5p-slice",
                      "v6e": "tpu-v6e-slice"}
GRACE_SECONDS = 300  # after SIGTERM: long enough for every host to agree on a step and save it
REPLICATED_JOB = "workers"  # the JobSet's one replicated job: its pods are NAME-workers-<slice>-<host>-<5 letters>
JOB_INDEX = "metadata.annotations['jobset.sigs.k8s.io/job-index']"  # the Job's index among the replicas
MAX_RESTARTS = 2**31 - 1  # failurePolicy.maxRestarts is an int32


def pod_name_length(name: str, pod, slices: int = 1) -> int:
  """The length of the longest pod name the JobSet controller makes for `pod`'s hosts: the JobSet webhook
  refuses a JobSet whose `NAME-workers-<job>-<host>` plus a 5-letter suffix exceeds a DNS label (63)."""
  return len(f"{name}-{REPLICATED_JOB}-{slices - 1}-{pod.num_hosts - 1}-abcde")


def coordinator_host(name: str) -> str:
  """The DNS name of slice 0's first host (with network.enableDNSHostnames: POD_HOSTNAME.JOBSET_NAME)."""
  return f"{name}-{REPLICATED_JOB}-0-0.{name}"


def check(args, pod) -> str | None:
  """What Kubernetes would refuse in the manifest (or what cannot be written), in one sentence; else None."""
  slices = getattr(args, "slices", 1)
  if pod_name_length(args.name, pod, slices) > 63:
    longest = 63 - pod_name_length("", pod, slices)
    hosts = f"{pod.num_hosts} host(s)" if slices == 1 else f"{slices} slices of {pod.num_hosts} host(s)"
    return (f"--name={args.name} is too long for a JobSet of {hosts}: the names of its pods "
            f"({args.name}-{REPLICATED_JOB}-{slices - 1}-{pod.num_hosts - 1}-xxxxx) must fit in 63 characters; use "
            f"at most {longest} characters")
  if not 0 <= args.max_restarts <= MAX_RESTARTS:
    return f"--max-restarts={args.max_restarts} must be 0 or more (each restart resumes from the newest checkpoint)"
  if not args.image or any(c.isspace() for c in args.image):
    return f"--image={args.image!r} must name a container image, e.g. python:3.11-slim"
  path = args.manifest or f"{args.name}-jobset.yaml"
  if os.path.isdir(path):
    return f"--manifest={path} is a folder; name the file to write, e.g. {os.path.join(path, args.name + '-jobset.yaml')}"
  folder = os.path.dirname(os.path.abspath(path))
  if not os.path.isdir(folder):
    return f"--manifest={path}: its folder {folder} does not exist; create it or name another file"
  if not os.access(folder, os.W_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
    return f"--manifest={path} cannot be written here; name another file"
  return None


def _yaml_scalar(value) -> str:
  if isinstance(value, bool):
    return "true" if value else "false"
  if isinstance(value, (int, float)):
    return str(value)
  return json.dumps(str(value))  # a JSON string is a valid YAML scalar, quoted and escaped


def to_yaml(value, indent: int = 0) -> str:
  """Dicts, lists and scalars as block YAML."""
  pad = " " * indent
  if isinstance(value, dict):
    if not value:
      return pad + "{}\n"
    out = ""
    for key, item in value.items():
      if isinstance(item, (dict, list)) and item:
        out += f"{pad}{key}:\n{to_yaml(item, indent + 2)}"
      else:
        out += f"{pad}{key}: {to_yaml(item).strip() if isinstance(item, (dict, list)) else _yaml_scalar(item)}\n"
    return out
  if isinstance(value, list):
    if not value:
      return pad + "[]\n"
    out = ""
    for item in value:
      text = to_yaml(item, indent + 2) if isinstance(item, (dict, list)) else pad + "  " + _yaml_scalar(item) + "\n"
      out += f"{pad}- {text.lstrip()}"
    return out
  return pad + _yaml_scalar(value) + "\n"


def source_url(workdir: str) -> str:
  """Where the project's tarball goes for the pods to fetch."""
  return workdir.rstrip("/") + "/_launch/nerfpod-src.tar.gz"


def container_script(workdir: str, forwarded: list[str], device_check: str) -> str:
  """What each pod runs: fetch and install the project, check its chips, then the job itself."""
  fetch = ("from google.cloud import storage; storage.Blob.from_string(" + json.dumps(source_url(workdir))
           + ", client=storage.Client()).download_to_filename('/tmp/nerfpod-src.tar.gz')")
  train = shlex.join(["python", "-m", "nerfpod.main", *forwarded, f"--workdir={workdir}"])
  return "\n".join([
      "set -e",
      "pip install -q google-cloud-storage",
      f"python -c {shlex.quote(fetch)}",
      "mkdir -p /nerfpod && tar -xzf /tmp/nerfpod-src.tar.gz -C /nerfpod && cd /nerfpod",
      "pip install -q -c constraints.txt -e '.[tpu,gcs]'",
      device_check,
      f"exec {train}",
  ])


def megascale_env(name: str, slices: int) -> list[dict]:
  """The variables multi-slice JAX and libtpu read on each host: the slice count, this host's slice (its
  Job's index) and where slice 0's first host is."""
  return [{"name": "MEGASCALE_NUM_SLICES", "value": str(slices)},
          {"name": "MEGASCALE_SLICE_ID", "valueFrom": {"fieldRef": {"fieldPath": JOB_INDEX}}},
          {"name": "MEGASCALE_COORDINATOR_ADDRESS", "value": coordinator_host(name)}]


def manifest(name: str, pod, image: str, script: str, max_restarts: int, slices: int = 1) -> dict:
  """The JobSet of `slices` slices of `pod` (a nerfpod.pod.chips.Pod) running `script` on each of their
  hosts: one Job per slice, each on a node pool of its own."""
  hosts = pod.num_hosts
  container = {
      "name": "nerfpod",
      "image": image,
      "command": ["bash", "-c", script],
      "ports": [{"containerPort": 8471}, {"containerPort": 8080}],
      "resources": {"limits": {"google.com/tpu": pod.num_chips // hosts}},
  }
  if slices > 1:
    container["env"] = megascale_env(name, slices)
  return {
      "apiVersion": "jobset.x-k8s.io/v1alpha2",
      "kind": "JobSet",
      "metadata": {"name": name,
                   "annotations": {"alpha.jobset.sigs.k8s.io/exclusive-topology": "cloud.google.com/gke-nodepool"}},
      "spec": {
          "failurePolicy": {"maxRestarts": max_restarts},
          "network": {"enableDNSHostnames": True},
          "replicatedJobs": [{
              "name": REPLICATED_JOB,
              "replicas": slices,
              "template": {"spec": {
                  "parallelism": hosts,
                  "completions": hosts,
                  "completionMode": "Indexed",
                  "backoffLimit": 0,
                  "template": {"spec": {
                      "restartPolicy": "Never",
                      "terminationGracePeriodSeconds": GRACE_SECONDS,
                      "nodeSelector": {"cloud.google.com/gke-tpu-accelerator": ACCELERATOR_LABELS[pod.generation],
                                       "cloud.google.com/gke-tpu-topology": pod.topology},
                      "containers": [container],
                  }},
              }},
          }],
      },
  }


def launch(args, forwarded: list[str], pack_step: tuple[str, list[str]], pod, device_check: str) -> int:
  """Packs and uploads the project, writes the manifest and applies it (or, with --dry-run, prints all).
  `pack_step`: (what, tar command) packing the project's own files (launch/pack.py); `device_check`: the
  command that fails in one sentence unless a host sees its TPU chips. The arguments were checked
  (tpu_pod.parse, check above)."""
  path = args.manifest or f"{args.name}-jobset.yaml"
  script = container_script(args.workdir, forwarded, device_check)
  with open(path, "w") as f:
    f.write(to_yaml(manifest(args.name, pod, args.image, script, args.max_restarts, args.slices)))
  tarball = pack_step[1][2]
  project = [f"--project={args.project}"] if args.project else []
  steps = [
      pack_step,
      ("upload it next to the workdir", ["gcloud", "storage", "cp", tarball, source_url(args.workdir), *project]),
      ("start the JobSet on the cluster", ["kubectl", "apply", "-f", path]),
  ]
  print(f"launch/tpu_pod.py: wrote the JobSet manifest {path}; follow the logs with: "
        f"kubectl logs -f -l jobset.sigs.k8s.io/jobset-name={args.name} "
        f"--max-log-requests={pod.num_hosts * args.slices}",
        flush=True)
  for what, cmd in steps:
    if args.dry_run:
      print(f"# {what}\n{shlex.join(cmd)}", flush=True)
      continue
    print(f"launch/tpu_pod.py: {what}\n  {shlex.join(cmd)}", flush=True)
    code = subprocess.call(cmd)
    if code != 0:
      print(f"launch/tpu_pod.py: failed ({what}) with exit status {code}", file=sys.stderr, flush=True)
      return code
  return 0
