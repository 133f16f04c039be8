"""launch/: the local N-process launcher (with stand-in processes, no JAX) and the TPU pod script."""
import os
import re
import shlex
import signal
import subprocess
import sys

import pytest

import procs
from procs import REPO

LOCAL = REPO / "launch" / "local.py"
TPU_POD = REPO / "launch" / "tpu_pod.py"


def _launch_stand_ins(tmp_path, actions: str, num_processes: int, devices_per_process: int, *launcher_flags):
  """launch/local.py starting stand-in processes that do `actions` (procs.Run's stand_in), no JAX."""
  return procs.Run(tmp_path / "w", num_processes=num_processes, devices_per_process=devices_per_process,
                   config="x.py", via_launcher=True, launcher_flags=launcher_flags, stand_in=actions,
                   log_dir=tmp_path / "logs")


def test_local_launcher_starts_every_process_with_its_id_and_stops_all_when_one_fails(tmp_path):
  with _launch_stand_ins(tmp_path, "wait,exit:3,wait", 3, 2, "--grace_s=1") as run:
    codes = run.wait(timeout=30)
  out = run.output(0)
  assert codes == [3], out  # the status of the process that failed, not of those stopped after it
  assert "process 1 exited with status 3" in out
  first = next(line for line in out.splitlines() if line.startswith("stand-in process 0 ready"))
  assert "JAX_NUM_CPU_DEVICES=2" in first
  assert f"--config=x.py --workdir={tmp_path / 'w'} --coordinator_address=127.0.0.1:" in first
  assert "--num_processes=3 --process_id=0" in first
  # Processes 1.. write to the log folder, not to the launcher's output.
  assert "stand-in process 1" not in out
  assert "--process_id=2" in run.launched_log(2)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "Ctrl-C"])
def test_local_launcher_passes_sigterm_or_ctrl_c_on_as_sigterm_and_exits_0_when_all_do(tmp_path, sig):
  with _launch_stand_ins(tmp_path, "wait,wait", 2, 1) as run:
    run.wait_for(lambda: "stand-in process 0 ready" in run.output(0)
                 and "stand-in process 1 ready" in run.launched_log(1), 30, "both stand-ins ready")
    run.signal(0, sig)  # the stand-ins exit 0 on SIGTERM only
    codes = run.wait(timeout=30)
  assert codes == [0], run.output(0)


def test_local_launcher_exits_with_the_preempted_status_when_the_processes_stopped_at_a_checkpoint(tmp_path):
  """A process that saved a step and stopped (exit 75) is no failure: its peers are not killed, and the
  launcher exits 75 (requeue me), even where a peer had already finished (0)."""
  with _launch_stand_ins(tmp_path, "wait:75,wait:75", 2, 1) as run:
    run.wait_for(lambda: "stand-in process 0 ready" in run.output(0)
                 and "stand-in process 1 ready" in run.launched_log(1), 30, "both stand-ins ready")
    run.signal(0, signal.SIGTERM)
    codes = run.wait(timeout=30)
  assert codes == [75], run.output(0)
  assert "stopped at a checkpoint (exit status 75)" in run.output(0)
  with _launch_stand_ins(tmp_path, "exit:75,exit:0", 2, 1, "--grace_s=60") as run:
    codes = run.wait(timeout=30)
  assert codes == [75] and "exited with status" not in run.output(0), run.output(0)
  with _launch_stand_ins(tmp_path, "exit:9,exit:9", 2, 1, "--preempted_exit_code=9") as run:
    assert run.wait(timeout=30) == [9] and "stopped at a checkpoint" in run.output(0)


def test_local_launcher_refuses_bad_counts():
  out = subprocess.run([sys.executable, str(LOCAL), "--num_processes=0"], capture_output=True, text=True,
                       timeout=30)
  assert out.returncode == 2 and "--num_processes and --devices_per_process must be at least 1" in out.stderr


def _tpu_pod(tmp_path, *args, fake_gcloud_exists=None, run_status=0):
  """Runs launch/tpu_pod.py with a stand-in `gcloud` on PATH that records its calls; returns (result, calls).

  fake_gcloud_exists: what the stand-in's `describe` answers: {"bucket": bool, "pod": bool}; run_status: the
  exit status of the run on worker 0, as the log follower reports it."""
  bin_dir = tmp_path / "bin"
  bin_dir.mkdir(exist_ok=True)
  calls = tmp_path / "gcloud_calls"
  exists = fake_gcloud_exists or {}
  gcloud = bin_dir / "gcloud"
  gcloud.write_text(
      "#!/bin/sh\n"
      f"printf '%s\\n' \"$*\" >> {shlex.quote(str(calls))}\n"
      f"case \"$*\" in *'storage buckets describe'*) exit {0 if exists.get('bucket') else 1};; "
      f"*'tpu-vm describe'*) exit {0 if exists.get('pod') else 1};; "
      f"*'tail --pid'*) exit {run_status};; esac\nexit 0\n")
  gcloud.chmod(0o755)
  env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}", TMPDIR=str(tmp_path))
  result = subprocess.run([sys.executable, str(TPU_POD), *args], capture_output=True, text=True, env=env,
                          timeout=60, cwd=tmp_path)
  return result, (calls.read_text().splitlines() if calls.exists() else [])


POD_ARGS = ("--name=nerf-pod", "--zone=us-central2-b", "--project=my-proj", "--accelerator-type=v4-32",
            "--skip-preflight", "--workdir=gs://my-bucket/runs/lego", "--", "--config=configs/default.py",
            "--config.train.num_steps=500")


def test_tpu_pod_dry_run_prints_every_command_and_runs_none(tmp_path):
  result, calls = _tpu_pod(tmp_path, "--dry-run", *POD_ARGS)
  assert result.returncode == 0, result.stderr
  assert calls == []  # nothing was run
  commands = [shlex.split(line) for line in result.stdout.splitlines()
              if line and not line.startswith(("#", "launch/tpu_pod.py:"))]
  assert [c[:5] for c in commands] == [
      ["gcloud", "storage", "buckets", "describe", "gs://my-bucket"],
      ["gcloud", "storage", "buckets", "create", "gs://my-bucket"],
      ["gcloud", "compute", "tpus", "tpu-vm", "describe"],
      ["gcloud", "compute", "tpus", "tpu-vm", "create"],
      ["tar", "-czf", str(tmp_path / "nerfpod-src.tar.gz"), "-C", str(REPO)],
      ["gcloud", "compute", "tpus", "tpu-vm", "scp"],
      ["gcloud", "compute", "tpus", "tpu-vm", "ssh"],
      ["gcloud", "compute", "tpus", "tpu-vm", "ssh"],
      ["gcloud", "compute", "tpus", "tpu-vm", "ssh"],
      ["gcloud", "compute", "tpus", "tpu-vm", "ssh"],
  ]
  bucket_create, _, pod_create, pack, scp, install, check, start, follow = commands[1:]
  assert pack[5:] == ["--null", f"--files-from={tmp_path / 'nerfpod-src.tar.gz.files'}"]
  assert "--location=us-central2" in bucket_create
  assert pod_create[5] == "nerf-pod" and "--accelerator-type=v4-32" in pod_create
  assert "--zone=us-central2-b" in pod_create and "--project=my-proj" in pod_create
  assert "--worker=all" in scp and "nerf-pod:~/nerfpod-src.tar.gz" in scp
  # v4's runtime image (Ubuntu 22.04, Python 3.10): each worker gets Python 3.11 in a virtual environment
  # with the suite's pinned versions and the TPU runtime of that JAX, then shows its chips before training.
  assert "--version=tpu-ubuntu2204-base" in pod_create
  assert "--worker=all" in install
  setup = _command(install)
  assert "uv python install 3.11" in setup and "venv" in setup and "--python 3.11 ~/nerfpod-venv" in setup
  # the gcs extra: gcsfs (scenes, and the workdir through epath and orbax) and google-cloud-storage (events)
  assert "pip install -q --python ~/nerfpod-venv/bin/python -c constraints.txt -e '.[tpu,gcs]'" in setup
  assert "--worker=all" in check
  assert shlex.split(_command(check).split("&& ", 1)[1]) == [
      "~/nerfpod-venv/bin/python", "launch/check_devices.py", "--pod=v4-32", "--chips=16", "--per-host=4"]
  # The same command on every worker, writing into the bucket; then worker 0's log, to the run's end.
  assert "--worker=all" in start
  inner = shlex.split(shlex.split(_command(start).split("nohup sh -c ", 1)[1])[0])
  assert inner[:3] == ["~/nerfpod-venv/bin/python", "-m", "nerfpod.main"]
  assert inner[3:6] == ["--config=configs/default.py", "--config.train.num_steps=500",
                        "--workdir=gs://my-bucket/runs/lego"]
  assert "--worker=0" in follow and "tail --pid=" in _command(follow)


def _command(ssh: list[str]) -> str:
  return next(a for a in ssh if a.startswith("--command="))[len("--command="):]


def test_tpu_pod_reuses_an_existing_pod_and_creates_a_missing_bucket(tmp_path):
  result, calls = _tpu_pod(tmp_path, *POD_ARGS, fake_gcloud_exists={"bucket": False, "pod": True})
  assert result.returncode == 0, result.stderr
  verbs = [" ".join(c.split()[:4]) for c in calls]
  assert verbs == ["storage buckets describe gs://my-bucket", "storage buckets create gs://my-bucket",
                   "compute tpus tpu-vm describe", "compute tpus tpu-vm scp", "compute tpus tpu-vm ssh",
                   "compute tpus tpu-vm ssh", "compute tpus tpu-vm ssh", "compute tpus tpu-vm ssh"]
  # The project's own files, packed for the workers: what installing and running nerfpod needs there.
  import tarfile
  with tarfile.open(tmp_path / "nerfpod-src.tar.gz") as tar:
    names = set(tar.getnames())
  assert {"pyproject.toml", "constraints.txt", "README.md", "nerfpod/main.py", "nerfpod/pod/chips.py",
          "configs/default.py", "launch/check_devices.py"} <= names
  assert not {n for n in names if n.startswith(("tests/", "docs/", "runs/", "build/", ".git"))
              or "__pycache__" in n or n.endswith(".pyc")}, names


def test_tpu_pod_passes_a_preempted_runs_status_75_on_with_how_to_resume(tmp_path):
  result, _ = _tpu_pod(tmp_path, *POD_ARGS, fake_gcloud_exists={"bucket": True, "pod": True}, run_status=75)
  assert result.returncode == 75, result.stderr
  assert "stopped at a checkpoint (preempted, exit status 75)" in result.stderr
  assert "run this script again with the same arguments" in result.stderr
  result, _ = _tpu_pod(tmp_path, *POD_ARGS, fake_gcloud_exists={"bucket": True, "pod": True}, run_status=1)
  assert result.returncode == 1 and "failed (stream worker 0's log" in result.stderr


RUN = ("--", "--config=configs/default.py")


@pytest.mark.parametrize("bad,message", [
    (("--workdir=/tmp/local", *RUN), "must be a gs:// path"),
    (("--workdir=gs://bkt/x", "--", "--config=configs/default.py", "--workdir=gs://bkt/y"),
     "pass --workdir to this script"),
    (("--workdir=gs://bkt/x", "--accelerator-type=v9-8", *RUN), "--accelerator-type=v9-8 is not a pod this script knows"),
    (("--workdir=gs://bkt/x", "--name=Bad_Name", *RUN), "--name='Bad_Name' must be lowercase letters, digits and hyphens"),
    (("--workdir=gs://bkt/x", "--name=Bad Name!", *RUN), "--name='Bad Name!' must be lowercase letters"),
    (("--workdir=gs://bkt/x", "--gke", "--name=Bad_Name", *RUN), "--name='Bad_Name' must be lowercase letters"),
    (("--workdir=gs://bkt/x", f"--name={'n' * 64}", *RUN), "at most 63 characters"),
    (("--workdir=gs://bkt/x", "--gke", "--accelerator-type=v5litepod-256", f"--name={'n' * 45}", *RUN),
     f"--name={'n' * 45} is too long for a JobSet of 64 host(s): the names of its pods"),
    (("--workdir=gs://bkt/x", "--zone=mars-1", *RUN), "--zone=mars-1 is not a Google Cloud zone"),
    (("--workdir=gs://My_Bucket/x", *RUN), "'My_Bucket' is not a Cloud Storage bucket name"),
    (("--workdir=gs://bkt/x", "--python=2.7", *RUN), "--python=2.7: nerfpod needs Python 3.11 or newer"),
    (("--workdir=gs://bkt/x", "--python=3.10", *RUN), "--python=3.10: nerfpod needs Python 3.11 or newer"),
    (("--workdir=gs://bkt/x", "--gke", "--max-restarts=-1", *RUN), "--max-restarts=-1 must be 0 or more"),
    (("--workdir=gs://bkt/x", "--max-restarts=3", *RUN), "--max-restarts is for --gke and would be ignored on TPU VMs"),
    (("--workdir=gs://bkt/x", "--image=python:3.12", *RUN), "--image is for --gke"),
    (("--workdir=gs://bkt/x", "--gke", "--spot", *RUN), "--spot is for TPU VMs and would be ignored with --gke"),
    (("--workdir=gs://bkt/x", "--gke", "--skip-setup", "--version=x", *RUN),
     "--version, --skip-setup are for TPU VMs and would be ignored with --gke"),
    (("--workdir=gs://bkt/x", "--gke", "--manifest=no/such/folder/job.yaml", *RUN),
     "--manifest=no/such/folder/job.yaml: its folder"),
    (("--workdir=gs://bkt/x", "--gke", "--manifest=.", *RUN), "--manifest=. is a folder; name the file to write"),
    (("--workdir=gs://bkt/x", "--skip-preflight", "--"), "the workers need at least --config=CONFIG after `--`"),
    (("--workdir=gs://bkt/x", "--skip-preflight"), "the workers need at least --config=CONFIG after `--`"),
    (("--workdir=gs://bkt/x", "--", "--config=configs/nope.py:smoke"), "configs/nope.py does not exist"),
    (("--workdir=gs://bkt/x", "--", "--config=/etc/hostname"), "--config=/etc/hostname is outside the project"),
], ids=lambda v: " ".join(v)[:60] if isinstance(v, tuple) else None)
def test_tpu_pod_refuses_what_cannot_work_on_a_pod_in_one_sentence_before_anything_runs(tmp_path, bad, message):
  result, calls = _tpu_pod(tmp_path, "--name=p", "--zone=us-central2-b", "--dry-run", *bad)
  assert result.returncode == 2, result.stdout + result.stderr
  lines = result.stderr.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("launch/tpu_pod.py: error: ") and message in lines[0], lines
  assert calls == [] and result.stdout == ""  # nothing ran, nothing was planned
  assert not list(tmp_path.glob("*.yaml")) and not list(tmp_path.glob("nerfpod-src*"))


def test_the_project_is_packed_without_runs_data_or_caches(tmp_path):
  """launch/pack.py: in a git checkout, what git does not ignore of the project's folders (a new config
  too); elsewhere, the same folders walked; never a user's runs/, data or a virtual environment."""
  import subprocess as sp
  sys.path.insert(0, str(REPO / "launch"))
  import pack
  for folder in ("nerfpod/pod", "configs", "launch", "runs/lego/checkpoints", "data", ".venv/lib", "tests",
                 "nerfpod/__pycache__"):
    (tmp_path / folder).mkdir(parents=True)
  for name in ("pyproject.toml", "constraints.txt", "README.md", "nerfpod/__init__.py", "nerfpod/pod/aot.py",
               "configs/default.py", "launch/check_devices.py", "runs/lego/checkpoints/state", "data/img.png",
               ".venv/lib/site.py", "tests/test_x.py", "nerfpod/__pycache__/x.pyc", "notes.txt"):
    (tmp_path / name).write_text("x")
  wanted = ["README.md", "configs/default.py", "constraints.txt", "launch/check_devices.py", "nerfpod/__init__.py",
            "nerfpod/pod/aot.py", "pyproject.toml"]
  assert pack.project_files(str(tmp_path)) == wanted  # not a git checkout: the folders walked
  git = lambda *a: sp.run(["git", "-C", str(tmp_path), *a], check=True, capture_output=True)
  git("init", "-q")
  (tmp_path / ".gitignore").write_text("/runs/\n__pycache__/\n/.venv/\n")
  git("add", "pyproject.toml", "constraints.txt", "README.md", "nerfpod", "configs", "launch/check_devices.py")
  (tmp_path / "configs" / "mine.py").write_text("x")  # new, not yet added: goes along
  (tmp_path / "configs" / "old.py").write_text("x")
  git("add", "configs/old.py")
  (tmp_path / "configs" / "old.py").unlink()  # deleted, not yet committed: left out
  assert pack.project_files(str(tmp_path)) == sorted(wanted + ["configs/mine.py"])
  assert pack.project_files(str(tmp_path), extra=("notes.txt",)) == sorted(wanted + ["configs/mine.py", "notes.txt"])


def test_tpu_pod_on_gke_writes_a_valid_jobset_with_one_process_per_host(tmp_path):
  """--gke: the same job as a JobSet on a GKE TPU slice; the manifest is checked against the JobSet schema
  (kubectl's client-side dry run needs the cluster's API discovery for a custom resource, so not here)."""
  import json

  import jsonschema
  import yaml
  manifest_path = tmp_path / "job.yaml"
  args = [a for a in POD_ARGS if not a.startswith("--accelerator-type")]
  result, calls = _tpu_pod(tmp_path, "--dry-run", "--gke", f"--manifest={manifest_path}",
                           "--accelerator-type=v5litepod-16", "--max-restarts=7", *args)
  assert result.returncode == 0, result.stderr
  assert calls == []  # a dry run: nothing uploaded or applied
  commands = [shlex.split(line) for line in result.stdout.splitlines()
              if line and not line.startswith(("#", "launch/tpu_pod.py:"))]
  assert commands[0][:5] == ["tar", "-czf", str(tmp_path / "nerfpod-src.tar.gz"), "-C", str(REPO)]
  assert commands[1][:3] == ["gcloud", "storage", "cp"]
  assert commands[1][-2:] == ["gs://my-bucket/runs/lego/_launch/nerfpod-src.tar.gz", "--project=my-proj"]
  assert commands[2] == ["kubectl", "apply", "-f", str(manifest_path)]
  job = yaml.safe_load(manifest_path.read_text())
  # The upstream CRD's own schema, as the API server checks it (tests/data/README.md) ...
  crd = json.loads((REPO / "tests" / "data" / "jobset_crd_v1alpha2.openapi.json").read_text())
  jsonschema.Draft4Validator(crd).validate(job)
  # ... and the names the JobSet webhook derives: its pods' names must be DNS labels of 63 characters at most.
  for host in range(4):
    name = f"{job['metadata']['name']}-{job['spec']['replicatedJobs'][0]['name']}-0-{host}-abcde"
    assert len(name) <= 63 and re.fullmatch(r"[a-z]([-a-z0-9]*[a-z0-9])?", name)
  schema = json.loads((REPO / "tests" / "data" / "jobset_v1alpha2.schema.json").read_text())
  jsonschema.validate(job, schema)
  assert job["metadata"]["annotations"]["alpha.jobset.sigs.k8s.io/exclusive-topology"] == \
      "cloud.google.com/gke-nodepool"
  assert job["spec"]["failurePolicy"]["maxRestarts"] == 7
  workers = job["spec"]["replicatedJobs"][0]["template"]["spec"]
  assert workers["parallelism"] == workers["completions"] == 4  # v5litepod-16: 4 hosts of 4 chips
  assert workers["completionMode"] == "Indexed"
  pod = workers["template"]["spec"]
  assert pod["nodeSelector"] == {"cloud.google.com/gke-tpu-accelerator": "tpu-v5-lite-podslice",
                                 "cloud.google.com/gke-tpu-topology": "4x4"}
  assert pod["terminationGracePeriodSeconds"] >= 60  # time to save a checkpoint after SIGTERM
  container = pod["containers"][0]
  assert container["resources"]["limits"]["google.com/tpu"] == 4
  script = container["command"][-1].splitlines()
  assert "pip install -q -c constraints.txt -e '.[tpu,gcs]'" in script
  assert "python launch/check_devices.py --pod=v5litepod-16 --chips=16 --per-host=4" in script
  assert shlex.split(script[-1]) == ["exec", "python", "-m", "nerfpod.main", "--config=configs/default.py",
                                     "--config.train.num_steps=500", "--workdir=gs://my-bucket/runs/lego"]
  # A broken manifest fails the same checks.
  broken = json.loads(json.dumps(job))
  broken["spec"]["failurePolicy"]["maxRestarts"] = "ten"
  with pytest.raises(jsonschema.ValidationError):
    jsonschema.Draft4Validator(crd).validate(broken)
  del pod["containers"][0]["image"]
  with pytest.raises(jsonschema.ValidationError):
    jsonschema.validate(job, schema)


def test_check_devices_refuses_a_host_without_its_tpu_chips_in_one_sentence():
  out = subprocess.run([sys.executable, str(REPO / "launch" / "check_devices.py"), "--pod=v4-32", "--chips=16",
                        "--per-host=4"], capture_output=True, text=True, timeout=120, cwd=REPO,
                       env=procs.environment(1))
  assert out.returncode == 1
  lines = out.stderr.strip().splitlines()
  assert len(lines) == 1 and "expected 4 TPU chips here and 16 in all (v4-32) but JAX sees 1 device(s) here " \
                             "(cpu:cpu)" in lines[0], out.stderr


def test_preflight_prints_the_figures_and_refuses_only_what_does_not_fit():
  sys.path.insert(0, str(REPO / "launch"))
  import preflight
  gib = 2**30
  report = {"pod": "v5litepod-16", "chips": 16, "hosts": 4, "num_steps": 30000, "rays_per_chip": 256,
            "microbatches": 1, "chip": {"hbm_bytes": 16 * gib},
            "step": {"seconds": 0.02, "rays_per_s": 204800.0, "run_seconds": 600.0, "fits_hbm": True,
                     "memory": {"peak_bytes": 3 * gib, "argument_bytes": gib, "temp_bytes": 2 * gib}}}
  assert preflight.summary(report) == (
      "v5litepod-16 (16 chips, 4 hosts): per chip 3.00 GiB of 16.00 GiB HBM (arguments 1.00 GiB, temporaries "
      "2.00 GiB); step 0.02 s, 204,800 rays/s; 30000 steps in about 10.0 min (XLA cost-model estimate, not a "
      "measurement)")
  assert preflight.refusal(report) is None
  report["step"].update(fits_hbm=False, memory={"peak_bytes": 20 * gib, "argument_bytes": gib,
                                                "temp_bytes": 19 * gib})
  assert preflight.refusal(report).startswith(
      "the train step needs 20.00 GiB per chip on v5litepod-16 (temporaries 19.00 GiB, arguments 1.00 GiB) but "
      "a chip has 16.00 GiB of HBM; split each chip's 256 rays into more micro-batches "
      "(--config.train.microbatches=2 or more)")
  report["microbatches"] = 0  # fitted, and XLA refused the step while fitting: more is still the fix
  assert "(--config.train.microbatches=2 or more)" in preflight.refusal(report)
  assert preflight.config_args(["--config=c.py", "--config.train.num_steps=5", "--mode=eval"]) == [
      "--config=c.py", "--config.train.num_steps=5"]
  assert preflight.command(["--config=c.py", "--mode=eval"], "v4-32", "r.json")[1:] == [
      "-m", "nerfpod.pod.aot", "--config=c.py", "--topology=v4-32", "--what=step,eval,orbit", "--json=r.json"]
  # A renderer that does not fit: the chunk is the fix.
  report["step"].update(fits_hbm=True)
  report["orbit"] = {"fits_hbm": False, "rays": 65536, "memory": {"peak_bytes": 18 * gib}}
  assert preflight.refusal(report) == (
      "the orbit renderer needs 18.00 GiB per chip on v5litepod-16 for 65,536 rays a call but a chip has 16.00 GiB "
      "of HBM; use a smaller --config.orbit.chunk.")


def test_multislice_on_gke_is_one_job_per_slice_with_the_variables_multislice_jax_reads(tmp_path):
  """--slices=2 --gke: the JobSet's replicated job has one replica (Job) per slice, each pod the MEGASCALE_*
  variables (slice count, its Job's index as its slice, slice 0's first host as coordinator); valid against
  both JobSet schemas."""
  import json

  import jsonschema
  import yaml
  manifest_path = tmp_path / "job.yaml"
  args = [a for a in POD_ARGS if not a.startswith("--accelerator-type")]
  result, calls = _tpu_pod(tmp_path, "--dry-run", "--gke", f"--manifest={manifest_path}",
                           "--accelerator-type=v5litepod-16", "--slices=2", *args)
  assert result.returncode == 0, result.stderr
  assert calls == [] and "--max-log-requests=8" in result.stdout  # 2 slices x 4 hosts
  job = yaml.safe_load(manifest_path.read_text())
  crd = json.loads((REPO / "tests" / "data" / "jobset_crd_v1alpha2.openapi.json").read_text())
  jsonschema.Draft4Validator(crd).validate(job)
  schema = json.loads((REPO / "tests" / "data" / "jobset_v1alpha2.schema.json").read_text())
  jsonschema.validate(job, schema)
  (workers,) = job["spec"]["replicatedJobs"]
  assert workers["replicas"] == 2
  assert workers["template"]["spec"]["parallelism"] == workers["template"]["spec"]["completions"] == 4
  # Each Job on a node pool of its own: one slice each.
  assert job["metadata"]["annotations"]["alpha.jobset.sigs.k8s.io/exclusive-topology"] == \
      "cloud.google.com/gke-nodepool"
  container = workers["template"]["spec"]["template"]["spec"]["containers"][0]
  env = {e["name"]: e for e in container["env"]}
  assert env["MEGASCALE_NUM_SLICES"]["value"] == "2"
  assert env["MEGASCALE_SLICE_ID"]["valueFrom"]["fieldRef"]["fieldPath"] == \
      "metadata.annotations['jobset.sigs.k8s.io/job-index']"
  assert env["MEGASCALE_COORDINATOR_ADDRESS"]["value"] == "nerf-pod-workers-0-0.nerf-pod"
  assert "python launch/check_devices.py --pod=v5litepod-16 --chips=32 --per-host=4" in container["command"][-1]
  for slice_index in range(2):  # the webhook's pod names, the last slice's too, are DNS labels
    name = f"nerf-pod-workers-{slice_index}-3-abcde"
    assert len(name) <= 63 and re.fullmatch(r"[a-z]([-a-z0-9]*[a-z0-9])?", name)
  # One slice: no MEGASCALE_* variables, one replica (the manifest of before).
  result, _ = _tpu_pod(tmp_path, "--dry-run", "--gke", f"--manifest={manifest_path}",
                       "--accelerator-type=v5litepod-16", *args)
  single = yaml.safe_load(manifest_path.read_text())
  assert single["spec"]["replicatedJobs"][0]["replicas"] == 1
  assert "env" not in single["spec"]["replicatedJobs"][0]["template"]["spec"]["template"]["spec"]["containers"][0]
  broken = json.loads(json.dumps(job))
  broken["spec"]["replicatedJobs"][0]["template"]["spec"]["template"]["spec"]["containers"][0]["env"][0] = {
      "name": "MEGASCALE_NUM_SLICES", "value": 2}  # a number where Kubernetes takes a string
  with pytest.raises(jsonschema.ValidationError):
    jsonschema.validate(broken, schema)


def test_multislice_on_tpu_vms_is_one_queued_resource_of_one_node_per_slice(tmp_path):
  result, calls = _tpu_pod(tmp_path, "--dry-run", "--slices=2", "--spot",
                           *[a if not a.startswith("--accelerator-type") else "--accelerator-type=v5litepod-256"
                             for a in POD_ARGS])
  assert result.returncode == 0, result.stderr
  assert calls == []
  commands = [shlex.split(line) for line in result.stdout.splitlines()
              if line and not line.startswith(("#", "launch/tpu_pod.py:"))]
  gcloud = [c for c in commands if c[0] == "gcloud" and c[1] == "compute"]
  assert all(c[:4] == ["gcloud", "compute", "tpus", "queued-resources"] for c in gcloud), gcloud
  describe, create, scp, install, check, start, follow = gcloud
  assert describe[4:6] == ["describe", "nerf-pod"]
  assert create[4:] == ["create", "nerf-pod", "--node-count=2", "--node-prefix=nerf-pod",
                        "--accelerator-type=v5litepod-256", "--runtime-version=v2-alpha-tpuv5-lite",
                        "--zone=us-central2-b", "--project=my-proj", "--spot"]
  wait = next(c for c in commands if c[0] == "sh")
  assert "queued-resources describe nerf-pod '--format=value(state.state)'" in wait[2]
  assert "ACTIVE) exit 0" in wait[2] and "FAILED|SUSPENDED)" in wait[2]
  assert commands.index(wait) == commands.index(create) + 1  # granted before anything is copied
  # Every worker of every slice at once: the check and the run start jax.distributed across the slices.
  for step in (scp, install, check, start):
    assert "--node=all" in step and "--worker=all" in step, step
  assert "nerf-pod:~/nerfpod-src.tar.gz" in scp
  assert shlex.split(_command(check).split("&& ", 1)[1]) == [
      "~/nerfpod-venv/bin/python", "launch/check_devices.py", "--pod=v5litepod-256", "--chips=512",
      "--per-host=4"]
  assert "--node=0" in follow and "--worker=0" in follow  # process 0: slice 0's first host


@pytest.mark.parametrize("bad,message", [
    (("--slices=0",), "--slices=0 must be 1 (one slice) or more"),
    # 44 characters fit one slice (tested above); the 11th slice's pods have a two-digit Job index.
    (("--gke", "--slices=11", "--accelerator-type=v5litepod-256", f"--name={'n' * 44}"),
     f"--name={'n' * 44} is too long for a JobSet of 11 slices of 64 host(s): the names of its pods "
     f"({'n' * 44}-workers-10-63-xxxxx) must fit in 63 characters; use at most 43 characters"),
])
def test_a_bad_slice_count_or_a_name_too_long_for_its_slices_is_one_sentence(tmp_path, bad, message):
  result, calls = _tpu_pod(tmp_path, "--name=p", "--zone=us-central2-b", "--dry-run", "--workdir=gs://bkt/x",
                           *bad, *RUN)
  assert result.returncode == 2 and calls == [] and result.stdout == ""
  lines = result.stderr.strip().splitlines()
  assert len(lines) == 1 and message in lines[0], lines


def test_the_preflight_compiles_every_slice():
  sys.path.insert(0, str(REPO / "launch"))
  import preflight
  assert preflight.command(["--config=c.py"], "v5litepod-256", "r.json", slices=2)[1:] == [
      "-m", "nerfpod.pod.aot", "--config=c.py", "--topology=v5litepod-256", "--slices=2",
      "--what=step,eval,orbit", "--json=r.json"]
