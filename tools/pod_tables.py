"""The README's pod tables, in one command: every config's train step compiled for named TPU pods, here.

    python -m tools.pod_tables [--pods=v4-32,v5e-64,v5p-128] [--out=FILE.md]

Three tables, each from nerfpod.pod.aot.compile_pod (the real step, XLA's TPU compiler, hlo_cost's
roofline on the chips' published peaks; estimates, not measurements):
1. per config and pod: per-chip memory, step time, rays/s, share of the bf16 peak, time of the whole run;
2. weak scaling: the default config's step with 256 rays per chip on v5e pods of 16 to 256 chips: step
   time and the all-reduce's share of it;
3. formulations on v5e-64: the hash grid's lookup by gather (and scatter-add) against the matmul lookup
   of its dense levels, and the MLP's matmuls in float32 against bfloat16.
A config whose batch or micro-batches do not split over a pod is shown with one micro-batch, and says so.
"""
import importlib
import os
import time

from absl import app, flags

from nerfpod import config_util
from nerfpod.pod import chips
from nerfpod.errors import UserError

_PODS = flags.DEFINE_list("pods", ["v4-32", "v5e-64", "v5p-128"], "Pods of the first table.")
_CONFIGS = flags.DEFINE_list("configs", ["default", "tiny", "blender", "blender_fast"],
                             "Configs (files in configs/) of the first table.")
_SCALING = flags.DEFINE_list("scaling", ["v5e-16", "v5e-32", "v5e-64", "v5e-128", "v5e-256"],
                             "Pods of the weak-scaling table (default, 256 rays per chip).")
_OUT = flags.DEFINE_string("out", None, "Also write the tables (markdown) to this file.")
_SECTIONS = flags.DEFINE_list("sections", ["configs", "scaling", "formulations"],
                              "Which tables (several processes can share the work).")


def load_config(name: str, **overrides):
  return config_util.override(importlib.import_module(f"configs.{name}").get_config(None), **overrides)


def _report(config, pod, note: list):
  """compile_pod's report of the step; None (with the reason in `note`) where the batch does not split."""
  from nerfpod.pod import aot
  try:
    return aot.compile_pod(config, pod, ("step",))
  except UserError as e:
    if config.train.microbatches == 1 or config.train.batch_size % pod.num_chips:
      note.append(str(e))
      return None
    note.append(f"{config.train.microbatches} micro-batches do not split over {pod.num_chips} chips: 1")
    config.train.microbatches = 1
    return aot.compile_pod(config, pod, ("step",))


def _time(seconds) -> str:
  from nerfpod.pod import aot
  return "n/a" if seconds is None else aot.duration(seconds)


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


def main(argv):
  del argv
  started = time.perf_counter()
  out = []
  if "configs" in _SECTIONS.value:
    out += ["| config | pod | rays/chip | memory/chip (peak) | step | rays/s/chip | rays/s pod | bf16 peak | "
            "whole run |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
  for name in _CONFIGS.value if "configs" in _SECTIONS.value else ():
    for pod_name in _PODS.value:
      config, note = load_config(name), []
      report = _report(config, chips.lookup(pod_name), note)
      out.append(_row(name, report, note) if report else _row(name, None, [f"{pod_name}: "] + note))
      print(out[-1], flush=True)
  if "scaling" in _SECTIONS.value:
    out += ["", "| pod | chips | hosts | batch | step | all-reduce | its share | rays/s pod |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |"]
  for pod_name in _SCALING.value if "scaling" in _SECTIONS.value else ():
    pod = chips.lookup(pod_name)
    config = load_config("default", **{"train.batch_size": 256 * pod.num_chips})
    step = _report(config, pod, [])["step"]
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
    step = _report(config, pod, [])["step"]
    split = step["seconds_split"]
    out.append(f"| `{name}` | {label} | {_time(step['seconds'])} | {_time(split['memory_bound'])} | "
               f"{_time(split['gather_scatter'])} | {step['flops_per_chip'] / 1e9:,.1f} G | "
               f"{_gib(step['memory']['peak_bytes'])} |")
    print(out[-1], flush=True)
  text = "\n".join(out)
  print(f"\n{text}\n\n({time.perf_counter() - started:.0f} s; load: {os.getloadavg()})", flush=True)
  if _OUT.value:
    with open(_OUT.value, "w") as f:
      f.write(text + "\n")


if __name__ == "__main__":
  from nerfpod.pod import aot
  aot._quiet_libtpu()
  app.run(main)
