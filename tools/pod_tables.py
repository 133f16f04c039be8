"""docs/pod-compile.md's pod tables, in one command: every config's programs compiled for named TPU pods, here.

    python -m tools.pod_tables [--pods=v4-32,v5e-64,v5p-128,v6e-64] [--sections=...] [--out=FILE.md]

Five tables, each from nerfpod.pod.aot.compile_pod (the real programs, XLA's TPU compiler, hlo_cost's
roofline on the chips' published peaks; estimates, not measurements), headed by the versions, date, machine
and command that made them:
1. per config and pod, the train step: per-chip memory, step time, rays/s, share of the bf16 peak, time of
   the whole run;
2. per config and pod, the renderers (evaluation and orbit, each over the whole pod): rays per call,
   per-chip memory, time per call and rays/s;
3. weak scaling: the default config's step with 256 rays per chip on v5e pods of 16 to 256 chips: step
   time and the all-reduce's share of it;
4. formulations on v5e-64: the hash grid's lookup by gather (and scatter-add) against the matmul lookup
   of its dense levels, and the MLP's matmuls in float32 against bfloat16;
5. multi-slice weak scaling (--sections=multislice, not in the default sections: minutes per row): the
   default config's step with 256 rays per chip on 1, 2 and 4 slices of v5e-256 joined by DCN: step time,
   the collectives' time and the part of it across the slices.
A config whose batch or micro-batches do not split over a pod is shown with one micro-batch, and says so; a
program the compiler refuses is shown as refused, with XLA's reason.
"""
import datetime
import importlib
import os
import platform
import sys
import time

from absl import app, flags

from nerfpod import config_util
from nerfpod.pod import chips
from nerfpod.errors import UserError

_PODS = flags.DEFINE_list("pods", ["v4-32", "v5e-64", "v5p-128", "v6e-64"], "Pods of the per-config tables.")
_CONFIGS = flags.DEFINE_list("configs", ["default", "tiny", "blender", "blender_fast"],
                             "Configs (files in configs/) of the first table.")
_SCALING = flags.DEFINE_list("scaling", ["v5e-16", "v5e-32", "v5e-64", "v5e-128", "v5e-256"],
                             "Pods of the weak-scaling table (default, 256 rays per chip).")
_SLICE_COUNTS = flags.DEFINE_list("slice_counts", ["1", "2", "4"], "Slice counts of the multi-slice table.")
_SLICE_POD = flags.DEFINE_string("slice_pod", "v5e-256", "The slice of the multi-slice table.")
_OUT = flags.DEFINE_string("out", None, "Also write the tables (markdown) to this file.")
_SECTIONS = flags.DEFINE_list("sections", ["configs", "scaling", "formulations"],
                              "Which tables (several processes can share the work): configs (the step and "
                              "renderer tables), scaling, formulations, multislice.")


def load_config(name: str, **overrides):
  return config_util.override(importlib.import_module(f"configs.{name}").get_config(None), **overrides)


def _report(config, pod, note: list, what=("step",), slices: int = 1):
  """compile_pod's report of `what`; None (with the reason in `note`) where the batch does not split or the
  compiler refuses a program."""
  from nerfpod.pod import aot
  try:
    try:
      return aot.compile_pod(config, pod, what, slices)
    except UserError as e:
      if config.train.microbatches == 1 or config.train.batch_size % pod.num_chips:
        note.append(str(e))
        return None
      note.append(f"{config.train.microbatches} micro-batches do not split over {pod.num_chips} chips: 1")
      config.train.microbatches = 1
      return aot.compile_pod(config, pod, what)
  except aot.CompileError as e:
    note.append(f"refused by XLA: {e}")
    return None


def _time(seconds) -> str:
  from nerfpod import text
  return "n/a" if seconds is None else text.duration(seconds)


def _gib(n) -> str:
  return f"{n / 2**30:.2f} GiB"


def _row(name: str, report: dict | None, note: list) -> str:
  if report is None:
    return f"| `{name}` | | | refused: {' '.join(note)} | | | | | |"
  step = report["step"]
  memory = step["memory"]
  if step["seconds"] is None:
    return (f"| `{name}` | {report['pod']} | {report['rays_per_chip']:,} | {_gib(memory['peak_bytes'])} (does not fit) "
            f"| n/a | n/a | n/a | n/a | n/a |")
  return (f"| `{name}`{' (' + '; '.join(note) + ')' if note else ''} | {report['pod']} | {report['rays_per_chip']:,} "
          f"| {_gib(memory['peak_bytes'])} | {_time(step['seconds'])} | {step['rays_per_s_per_chip']:,.0f} "
          f"| {step['rays_per_s']:,.0f} | {100 * step['bf16_peak_share']:.2f}% "
          f"| {_time(step['run_seconds'])} ({report['num_steps']:,} steps) |")


def _renderer_cells(report: dict, program: str) -> str:
  r = report[program]
  if r["seconds"] is None:
    return f"{r['rays']:,} | {_gib(r['memory']['peak_bytes'])} (does not fit) | n/a | n/a"
  return f"{r['rays']:,} | {_gib(r['memory']['peak_bytes'])} | {_time(r['seconds'])} | {r['rays_per_s']:,.0f}"


def provenance(seconds: float) -> str:
  """When, where and with what the tables were made."""
  import jax
  import jaxlib
  from importlib import metadata
  try:
    libtpu = metadata.version("libtpu")
  except metadata.PackageNotFoundError:
    libtpu = "absent"
  cpu = platform.processor() or platform.machine()
  try:
    with open("/proc/cpuinfo") as f:
      cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
  except (OSError, StopIteration):
    pass
  load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
  command = " ".join(["python -m tools.pod_tables", *sys.argv[1:]])
  return (f"Made on {datetime.date.today().isoformat()} by `{command}` with JAX {jax.__version__}, jaxlib "
          f"{jaxlib.__version__} "
          f"and libtpu {libtpu}, on a {os.cpu_count()}-core {cpu} (Python {platform.python_version()}, load "
          f"average {load} at the end), in {seconds / 60:.0f} min.")


def main(argv):
  del argv
  started = time.perf_counter()
  out, renderers = [], []
  if "configs" in _SECTIONS.value:
    out += ["| config | pod | rays/chip | memory/chip (peak) | step | rays/s/chip | rays/s pod | bf16 peak | "
            "whole run |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    renderers += ["| config | pod | eval: rays/call | memory/chip | time/call | rays/s pod | orbit: rays/call | "
                  "memory/chip | time/call | rays/s pod |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- "
                  "| --- |"]
  for name in _CONFIGS.value if "configs" in _SECTIONS.value else ():
    for pod_name in _PODS.value:
      config, note = load_config(name), []
      report = _report(config, chips.lookup(pod_name), note, ("step", "eval", "orbit"))
      out.append(_row(name, report, note) if report else _row(name, None, [f"{pod_name}: "] + note))
      print(out[-1], flush=True)
      if report is not None:
        renderers.append(f"| `{name}` | {report['pod']} | {_renderer_cells(report, 'eval')} | "
                         f"{_renderer_cells(report, 'orbit')} |")
        print(renderers[-1], flush=True)
  if renderers:
    out += [""] + renderers
  if "scaling" in _SECTIONS.value:
    out += ["", "| pod | chips | hosts | batch | step | all-reduce | its share | rays/s pod |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |"]
  for pod_name in _SCALING.value if "scaling" in _SECTIONS.value else ():
    pod = chips.lookup(pod_name)
    config = load_config("default", **{"train.batch_size": 256 * pod.num_chips})
    note = []
    report = _report(config, pod, note)
    if report is None:
      out.append(f"| {pod.name} | {pod.num_chips} | {pod.num_hosts} | {256 * pod.num_chips:,} | refused: "
                 f"{' '.join(note)} | | | |")
      print(out[-1], flush=True)
      continue
    step = report["step"]
    collective = step["seconds_split"]["collectives"]
    out.append(f"| {pod.name} | {pod.num_chips} | {pod.num_hosts} | {256 * pod.num_chips:,} | "
               f"{_time(step['seconds'])} | {_time(collective)} | {100 * collective / step['seconds']:.2f}% | "
               f"{step['rays_per_s']:,.0f} |")
    print(out[-1], flush=True)
  if "formulations" in _SECTIONS.value:
    out += ["", "| config | formulation | step | memory-bound | gathers/scatters | matmul FLOPs/chip | "
            "memory/chip |", "| --- | --- | --- | --- | --- | --- | --- |"]
  pod = chips.lookup("v5e-64")
  for name, label, overrides in () if "formulations" not in _SECTIONS.value else (
      ("default", "hash grid: gather + scatter-add", {"compile.hashgrid_lookup": "gather"}),
      ("default", "hash grid: matmul for dense levels (auto on TPU)", {}),
      ("blender_fast", "hash grid: gather + scatter-add", {"compile.hashgrid_lookup": "gather"}),
      ("blender_fast", "hash grid: matmul for dense levels (auto on TPU)", {}),
      ("blender", "MLP: float32 matmuls", {}),
      ("blender", "MLP: bfloat16 matmuls", {"model.compute_dtype": "bfloat16"})):
    config = load_config(name, **overrides)
    note = []
    report = _report(config, pod, note)
    if report is None:
      out.append(f"| `{name}` | {label} | refused: {' '.join(note)} | | | | |")
      print(out[-1], flush=True)
      continue
    step = report["step"]
    split = step["seconds_split"]
    out.append(f"| `{name}` | {label} | {_time(step['seconds'])} | {_time(split['memory_bound'])} | "
               f"{_time(split['gather_scatter'])} | {step['flops_per_chip'] / 1e9:,.1f} G | "
               f"{_gib(step['memory']['peak_bytes'])} |")
    print(out[-1], flush=True)
  if "multislice" in _SECTIONS.value:
    out += ["", "| slices | chips | hosts | batch | step | collectives | of which across slices (DCN) | DCN bytes "
            "per chip | rays/s | per slice |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
  for count in [int(n) for n in _SLICE_COUNTS.value] if "multislice" in _SECTIONS.value else ():
    pod = chips.lookup(_SLICE_POD.value)
    chips_total = pod.num_chips * count
    config = load_config("default", **{"train.batch_size": 256 * chips_total})
    note = []
    report = _report(config, pod, note, slices=count)
    if report is None:
      out.append(f"| {count} x {pod.name} | {chips_total} | | | refused: {' '.join(note)} | | | | | |")
      print(out[-1], flush=True)
      continue
    step = report["step"]
    split = step["seconds_split"]
    dcn_bytes = sum(c["bytes"] * c["count"] for c in step["collectives"] if c["network"] == "dcn")
    out.append(f"| {count} x {pod.name} | {chips_total} | {report['hosts']} | {256 * chips_total:,} | "
               f"{_time(step['seconds'])} | {_time(split['collectives'])} | {_time(split['dcn'])} | "
               f"{dcn_bytes / 2**10:,.0f} KiB | {step['rays_per_s']:,.0f} | {step['rays_per_s'] / count:,.0f} |")
    print(out[-1], flush=True)
  text = "\n".join([provenance(time.perf_counter() - started), ""] + out)
  print(f"\n{text}", flush=True)
  if _OUT.value:
    with open(_OUT.value, "w") as f:
      f.write(text + "\n")


if __name__ == "__main__":
  from nerfpod.pod import aot
  aot._quiet_libtpu()
  app.run(main)
