"""The sweep that would have caught the orbit on v5e pods: the smoke config's train step, evaluation renderer
and orbit renderer compiled by the real TPU compiler (libtpu, the `tpu` extra) for one pod of every
generation and host-count class that behaves differently, in parallel processes of the pod compile tool.

v5e pods of 32 chips and more (several hosts, limited ICI routing) refuse a program on some of the slice's
chips, which one-host pods (v4-8, v5e-8, v6e-8) and v4, v5p and v6e pods accept: every program of a run spans
the whole slice (tests/test_whole_slice.py checks a run on CPU), and this checks that each compiles for each.
Skipped, saying so, where libtpu is absent."""
import concurrent.futures
import json
import subprocess
import sys
import time

import pytest

from procs import REPO
from test_aot import _aot, needs_libtpu

pytestmark = [pytest.mark.slow, needs_libtpu]

# Generation x host-count class: one host (v4-8: 4 chips; v5e-8, v6e-8: 8 chips on one host), a few hosts
# (v4-16: 8 chips on 2 hosts, whose report is also checked in detail below), v5e from 32 chips on (limited ICI
# routing: whole-slice programs only), v5p, v6e's largest. The largest v5e (v5e-256) is compiled by
# tests/test_aot.py, two slices of it with the default config's every program.
SWEEP = ["v4-8", "v4-16", "v5e-8", "v5e-32", "v5p-16", "v6e-8", "v6e-256"]
PROCESSES = 4  # each compiles one or two pods (one process start-up per two); the cores do the rest


def _compile(pods: list[str], folder) -> tuple[subprocess.CompletedProcess, list[dict]]:
  path = folder / f"{'_'.join(pods)}.json"
  out = _aot("--config=configs/default.py:smoke", f"--topology={','.join(pods)}", f"--json={path}")
  if out.returncode != 0:
    return out, []
  reports = json.loads(path.read_text())
  return out, reports if isinstance(reports, list) else [reports]


def test_every_program_compiles_for_a_pod_of_every_generation_and_host_class(tmp_path):
  groups = [SWEEP[i::PROCESSES] for i in range(PROCESSES)]
  started = time.perf_counter()
  with concurrent.futures.ThreadPoolExecutor(PROCESSES) as pool:
    results = list(pool.map(lambda pods: _compile(pods, tmp_path), groups))
  seconds = time.perf_counter() - started
  failures = [f"{pods}: exit {out.returncode}: {out.stderr.strip().splitlines()[-1:]}"
              for pods, (out, _) in zip(groups, results) if out.returncode != 0]
  assert not failures, failures
  reports = {r["pod"]: r for _, rs in results for r in rs}
  from nerfpod.pod import chips
  assert sorted(reports) == sorted(chips.lookup(name).name for name in SWEEP)
  for name, report in reports.items():
    pod = chips.lookup(name)
    assert (report["chips"], report["hosts"]) == (pod.num_chips, pod.num_hosts), name
    for program in ("step", "eval", "orbit"):
      r = report[program]
      assert r["fits_hbm"] and r["seconds"] > 0 and r["rays_per_s"] > 0, (name, program)
      # Every program over every chip of the pod: per-chip figures are the pod's over all its chips.
      assert r["rays_per_s_per_chip"] == pytest.approx(r["rays_per_s"] / pod.num_chips), (name, program)
    assert report["orbit"]["rays"] == 1024 * pod.num_hosts  # orbit.chunk (smoke) from each host
    assert report["eval"]["collectives"] == [] and report["orbit"]["collectives"] == []
    assert [c["op"] for c in report["step"]["collectives"]] == ["all-reduce"], name
    assert all(c["group"] == pod.num_chips for c in report["step"]["collectives"]), name
    assert report["step"]["unexpected_collectives"] == [] and report["host_rows_contiguous"], name
  for out, _ in results:
    assert "Failed to find host bounds" not in out.stderr + out.stdout  # libtpu's start-up noise kept out
  v4_16_out = next(out for pods, (out, _) in zip(groups, results) if "v4-16" in pods)
  _check_a_multi_host_pod_in_detail(reports[chips.lookup("v4-16").name], v4_16_out)
  each = {n: sum(reports[chips.lookup(n).name][p]["compile_seconds"] for p in ("step", "eval", "orbit"))
          for n in SWEEP}
  print(f"\nsweep: {len(SWEEP)} pods x 3 programs in {PROCESSES} processes: {seconds:.0f} s (compiling: "
        f"{', '.join(f'{n} {t:.0f} s' for n, t in each.items())})")


def _check_a_multi_host_pod_in_detail(report, out):
  """v4-16 (8 chips, megacore, on 2 hosts): memory, the step's one all-reduce of the gradients and the figures
  the tool prints."""
  assert (report["chips"], report["hosts"]) == (8, 2)
  assert report["host_rows_contiguous"]  # each host's chips hold the rows that host loads
  for name in ("step", "eval", "orbit"):
    assert 0 < report[name]["memory"]["peak_bytes"] <= 32 * 2**30, name
  step = report["step"]
  # A data-parallel step's only cross-chip traffic: one all-reduce of the gradients and a few scalars.
  reduced = sum(c["bytes"] * c["count"] for c in step["collectives"])
  assert report["param_bytes"] <= reduced <= report["param_bytes"] + 64
  assert step["run_seconds"] == pytest.approx(step["seconds"] * report["num_steps"])
  assert "v4-16 (v4:2x2x2, 8 chips of TPU v4 on 2 hosts)" in out.stdout
  assert "step collectives: the gradient all-reduce and scalars only" in out.stdout


PROBE = r"""
import json, sys
from nerfpod.pod import aot, chips
aot._quiet_libtpu()
import jax, numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
pod = chips.lookup(sys.argv[1])
devices = aot.topology_devices(pod)
def program(chosen):
  mesh = Mesh(np.array(chosen), ("data",))
  x = jax.ShapeDtypeStruct((8 * len(chosen), 3), np.float32, sharding=NamedSharding(mesh, P("data")))
  return lambda: jax.jit(lambda x: x * 2.0 + 1.0).lower(x).compile()
host = [d for d in devices if d.process_index == devices[0].process_index]
out = {}
for name, chosen in (("one chip", devices[-1:]), ("one host", host), ("every chip", devices)):
  try:
    aot._compile("orbit", program(chosen), pod, len(chosen), 8 * len(chosen))
    out[name] = "compiled"
  except aot.CompileError as e:
    out[name] = str(e)
print(json.dumps(out))
"""


@pytest.mark.parametrize("name,one_host_compiles", [("v5e-32", False), ("v5e-16", True), ("v6e-64", True)])
def test_which_pods_refuse_a_program_on_one_hosts_chips(name, one_host_compiles):
  """What the rule rests on, with the TPU compiler itself: v5e-32 refuses a program on one host's 4 chips
  (in one sentence naming the program, the pod and XLA's reason) while it compiles one on a single chip or
  on every chip; pods that route any chip subset accept all three."""
  env = __import__("procs").environment(1)
  env.pop("JAX_PLATFORMS")
  out = subprocess.run([sys.executable, "-c", PROBE, name], cwd=REPO, env=env, capture_output=True, text=True,
                       timeout=300)
  assert out.returncode == 0, out.stderr[-2000:]
  result = json.loads(out.stdout.strip().splitlines()[-1])
  assert result["one chip"] == result["every chip"] == "compiled"
  if one_host_compiles:
    assert result["one host"] == "compiled"
  else:
    assert result["one host"].startswith("the orbit renderer does not compile for v5litepod-32 (32 chips on 8 "
                                         "hosts): INTERNAL: RET_CHECK failure")
    assert "should include all slice devices" in result["one host"] and "\n" not in result["one host"]
