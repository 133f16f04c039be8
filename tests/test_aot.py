"""The pod compile tool (nerfpod.pod.aot: `nerfpod aot`), the launcher's preflight, and a CPU run with libtpu
installed.

Compiling for a TPU topology needs libtpu (the `tpu` extra); those tests skip, saying so, where it is absent.
They compile the smoke config only, on small multi-host pods, and are marked slow."""
import importlib.util
import json
import os
import subprocess
import sys

import pytest

import procs
from procs import REPO

HAS_LIBTPU = importlib.util.find_spec("libtpu") is not None
needs_libtpu = pytest.mark.skipif(not HAS_LIBTPU, reason="libtpu is not installed (pip install -e '.[tpu]')")


AOT = ["-m", "nerfpod.pod.aot"]
# What the tool sets in its process (aot._quiet_libtpu: the variables libtpu reads, and JAX_PLATFORMS, which a
# process of the tool starts without: _aot).
TOOL_ENVIRONMENT = ("TPU_ACCELERATOR_TYPE", "TPU_WORKER_HOSTNAMES", "TPU_SKIP_MDS_QUERY", "ALLOW_MULTIPLE_LIBTPU_LOAD",
                    "JAX_PLATFORMS")


def _aot(*args, timeout=600, entry=AOT) -> subprocess.CompletedProcess:
  """`python -m nerfpod.pod.aot ARGS` in a process of its own: for the compiles for a TPU topology (libtpu,
  loaded with the variables the tool sets first) and the module's own entry point."""
  env = procs.environment(1)
  env.pop("JAX_PLATFORMS")  # the tool chooses its own
  return subprocess.run([sys.executable, *entry, *args], cwd=REPO, env=env, capture_output=True, text=True,
                        timeout=timeout)


@pytest.fixture
def aot_here(capsys, monkeypatch):
  """`nerfpod aot ARGS` in this process (aot.run, as the `nerfpod` command calls it; procs.in_process), for the
  tool's refusals, which come before any compile and any JAX call (this process's JAX, already started on its
  CPU devices, plays no part). The variables the tool sets with os.environ.setdefault (TOOL_ENVIRONMENT) go
  back to what they were after the test; JAX_PLATFORMS is unset during it, as in _aot's process."""
  from nerfpod.pod import aot
  for name in TOOL_ENVIRONMENT:
    was = os.environ.get(name)
    monkeypatch.setenv(name, was or "")  # restored after the test: to `was`, or to no variable at all
    if was is None or name == "JAX_PLATFORMS":
      monkeypatch.delenv(name)
  return procs.in_process(aot.run, "nerfpod aot", capsys, monkeypatch, REPO, flag_values=[aot.FLAGS])


@pytest.mark.parametrize("entry", ["run", "module"])
def test_unknown_topology_is_refused_in_one_sentence_listing_the_known_ones(aot_here, entry):
  """The ways in: `nerfpod aot` (its run(argv), in this process) and `python -m nerfpod.pod.aot` (the module's
  __main__, in a process of its own: it refuses before importing JAX, a fraction of a second)."""
  args = ("--config=configs/default.py:smoke", "--topology=v9-1024")
  out = aot_here(*args) if entry == "run" else _aot(*args)
  assert out.returncode == 2
  lines = out.stderr.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("nerfpod: error: unknown --topology=v9-1024; known pods:")
  for name in ("v4-8", "v4-32", "v5litepod-16", "v5litepod-64", "v5litepod-256", "v5p-128", "v6e-64"):
    assert name in lines[0]


def _one_sentence(out: subprocess.CompletedProcess, code: int = 2) -> str:
  """The tool's one line on stderr (after libtpu's own log lines, if any), no traceback; returns it."""
  assert out.returncode == code, out.stderr
  assert "Traceback" not in out.stderr + out.stdout
  lines = [l for l in out.stderr.strip().splitlines() if not l.startswith(("I1", "I0", "W1", "W0"))]
  assert len(lines) == 1 and lines[0].startswith("nerfpod: error: "), out.stderr
  return lines[0]


@pytest.mark.parametrize("args,message", [
    (["--topology="], "--topology is empty; name the pod to compile for, e.g. --topology=v5e-64 (known pods: v4-8"),
    (["--topology=,"], "--topology is empty"),
    (["--config=configs/nope.py", "--topology=v5e-8"], "the --config file configs/nope.py does not exist"),
    (["--topology=v5e-8", "--config.train.nope=3"], "--config.train.nope: config section train has no field 'nope'; "
                                                     "`python -m nerfpod.schema` lists every field"),
    (["--topology=v5e-8", "--config.train.num_steps=many"], "--config.train.num_steps=many: invalid literal"),
    (["--config=configs/default.py:nosuch", "--topology=v5e-8"], "unknown config argument 'nosuch'"),
    (["--topology=v5e-8", "--bogus"], "unknown flag --bogus; nerfpod aot takes --config, --json, --slices"),
    (["--topology=v5e-8", "extra"], "unexpected arguments: extra"),
    (["--topology=v5e-8", "--what="], "--what=: choose one or more of step, eval, orbit"),
    (["--topology=v5e-8", "--what=step,train"], "--what=step,train: choose one or more of step, eval, orbit"),
    (["--topology=v5e-8", "--json=/nonexistent/r.json"], "--json=/nonexistent/r.json: its folder /nonexistent "
                                                         "does not exist"),
    (["--topology=v5e-8", "--json=tests"], "--json=tests is a folder; name a file"),
    (["--config=configs/default.py:smoke"], "--topology is required, e.g. --topology=v5e-64"),
    (["--topology=v5e-8", "--slices=0"], "--slices=0 must be 1 (one slice) or more"),
    (["--topology=v5e-8", "--slices=two"], "--slices=two: invalid literal"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_bad_arguments_are_one_sentence_and_exit_2(aot_here, args, message):
  if not any(a.startswith("--config=") for a in args) and "--config=configs/default.py:smoke" not in args:
    args = ["--config=configs/default.py:smoke", *args]
  line = _one_sentence(aot_here(*args))
  assert message in line, line


def test_a_compiler_refusal_is_one_sentence_naming_the_program_the_pod_and_xlas_reason_exit_1(aot_here, monkeypatch):
  """As the TPU compiler refused the orbit's per-host program on v5e pods (tests/test_pod_sweep.py has the
  real refusal): here a stand-in compile_pod raises XLA's error through the tool's own handling."""
  import jax
  from nerfpod.pod import aot
  xla = ("INTERNAL: RET_CHECK failure (deepsea_compiler_base.cc:1879) device_count\n"
         "   == target.Topology()->LogicalDeviceCount() should include all slice devices\nmore detail")

  def refusing(error):
    def compile_pod(config, pod, what, slices=1):  # noqa: ARG001 (compile_pod's signature)
      def compile_fn():
        raise error
      return {"orbit": aot._compile("orbit", compile_fn, pod, 4, 1024)}
    return compile_pod
  monkeypatch.setattr(aot, "compile_pod", refusing(jax.errors.JaxRuntimeError(xla)))
  line = _one_sentence(aot_here("--config=configs/default.py:smoke", "--topology=v5e-64", "--what=orbit"), code=1)
  assert line == ("nerfpod: error: the orbit renderer does not compile for v5litepod-64 (64 chips on 16 hosts): "
                  "INTERNAL: RET_CHECK failure (deepsea_compiler_base.cc:1879) device_count")
  monkeypatch.setattr(aot, "compile_pod", refusing(IndexError(xla)))  # a crash, not XLA's error
  line = _one_sentence(aot_here("--config=configs/default.py:smoke", "--topology=v5e-64"), code=1)
  assert line.startswith("nerfpod: error: the orbit renderer does not compile for v5litepod-64 (64 chips on 16 "
                         "hosts): IndexError: INTERNAL: RET_CHECK")


@pytest.mark.slow
@needs_libtpu
def test_json_to_stdout_is_the_report_alone_and_the_tables_go_to_stderr():
  out = _aot("--config=configs/default.py:smoke", "--topology=v4-8", "--what=eval", "--json=-", timeout=300)
  assert out.returncode == 0, out.stderr
  report = json.loads(out.stdout)
  assert report["pod"] == "v4-8" and set(report) >= {"eval"} and "step" not in report
  assert "v4-8 (v4:2x2x1, 4 chips of TPU v4 on 1 hosts)" in out.stderr and "Traceback" not in out.stderr


def test_a_batch_that_does_not_split_over_the_pod_is_refused(aot_here):
  out = aot_here("--config=configs/default.py:smoke", "--config.train.batch_size=100", "--topology=v5e-64")
  assert out.returncode == 2
  assert "train.batch_size=100 does not split over 64 devices" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.slow
@needs_libtpu
def test_the_launchers_preflight_refuses_a_job_too_large_for_the_chips_with_the_figures(tmp_path):
  from test_launch import _tpu_pod
  result, calls = _tpu_pod(tmp_path, "--dry-run", "--name=p", "--zone=us-central2-b",
                           "--accelerator-type=v5litepod-16", "--workdir=gs://bkt/x", "--",
                           "--config=configs/default.py:smoke", "--config.train.batch_size=16777216")
  assert result.returncode == 2, result.stdout + result.stderr
  assert calls == []  # refused before any pod is created or used
  assert "-m nerfpod.pod.aot --config=configs/default.py:smoke --config.train.batch_size=16777216 " \
         "--topology=v5litepod-16 --what=step,eval,orbit" in result.stdout
  assert "preflight: v5litepod-16 (16 chips, 4 hosts): per chip" in result.stdout
  error = result.stderr.strip().splitlines()[-1]
  assert "the train step needs" in error and "of HBM" in error
  assert "--config.train.microbatches=2" in error  # the fix, with the figures
  assert "gcloud" not in result.stdout.split("preflight:")[-1]  # no pod command was even printed


@pytest.mark.slow
@needs_libtpu
def test_a_cpu_run_with_libtpu_installed_behaves_as_without_it(tmp_path):
  """No JAX_PLATFORMS given: nerfpod keeps JAX off the absent TPU (no start-up errors) and trains on the
  CPU to the very same result as a run told to use the CPU."""
  flags = ["--config=configs/default.py:smoke", "--config.train.num_steps=4",
           "--config.orbit.render_after_training=false", "--config.eval.max_views=1"]
  results = {}
  for name, platforms in (("unset", None), ("cpu", "cpu")):
    env = procs.environment(1)
    env.pop("JAX_PLATFORMS")
    if platforms:
      env["JAX_PLATFORMS"] = platforms
    out = subprocess.run([sys.executable, "-m", "nerfpod.main", *flags, f"--workdir={tmp_path / name}"], cwd=REPO,
                         env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    results[name] = (out, json.loads((tmp_path / name / "eval" / "metrics.json").read_text()))
  unset, _ = results["unset"]
  for noise in ("TPU", "libtpu", "Failed to find host bounds"):
    assert noise not in unset.stderr, unset.stderr
  assert results["unset"][1]["views"] == results["cpu"][1]["views"]
  assert "1 device(s)" in unset.stdout and os.cpu_count()


@pytest.mark.parametrize("name,num_chips,hosts,kind", [
    ("v4-8", 4, 1, "v4"), ("v4-32", 16, 4, "v4"), ("v5p-128", 64, 16, "v5p"), ("v5e-16", 16, 4, "v5e"),
    ("v5litepod-64", 64, 16, "v5e"), ("v5e-256", 256, 64, "v5e"), ("v6e-64", 64, 16, "v6e")])
def test_named_pods_have_the_chips_and_hosts_of_their_accelerator_type(name, num_chips, hosts, kind):
  """v4 and v5p names count TensorCores (two per chip), v5e and v6e names count chips; 4 chips per host."""
  from nerfpod.pod import chips
  pod = chips.lookup(name)
  assert (pod.num_chips, pod.num_hosts, pod.generation) == (num_chips, hosts, kind)
  assert pod.chip.hbm_bytes >= 16 * 2**30 and pod.chip.source.startswith("https://cloud.google.com/tpu/docs/")
  assert chips.lookup("v5e-17") is None


@needs_libtpu
@pytest.mark.parametrize("model", [
    # The quick loop's: the MLP field without proposals (4 s of TPU compile rather than 10; the step's collectives
    # are the same kind, the gradient mean's, over fewer parameters).
    ["--config.model.field=mlp", "--config.render.proposal_samples=()"],
    # The smoke model itself, hash grid and proposals, in the gate.
    pytest.param([], marks=pytest.mark.slow)], ids=["mlp", "smoke"])
def test_two_slices_compile_as_one_program_with_the_cross_slice_reduction_over_dcn_as_its_own_collective(model):
  """Multi-slice (the small case): 2 slices of v5e-4 (8 chips on 2 hosts), the smoke step; the gradient mean
  runs within each slice over ICI and across the slices over DCN, reported with its bytes and costed at v5e's
  published DCN bandwidth."""
  out = _aot("--config=configs/default.py:smoke", *model, "--topology=v5e-4", "--slices=2", "--what=step",
             "--json=-")
  assert out.returncode == 0, out.stderr
  report = json.loads(out.stdout)
  assert (report["slices"], report["chips"], report["hosts"]) == (2, 8, 2)
  assert report["mesh"] == {"slice": 2, "data": 4} and report["host_rows_contiguous"]
  assert report["chip"]["dcn_bytes_per_s"] == pytest.approx(6.4e12 / 8 / 256)
  step = report["step"]
  dcn = [c for c in step["collectives"] if c["network"] == "dcn"]
  assert dcn and all(c["op"] == "all-reduce" and c["group"] == 2 and c["bytes"] > 0 for c in dcn)
  # Each chip sends its share of the gradients across the slices, not all of them: at most the gradients.
  across = sum(c["bytes"] * c["count"] for c in dcn)
  assert 0 < across <= report["param_bytes"] + 4096
  within = [c for c in step["collectives"] if c["network"] == "ici"]
  assert within and all(c["group"] == 4 for c in within)  # within a slice: its 4 chips
  assert step["unexpected_collectives"] == []
  assert step["seconds_split"]["dcn"] == pytest.approx(
      sum(2 * (2 - 1) / 2 * c["bytes"] * c["count"] for c in dcn) / report["chip"]["dcn_bytes_per_s"])
  assert 0 < step["seconds_split"]["dcn"] < step["seconds_split"]["collectives"] < step["seconds"]
  assert "2 slices of v5litepod-4 joined by DCN (v5e:2x2, 8 chips of TPU v5 lite on 2 hosts)" in out.stderr
  assert "per chip across 2 slices (DCN)" in out.stderr and "DCN between slices: 3.12 GB/s per chip" in out.stderr


@needs_libtpu
def test_a_config_whose_slices_are_not_the_topologys_is_one_sentence():
  """In a process of its own: refused once libtpu has described the topology's devices (libtpu loaded into the
  process, with the variables the tool sets before it loads)."""
  line = _one_sentence(_aot("--config=configs/default.py:smoke", "--topology=v5e-4", "--slices=2",
                            "--config.mesh.slices=4", "--what=step"))
  assert "mesh.slices=4 but the 8 devices are in 2 slices" in line


@pytest.mark.slow
@needs_libtpu
def test_two_slices_of_v5e_256_compile_every_program_of_the_default_config(tmp_path):
  """--topology=v5e-256 --slices=2 with the default config (512 chips on 128 hosts)
  compiles the step and both renderers over every chip of both slices, exit 0, and reports the DCN
  collective (about 100 s on a 2-core CPU)."""
  report_path = tmp_path / "report.json"
  out = _aot("--config=configs/default.py", "--topology=v5e-256", "--slices=2", f"--json={report_path}", timeout=900)
  assert out.returncode == 0, out.stderr
  report = json.loads(report_path.read_text())
  assert (report["slices"], report["chips"], report["hosts"]) == (2, 512, 128)
  for name in ("step", "eval", "orbit"):
    assert report[name]["fits_hbm"] and report[name]["seconds"] > 0
    assert report[name]["rays_per_s_per_chip"] == pytest.approx(report[name]["rays_per_s"] / 512)
  dcn = [c for c in report["step"]["collectives"] if c["network"] == "dcn"]
  assert dcn and report["step"]["seconds_split"]["dcn"] > 0
  assert report["step"]["unexpected_collectives"] == []
  assert "per chip across 2 slices (DCN)" in out.stdout
