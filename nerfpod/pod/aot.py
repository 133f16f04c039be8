"""The pod, proven before it is paid for: compile a config's train step and renderers for a TPU pod, here.

    nerfpod aot --config=configs/blender_fast.py --topology=v5e-64 [--json=FILE]

(also `python -m nerfpod.pod.aot ...`).

XLA compiles for a TPU topology ahead of time on a machine without TPUs (it needs libtpu: `pip install -e
'.[tpu]'`). This builds the pod's device mesh as a run on it would (distributed.make_mesh over the
topology's chips, hosts in order), lays the global batch over it as each host feeds it (ShapeDtypeStructs
with the batch's sharding: no data is loaded), and compiles the very functions a run compiles, from the one
builder a run uses (components.build_program): the train step (step.compile_fitted, micro-batches fitted to
85% of a chip's HBM where train.microbatches=0, as a run on the pod fits them), the evaluation renderer over
the whole pod (eval.chunk rays) and the orbit renderer, also over the whole pod (orbit.chunk rays from each
host: every host feeds its own frame's rays, nerfpod.run.orbit). Every program spans every chip of the pod, as
every program of a run does (TPU v5e refuses a program on some of a slice's chips). It reports
per-chip memory against the chip's HBM, FLOPs and bytes per step, the estimated step time (hlo_cost's
roofline; XLA's own figures beside it where they are sane), the step's lookups (slices gathered and
scattered per chip, at the chip's per-index time, and their bytes), rays/s for the pod and per chip (the
pod's over its chips), every collective in the step with its size and the mesh axes it runs over, a region
model's traffic between its regions per step (model.regions > 1: region_traffic) and its rays and field
evaluations per chip (a chip holds its region group's rays and renders its own regions, dense and with
model.region_capacity: region_figures), and the estimated time of the config's train.num_steps. Estimates
from XLA's program and the chips' published peaks, not measurements. A program too large for a chip is a
report too (fits_hbm false, with XLA's figures), not a crash.

Nothing it is given ends in a traceback: a topology it does not know (or none), a config file that does not
load, a bad flag, override or --json path, a config whose batch does not split over the pod: one sentence,
`nerfpod: error: ...`, exit 2 (the flags are read as every subcommand reads them: errors.parse_flags);
a program the TPU compiler refuses: one sentence naming the program, the pod and XLA's reason, exit 1.
With --json=-, stdout holds the JSON report alone (the tables go to stderr).
"""
import dataclasses
import json
import os
import sys
import time

from absl import flags
from ml_collections import config_flags

from nerfpod import schema
from nerfpod.errors import Command, UserError, fail
from nerfpod.pod import chips
from nerfpod.text import byte_size, duration

ABOUT = "compile a config for a TPU pod topology here, and report memory and time"
# Its own flags (not absl's global ones): tools.pod_tables imports this module beside flags of its own.
FLAGS = flags.FlagValues()
config_flags.DEFINE_config_file(
    "config", None, "Config file, e.g. configs/default.py[:arg]; a field is overridden as "
    "--config.section.name=value "
    "(`python -m nerfpod.schema` lists every field, its default, range and meaning).",
    flag_values=FLAGS, lock_config=True)
_TOPOLOGY = flags.DEFINE_string("topology", None, "The pod: an accelerator type, e.g. v4-32, v5e-64 (= "
                                "v5litepod-64), v5p-128, v6e-64; several, comma-separated.", flag_values=FLAGS)
_SLICES = flags.DEFINE_integer("slices", 1, "Multi-slice: this many slices of the --topology pod, joined by the "
                               "data-centre network (DCN), e.g. --topology=v5e-256 --slices=2 (512 chips).",
                               flag_values=FLAGS)
_WHAT = flags.DEFINE_list("what", ["step", "eval", "orbit"], "What to compile: step, eval, orbit.",
                          flag_values=FLAGS)
_JSON = flags.DEFINE_string("json", None, "Also write the report as JSON to this file ('-': stdout only).",
                            flag_values=FLAGS)


def _quiet_libtpu() -> None:
  """libtpu, loaded to compile for a TPU on a machine without one, looks for the VM's TPU metadata and
  prints pages of warnings when it finds none; naming a stand-in host and type keeps the output readable.
  Nothing runs on a TPU here: the TPU backend only compiles."""
  os.environ.setdefault("TPU_ACCELERATOR_TYPE", "v5litepod-4")
  os.environ.setdefault("TPU_WORKER_HOSTNAMES", "localhost")
  os.environ.setdefault("TPU_SKIP_MDS_QUERY", "1")
  # libtpu takes a machine-wide lock file (/tmp/libtpu_lockfile) so that two processes never drive one TPU;
  # compiling drives none, so several of these tools (and a test suite) may run side by side.
  os.environ.setdefault("ALLOW_MULTIPLE_LIBTPU_LOAD", "1")
  os.environ.setdefault("JAX_PLATFORMS", "cpu")  # the process itself runs nothing on a device
  if "jax" in sys.modules:  # a caller imported JAX first, and JAX read JAX_PLATFORMS then
    import jax
    if not jax.config.jax_platforms:
      jax.config.update("jax_platforms", "cpu")


def resolve_pods(names: str) -> list[chips.Pod]:
  out = []
  for name in [n.strip() for n in names.split(",") if n.strip()]:
    pod = chips.lookup(name)
    if pod is None:
      raise UserError(f"unknown --topology={name}; known pods: {', '.join(chips.known_names())} (v5e-N is "
                      f"v5litepod-N).")
    out.append(pod)
  return out


def check_slices(slices: int) -> None:
  if slices < 1:
    raise UserError(f"--slices={slices} must be 1 (one slice) or more (multi-slice: slices joined by the "
                    f"data-centre network), e.g. --slices=2.")


def pod_label(pod: chips.Pod, slices: int = 1) -> str:
  """The pod as reports name it: v5litepod-64, or 2 x v5litepod-256 for two slices."""
  return pod.name if slices == 1 else f"{slices} x {pod.name}"


def topology_devices(pod: chips.Pod, slices: int = 1):
  """The TPU devices (every host's) of `slices` slices of the pod, from libtpu's description of the topology:
  with several, each device carries its slice_index, as on a multi-slice run."""
  check_slices(slices)
  try:
    from jax.experimental import topologies
    return topologies.get_topology_desc(platform="tpu", topology_name=pod.topology_name,
                                        chip_config_name=pod.chip_config,
                                        chips_per_host_bounds=pod.chips_per_host, num_slices=slices).devices
  except Exception as e:  # no libtpu, or one that does not know the generation (or the slices)
    what = f"the {pod.name} topology" if slices == 1 else f"{slices} slices of the {pod.name} topology"
    fix = ("install the TPU compiler with pip install -c constraints.txt -e '.[tpu]'" if slices == 1 else
           "compile one slice (--slices=1), or install the TPU compiler matched to JAX with pip install -c "
           "constraints.txt -e '.[tpu]'")
    raise UserError(f"cannot describe {what} on this machine ({str(e).splitlines()[0][:200]}); {fix}.") from None


def _memory(compiled) -> dict:
  m = compiled.memory_analysis()
  argument, output, temp = m.argument_size_in_bytes, m.output_size_in_bytes, m.temp_size_in_bytes
  alias = m.alias_size_in_bytes
  return {"argument_bytes": argument, "output_bytes": output, "temp_bytes": temp, "alias_bytes": alias,
          "code_bytes": m.generated_code_size_in_bytes,
          # Donated arguments are reused for the outputs they alias: they are not held twice.
          "peak_bytes": argument + output - alias + temp + m.generated_code_size_in_bytes}


def _xla_cost(compiled) -> dict:
  cost = compiled.cost_analysis()
  cost = cost[0] if isinstance(cost, (list, tuple)) else (cost or {})
  optimal = float(cost.get("optimal_seconds", -1.0))
  return {"flops": float(cost.get("flops", 0.0)), "bytes_accessed": float(cost.get("bytes accessed", 0.0)),
          # XLA's TPU estimate: kept only where it is a time at all (it came back negative for these steps).
          "optimal_seconds": optimal if optimal > 0 else None}


def _roofline(compiled, pod: chips.Pod, num_devices: int, slices: int = 1, mesh_axes: dict | None = None):
  from nerfpod.pod import hlo_cost
  return hlo_cost.HloProgram(compiled.as_text(), pod.chip, num_devices, slices, mesh_axes).cost()


def _program_report(compiled, pod: chips.Pod, num_devices: int, rays: int, seconds_to_compile: float,
                    slices: int = 1, mesh_axes: dict | None = None) -> dict:
  cost = _roofline(compiled, pod, num_devices, slices, mesh_axes)
  memory = _memory(compiled)
  rate = pod.chip.gather_indices_per_s
  seconds = cost.seconds
  return {
      "compile_seconds": round(seconds_to_compile, 1),
      "memory": memory, "fits_hbm": memory["peak_bytes"] <= pod.chip.hbm_bytes,
      "hbm_bytes": pod.chip.hbm_bytes,
      "flops_per_chip": cost.flops, "bytes_per_chip": cost.bytes, "vmem_bytes_per_chip": cost.vmem_bytes,
      "seconds": seconds,
      "seconds_split": {"matmul_bound": cost.compute_seconds, "memory_bound": cost.memory_seconds,
                        "index_bound": cost.index_bound_seconds, "gather_scatter": cost.gather_scatter_seconds,
                        "collectives": cost.collective_seconds, "dcn": cost.dcn_seconds},
      # The gathers and scatters (hash-grid lookups and their gradients), per chip: slices gathered or
      # scattered, their time by index count alone (hlo_cost: per-index rates, chips.py), their HBM bytes.
      "lookups": {"indices": cost.indices, "vmem_indices": cost.vmem_indices,
                  "seconds_per_index": 1 / rate if rate else None,
                  "vmem_seconds_per_index": 1 / rate / pod.chip.vmem_gather_speedup if rate else None,
                  "index_seconds": cost.index_seconds, "bytes": cost.gather_scatter_bytes,
                  "seconds": cost.gather_scatter_seconds},
      "bf16_peak_share": (cost.flops / seconds / pod.chip.bf16_flops) if seconds > 0 else 0.0,
      "rays": rays, "rays_per_s": rays / seconds if seconds > 0 else None,
      "rays_per_s_per_chip": rays / seconds / num_devices if seconds > 0 else None,
      "collectives": _merge_collectives(cost.collectives),
      "xla": _xla_cost(compiled),
  }


_SIZE_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def _out_of_memory_report(error: Exception, pod: chips.Pod, rays: int, seconds_to_compile: float) -> dict | None:
  """The report of a program XLA refused to compile because it does not fit the chip's HBM (None: the
  error is another). XLA's message names what it needed and what the chip has, e.g. 'the total memory
  required for HLO temporaries (108.00G) exceeds available HBM (15.75G)'."""
  import re
  text = " ".join(str(error).split())
  if "RESOURCE_EXHAUSTED" not in text and "Ran out of memory" not in text:
    return None
  sizes = [float(n) * _SIZE_UNITS[u] for n, u in re.findall(r"\(([0-9.]+)([KMGT]?)i?B?\)", text)]
  needed, available = (sizes + [float("nan"), float("nan")])[:2]
  return {
      "compile_seconds": round(seconds_to_compile, 1), "compile_error": text[:400],
      "memory": {"argument_bytes": 0, "output_bytes": 0, "temp_bytes": needed, "alias_bytes": 0, "code_bytes": 0,
                 "peak_bytes": needed, "xla_available_bytes": available},
      "fits_hbm": False, "hbm_bytes": pod.chip.hbm_bytes, "flops_per_chip": None, "bytes_per_chip": None,
      "vmem_bytes_per_chip": None, "seconds": None, "seconds_split": None, "lookups": None, "bf16_peak_share": None,
      "rays": rays, "rays_per_s": None, "rays_per_s_per_chip": None, "collectives": [], "xla": None,
  }


PROGRAMS = {"step": "the train step", "eval": "the evaluation renderer", "orbit": "the orbit renderer"}


class CompileError(Exception):
  """XLA refused to compile one of the programs for the pod (not for want of memory: that is a report)."""

  def __init__(self, program: str, pod: chips.Pod, reason: str, slices: int = 1):
    self.program, self.pod, self.reason = program, pod, reason
    super().__init__(f"{PROGRAMS[program]} does not compile for {pod_label(pod, slices)} ({pod.num_chips * slices} "
                     f"chips on {pod.num_hosts * slices} hosts): {reason}")


def _reason(error: Exception) -> str:
  """XLA's reason in one line: the error's first line that says something, whitespace collapsed (an error
  other than XLA's runtime error is named by its type)."""
  import jax
  lines = [" ".join(line.split()) for line in str(error).splitlines()]
  text = next((line for line in lines if line), "")
  if not isinstance(error, jax.errors.JaxRuntimeError):
    text = f"{type(error).__name__}: {text}" if text else type(error).__name__
  return text if len(text) <= 400 else text[:397] + "..."


def _compile(program: str, compile_fn, pod: chips.Pod, num_devices: int, rays: int, slices: int = 1,
             mesh_axes: dict | None = None) -> dict:
  """compile_fn() and its report; a program too large for the chip is a report too (fits_hbm false), not a
  crash; any other refusal is a CompileError naming the program, the pod (its slices) and XLA's reason.
  `mesh_axes` (the program's mesh, name -> size): each collective names the axes it runs over."""
  import jax
  start = time.perf_counter()
  try:
    compiled = compile_fn()
  except UserError:
    raise
  except jax.errors.JaxRuntimeError as e:
    report = _out_of_memory_report(e, pod, rays, time.perf_counter() - start)
    if report is None:
      raise CompileError(program, pod, _reason(e), slices) from None
    return report
  except Exception as e:  # noqa: BLE001 (lowering or compiling failed in another way: still one sentence)
    raise CompileError(program, pod, _reason(e), slices) from None
  return _program_report(compiled, pod, num_devices, rays, time.perf_counter() - start, slices, mesh_axes)


def _explained(error: CompileError, config, pod: chips.Pod, slices: int) -> CompileError:
  """A refusal of compile.hashgrid_lookup=sparsecore's kernels (Mosaic's indexed DMA), with what it means and
  what to use instead; any other refusal as it is."""
  if config.compile.hashgrid_lookup != "sparsecore" or "enqueue_indirect_dma" not in error.reason:
    return error
  features = config.model.hashgrid.features_per_level
  return CompileError(error.program, pod, f"{error.reason} (Mosaic's indexed DMA on the SparseCores refuses "
                      f"the hash grid's rows of {features} values, so compile.hashgrid_lookup=sparsecore does not "
                      f"compile for {pod.generation}; use --config.compile.hashgrid_lookup=auto: "
                      f"docs/pod-compile.md, \"A SparseCore lookup\")", slices)


def _merge_collectives(collectives: list) -> list:
  merged = {}
  for c in collectives:
    key = (c.get("network", "ici"), c["op"], c["bytes"], c["group"], c.get("axes"))
    merged[key] = merged.get(key, 0) + c["count"]
  out = []
  ordered = sorted(merged.items(), key=lambda item: (item[0][:4], item[0][4] or ()))  # axes: None or a tuple
  for (network, op, size, group, axes), count in ordered:
    out.append({"op": op, "bytes": size, "group": group, "network": network, "count": count})
    if axes is not None:
      out[-1]["axes"] = list(axes)
  return out


def region_traffic(step: dict) -> dict:
  """What a region model's step (model.regions > 1) moves between its regions and for its gradients, per
  step and chip, from the compiled step's collectives within a slice (their mesh axes, hlo_cost): the
  partial sums all-gathered over the region axis (bytes each chip holds after the gathers: every region's
  per-ray sums of its group's rays; it receives (K - 1) / K of them from the other chips of the axis), what
  is reduced over the region axis (the gradient norm's sums, the replicated per-frame tables' gradients, and
  per-ray terms that XLA sums over the axis instead of gathering them, as the interlevel loss's on a large
  pod), and the gradient mean over the batch's axes within the slice (1/K of the region fields' gradients,
  the replicated ones whole); `other_region_bytes`, any other collective over the region axis."""
  ici = [c for c in step["collectives"] if c.get("network", "ici") == "ici" and c.get("axes") is not None]
  total = lambda chosen: int(sum(c["bytes"] * c["count"] for c in chosen))  # noqa: E731
  over_region = [c for c in ici if "region" in c["axes"]]
  gathers = [c for c in over_region if c["op"] == "all-gather" and c["axes"] == ["region"]]
  reduces = [c for c in over_region if c["op"] in ("all-reduce", "reduce-scatter")]
  mean = [c for c in ici if "region" not in c["axes"] and c["axes"] and c["op"] in ("all-reduce", "reduce-scatter")]
  return {"gathered_bytes": total(gathers), "gathers": int(sum(c["count"] for c in gathers)),
          "region_reduce_bytes": total(reduces), "gradient_mean_bytes": total(mean),
          "other_region_bytes": total([c for c in over_region if c not in gathers and c not in reduces])}


def region_figures(batch: int, batch_devices: int, regions: int, region_axis: int, field_samples: int,
                   microbatches: int, capacity: float = 0.0, split_capacity: tuple = (),
                   split_by: str = "length", sample_counts: tuple = ()) -> dict:
  """A region model's rays and field evaluations per chip and step (docs/scale.md, "Dispatch and capacity"),
  from its shapes: a chip holds its region group's rays, `batch` / `batch_devices` (the chips of the batch's
  axes: data, and slice), and renders L = `regions` / `region_axis` regions; each micro-batch (of
  `microbatches`) gives each region R rows, or C = regions.capacity_rows(`capacity`, R) with
  model.region_capacity (a fraction: 'auto' is measured before, step.measure_for_tool); a row costs
  `field_samples` field evaluations (sum of NeRF.sample_counts(): the proposal rounds' and the NeRF's). The
  same figures as the step's regions/field_evals_per_chip (dense: L x R x field_samples x microbatches).
  `field_evals_per_chip` is the step's as configured (compacted where a capacity is set, dense otherwise);
  `field_evals_per_chip_dense` the dense step's beside it. With model.region_split, `split_capacity` is each
  sample class's fraction: `class_rows` its C_j, `class_samples` its field samples per row, and by length a chip's
  evaluations sum C_j x samples over the classes (`capacity_rows` their sum). With `split_by` 'weights' the NeRF
  round's rows are the weight classes' (`final_rows`: regions.final_capacities). Either way the evaluations are
  regions.split_evals of the model's `sample_counts` (NeRF.sample_counts()), as the step's."""
  from nerfpod.nerf import regions as regions_lib
  microbatches = max(1, microbatches)
  rays_per_chip = batch // batch_devices
  rows = rays_per_chip // microbatches  # R: one micro-batch's rays on one chip
  local = regions // region_axis
  dense = local * rows * field_samples * microbatches
  capacity_rows = regions_lib.capacity_rows(capacity, rows) if capacity else None
  out = {"regions": regions, "region_axis": region_axis, "regions_per_chip": local,
         "batch_devices": batch_devices, "rays_per_chip": rays_per_chip, "microbatches": microbatches,
         "rows_per_region": rows, "field_samples_per_ray": field_samples, "capacity": capacity or 0.0,
         "capacity_rows": capacity_rows, "field_evals_per_chip_dense": dense,
         "field_evals_per_chip": (local * capacity_rows * field_samples * microbatches if capacity_rows
                                  else dense)}
  if capacity and split_capacity:
    class_rows = [regions_lib.capacity_rows(f, rows) for f in split_capacity]
    out.update(split_capacity=list(split_capacity), class_rows=class_rows, capacity_rows=sum(class_rows),
               class_samples=list(regions_lib.class_samples(tuple(sample_counts), len(class_rows))),
               field_evals_per_chip=local * regions_lib.split_evals(tuple(sample_counts), tuple(class_rows),
                                                                    split_by) * microbatches)
    if split_by == "weights":
      out.update(split_by=split_by, final_rows=list(regions_lib.final_capacities(tuple(class_rows))))
  return out


def check_collectives(step: dict, state_bytes: int, slices: int = 1, regions: bool = False) -> list[str]:
  """What in the step's collectives is not a data-parallel step's: on one slice, anything but all-reduces,
  or all-reduces beyond the gradients plus a few scalars. Across slices the TPU compiler splits the
  gradients' all-reduce in three: within each slice (ICI: an all-reduce or reduce-scatter), across the slices
  (DCN: an all-reduce of each chip's share, or of a small gradient whole), and an all-gather of the shares
  within each slice; anything else, more than the (padded) gradients on either network, or no cross-slice
  reduction at all, is reported. A region model's step (`regions`) also gathers its partial sums over the
  region axis (all-gathers over that axis alone: region_traffic)."""
  ici = [c for c in step["collectives"] if c.get("network", "ici") == "ici"
         and not (regions and c["op"] == "all-gather" and c.get("axes") == ["region"])]
  dcn = [c for c in step["collectives"] if c.get("network") == "dcn"]
  within = ("all-reduce",) if slices == 1 else ("all-reduce", "reduce-scatter", "all-gather")
  problems = [f"{c['op']} of {c['bytes']} bytes" for c in ici if c["op"] not in within]
  problems += [f"{c['op']} of {c['bytes']} bytes across slices" for c in dcn if c["op"] != "all-reduce"]
  reduced = sum(c["bytes"] * c["count"] for c in ici if c["op"] in ("all-reduce", "reduce-scatter"))
  # Across slices the compiler pads each gradient to whole shares of the slice's chips before the reduction
  # (1.9% more bytes for the default config on 2 x v5e-256): a 5% allowance for that padding.
  allowance = 4096 if slices == 1 else 4096 + state_bytes // 20
  if reduced > state_bytes + allowance:
    problems.append(f"all-reduces of {reduced} bytes, more than the gradients' {state_bytes}")
  across = sum(c["bytes"] * c["count"] for c in dcn if c["op"] == "all-reduce")
  if across > state_bytes + allowance:
    problems.append(f"all-reduces across slices of {across} bytes, more than the gradients' {state_bytes}")
  if slices > 1 and not dcn:
    problems.append(f"no reduction across the {slices} slices")
  return problems


def compile_pod(config, pod: chips.Pod, what=("step", "eval", "orbit"), slices: int = 1) -> dict:
  """Compiles `config`'s programs for `slices` slices of `pod` (multi-slice where more than one: every
  program spans every chip of every slice) and reports on them (see the module's docstring)."""
  import jax
  import numpy as np
  from nerfpod import distributed
  from nerfpod.run import compilation, components, step

  check_slices(slices)
  num_chips = pod.num_chips * slices
  # e.g. a batch that does not split over the pod's chips, or a SparseCore lookup for a pod without them
  schema.validate(config, num_chips, backend="tpu", tpu_generation=pod.generation, pod=pod.name)
  devices = topology_devices(pod, slices)
  mesh = distributed.make_mesh(devices, num_slices=config.mesh.slices or None, regions=config.model.regions)
  measured = step.measure_for_tool(config, mesh)  # model.region_capacity=auto: on a built-in scene, or refused
  if measured is not None:
    config = step.with_capacity(config, measured.fraction, measured.split_fractions)
  # (a fitted train.microbatches=0 widens a measured capacity's margin for its micro-batch: step.fitted_capacity)
  program = dataclasses.replace(components.build_program(config, mesh, backend="tpu"), capacity_measured=measured)
  tc = config.train
  hosts = sorted({d.process_index for d in devices})
  order = [d.process_index for d in mesh.devices.flat]
  report = {
      "pod": pod.name, "topology": pod.topology_name, "slices": slices, "chips": num_chips, "hosts": len(hosts),
      "mesh": dict(mesh.shape),
      "chip": {"kind": pod.chip.name, "bf16_flops": pod.chip.bf16_flops, "hbm_bytes": pod.chip.hbm_bytes,
               "hbm_bytes_per_s": pod.chip.hbm_bytes_per_s,
               "allreduce_bytes_per_s": pod.chip.allreduce_bytes_per_s, "source": pod.chip.source,
               "dcn_bytes_per_s": pod.chip.dcn_bytes_per_s, "gather_indices_per_s": pod.chip.gather_indices_per_s,
               "vmem_gather_speedup": pod.chip.vmem_gather_speedup, "vmem_bytes_per_s": pod.chip.vmem_bytes_per_s},
      # A chip's rays: the batch over the chips of the batch's axes (every chip, or with regions the data and
      # slice axes: each chip of a region group renders the group's rays, through its own regions).
      "batch": tc.batch_size, "rays_per_chip": tc.batch_size // distributed.batch_devices(mesh),
      "microbatches": tc.microbatches,
      "compute_dtype": config.model.compute_dtype,
      "hashgrid_matmul_max_rows": program.model.grid_matmul_max_rows,
      # Each host's chips hold one contiguous block of the batch: the rows distributed.local_slice loads.
      "host_rows_contiguous": all(order[i] <= order[i + 1] for i in range(len(order) - 1)),
      "num_steps": tc.num_steps,
  }
  state_bytes = sum(int(np.prod(s.shape)) * s.dtype.itemsize for s in jax.tree.leaves(program.state_shapes.params))
  report["param_bytes"] = state_bytes
  key = jax.ShapeDtypeStruct((), jax.random.key(0).dtype, sharding=distributed.replicated(mesh))
  try:
    _compile_programs(report, config, program, pod, what, key, num_chips, hosts, slices, mesh)
  except CompileError as e:
    raise _explained(e, config, pod, slices) from None
  if config.model.regions > 1:  # with the step's micro-batches where it was compiled (fitted), and its capacity
    config = step.fitted_capacity(program, report["microbatches"]).config
    report["regions"] = region_figures(tc.batch_size, distributed.batch_devices(mesh), config.model.regions,
                                       distributed.num_regions(mesh), sum(program.model.sample_counts()),
                                       report["microbatches"], float(config.model.region_capacity),
                                       **_split_figures(config, program.model))
  return report


def _split_figures(config, model) -> dict:
  """region_figures' keywords for model.region_split > 1 (each class's fraction, what picks the NeRF round's
  classes, the model's sample counts), else none."""
  from nerfpod.nerf import regions as regions_lib
  classes = int(config.model.region_split)
  fractions = regions_lib.class_capacities(config.model.region_capacity, classes,
                                           tuple(config.model.region_split_capacity))
  if not fractions:
    return {}
  return dict(split_capacity=fractions, split_by=config.model.region_split_by,
              sample_counts=tuple(model.sample_counts()))


def _compile_programs(report: dict, config, program, pod: chips.Pod, what, key, num_chips: int, hosts: list,
                      slices: int, mesh) -> None:
  """compile_pod's compiles of `what`, each program's report into `report`."""
  import jax
  import numpy as np
  from nerfpod import distributed
  from nerfpod.run import compilation, step
  tc = config.train
  state_bytes = report["param_bytes"]
  if "step" in what:
    # As a run on the pod fits them where train.microbatches=0: the fewest that fit its share of the HBM.
    budget = int(compilation.ACCELERATOR_MEMORY_SHARE * pod.chip.hbm_bytes)
    fitted = {}

    def compile_step():
      fitted["microbatches"], compiled, _ = step.compile_fitted(program, key, budget, backend="tpu")
      return compiled
    report["step"] = _compile("step", compile_step, pod, num_chips, tc.batch_size, slices, dict(mesh.shape))
    # Where XLA refused the step as too large: train.microbatches as configured (0: refused while fitting).
    report["microbatches"] = fitted.get("microbatches", tc.microbatches)
    step_report = report["step"]
    step_report["unexpected_collectives"] = check_collectives(step_report, state_bytes, slices,
                                                              regions=config.model.regions > 1)
    if config.model.regions > 1 and step_report["seconds"] is not None:
      step_report["region_traffic"] = region_traffic(step_report)
    step_report["run_seconds"] = (step_report["seconds"] * tc.num_steps if step_report["seconds"] is not None
                                  else None)
  params = program.state_shapes.params
  if "eval" in what:
    chunk = max(num_chips, config.eval.chunk - config.eval.chunk % num_chips)
    rays = jax.ShapeDtypeStruct((chunk, 3), np.float32, sharding=distributed.batch_sharding(mesh))
    report["eval"] = _compile("eval", lambda: program.make_renderer().lower(params, rays, rays).compile(), pod,
                              num_chips, chunk, slices)
  if "orbit" in what:
    # The orbit's call: every host feeds orbit.chunk rays (rounded to its chips) of its own frame, on its
    # own chips, into the one renderer over the whole pod (nerfpod.run.orbit).
    per_host = num_chips // len(hosts)
    chunk = max(per_host, config.orbit.chunk - config.orbit.chunk % per_host) * len(hosts)
    orbit_rays = jax.ShapeDtypeStruct((chunk, 3), np.float32, sharding=distributed.batch_sharding(mesh))
    report["orbit"] = _compile("orbit", lambda: program.make_renderer().lower(params, orbit_rays, orbit_rays)
                               .compile(), pod, num_chips, chunk, slices)


def format_report(report: dict) -> str:
  """The report as a readable table."""
  slices = report.get("slices", 1)
  where = report["pod"] if slices == 1 else f"{slices} slices of {report['pod']} joined by DCN"
  lines = [f"{where} ({report['topology']}, {report['chips']} chips of {report['chip']['kind']} on "
           f"{report['hosts']} hosts): batch {report['batch']} rays, {report['rays_per_chip']} per chip, "
           f"{report['microbatches']} micro-batch(es), {report['compute_dtype']} matmuls, hash-grid matmul "
           f"lookup up to {report['hashgrid_matmul_max_rows']} rows",
           f"  {'program':<7} {'args':>9} {'temp':>9} {'out':>9} {'peak':>9} {'HBM':>8} {'GFLOP':>9} "
           f"{'GB':>8} {'est. time':>10} {'XLA est.':>9} {'rays/s/chip':>12} {'rays/s pod':>12} {'compile':>8}"]
  for name in ("step", "eval", "orbit"):
    if name not in report:
      continue
    r = report[name]
    m = r["memory"]
    if r["seconds"] is None:
      lines.append(f"  {name:<7} does not fit: XLA needs {byte_size(m['peak_bytes'])} of temporaries, the chip has "
                   f"{byte_size(m['xla_available_bytes'])} ({r['compile_error'][:160]})")
      continue
    xla = r["xla"]["optimal_seconds"]
    lines.append(
        f"  {name:<7} {byte_size(m['argument_bytes']):>9} {byte_size(m['temp_bytes']):>9} "
        f"{byte_size(m['output_bytes']):>9} "
        f"{byte_size(m['peak_bytes']):>9} {('fits' if r['fits_hbm'] else 'OVER'):>8} {r['flops_per_chip'] / 1e9:>9.3f} "
        f"{r['bytes_per_chip'] / 1e9:>8.3f} {duration(r['seconds']):>10} "
        f"{(duration(xla) if xla else 'n/a'):>9} {r['rays_per_s_per_chip'] or 0:>12,.0f} "
        f"{(r['rays_per_s'] or 0):>12,.0f} {r['compile_seconds']:>7.1f}s")
  if "regions" in report:
    g = report["regions"]
    lines.append(f"  regions: {g['regions']} over a region axis of {g['region_axis']}, {g['regions_per_chip']} per "
                 f"chip; each chip holds its region group's {g['rays_per_chip']} rays (the batch over the "
                 f"{g['batch_devices']} chips of the batch's axes)")
    evals = (f"{g['regions_per_chip']} region(s) x {{}} rows x {g['field_samples_per_ray']} samples x "
             f"{g['microbatches']} micro-batch(es)")
    dense = f"{evals.format(g['rows_per_region'])} = {g['field_evals_per_chip_dense']:,} dense"
    if g.get("final_rows"):  # (by weights: the proposal rounds' rows, then the NeRF round's)
      share = g["field_evals_per_chip"] / g["field_evals_per_chip_dense"]
      lines.append(f"  field evaluations per chip and step: {g['regions_per_chip']} region(s) x the proposal "
                   f"rounds on {' + '.join(str(c) for c in g['class_rows'])} rows of the length classes and the "
                   f"NeRF round on {' + '.join(str(c) for c in g['final_rows'])} rows of the weight classes x "
                   f"{g['microbatches']} micro-batch(es) = {g['field_evals_per_chip']:,} ({share:.3g} of dense: "
                   f"{dense})")
    elif g.get("class_rows"):
      classes = " + ".join(f"{c} rows x {n} samples" for c, n in zip(g["class_rows"], g["class_samples"]))
      share = g["field_evals_per_chip"] / g["field_evals_per_chip_dense"]
      lines.append(f"  field evaluations per chip and step: {g['regions_per_chip']} region(s) x ({classes}) x "
                   f"{g['microbatches']} micro-batch(es) = {g['field_evals_per_chip']:,} with model.region_split's "
                   f"{len(g['class_rows'])} sample classes ({share:.3g} of dense: {dense})")
    elif g["capacity_rows"]:
      lines.append(f"  field evaluations per chip and step: {evals.format(g['capacity_rows'])} = "
                   f"{g['field_evals_per_chip']:,} at model.region_capacity={g['capacity']:g} "
                   f"({g['field_evals_per_chip'] / g['field_evals_per_chip_dense']:.3g} of dense: {dense})")
    else:
      lines.append(f"  field evaluations per chip and step: {dense}")
  if "step" in report and report["step"]["seconds"] is not None:
    s = report["step"]
    split = s["seconds_split"]
    lines.append(f"  step time: {duration(split['matmul_bound'])} matmul-bound ops, "
                 f"{duration(split['memory_bound'])} memory-bound, {duration(split['index_bound'])} bound by "
                 f"gather/scatter indices (gathers/scatters in all {duration(split['gather_scatter'])}), "
                 f"{duration(split['collectives'])} collectives"
                 + (f" (of which across slices over DCN {duration(split.get('dcn', 0.0))})" if slices > 1 else "")
                 + f"; {100 * s['bf16_peak_share']:.2f}% of the bf16 peak")
    lookups = s["lookups"]
    if lookups["indices"]:
      per_index = (f"{1e9 * lookups['seconds_per_index']:.3g} ns each ({1e9 * lookups['vmem_seconds_per_index']:.3g} "
                   f"ns from VMEM), {duration(lookups['index_seconds'])} by index count"
                   if lookups["seconds_per_index"] else "no per-index rate for this chip")
      lines.append(f"  lookups per step and chip: {lookups['indices']:,.0f} slices gathered or scattered (of which "
                   f"{lookups['vmem_indices']:,.0f} in VMEM tables) at {per_index}; "
                   f"{byte_size(lookups['bytes'])} of HBM traffic; {duration(lookups['seconds'])} of the step")
    for c in s["collectives"]:
      if c.get("network") == "dcn":
        lines.append(f"  collective: {c['op']} of {byte_size(c['bytes'])} per chip across {c['group']} slices (DCN), "
                     f"x{c['count']:g}")
      else:
        axes = f" ({' x '.join(c['axes'])} axis)" if c.get("axes") else ""
        lines.append(f"  collective: {c['op']} of {byte_size(c['bytes'])} over {c['group']} chips{axes}, "
                     f"x{c['count']:g}")
    verdict = "; ".join(s["unexpected_collectives"]) or (
        "the gradient all-reduce and scalars only" if slices == 1 else
        "the gradient all-reduce (within each slice, then across the slices over DCN) and scalars only")
    if "region_traffic" in s and not s["unexpected_collectives"]:
      verdict = verdict.replace(" and scalars only", ", the regions' partial sums gathered and scalars only")
    lines.append(f"  step collectives: {verdict}")
    if "region_traffic" in s:
      t, regions = s["region_traffic"], report["mesh"].get("region", 1)
      lines.append(f"  region traffic per step and chip: {byte_size(t['gathered_bytes'])} of partial sums all-gathered "
                   f"over the region axis ({t['gathers']:g} gather(s); {regions - 1}/{regions} of it from the other "
                   f"{regions - 1} chips), {byte_size(t['region_reduce_bytes'])} reduced over the region axis, "
                   f"{byte_size(t['gradient_mean_bytes'])} in the gradient mean over the batch's axes"
                   + (f", {byte_size(t['other_region_bytes'])} other over the region axis" if t["other_region_bytes"]
                      else ""))
    lines.append(f"  {report['num_steps']} steps (train.num_steps): {duration(s['run_seconds'])} estimated")
  if slices > 1:
    dcn = report["chip"].get("dcn_bytes_per_s")
    lines.append(f"  DCN between slices: {dcn / 1e9:.3g} GB/s per chip ({report['chip']['source']}: data-centre "
                 f"network bandwidth per pod over its chips)" if dcn else
                 f"  DCN between slices: no published bandwidth for {report['chip']['kind']}; the time across "
                 f"slices is left out of the estimates")
  lines.append(f"  host rows contiguous: {report['host_rows_contiguous']}; HBM per chip "
               f"{byte_size(report['chip']['hbm_bytes'])} ({report['chip']['source']}); times are estimates (XLA's "
               f"compiled program on the chip's published peaks: nerfpod.pod.hlo_cost), not measurements")
  return "\n".join(lines)


def _check_json_path(path: str | None) -> None:
  """--json names a file that can be written once the compiles (minutes) are done: checked first."""
  if not path or path == "-":
    return
  if os.path.isdir(path):
    raise UserError(f"--json={path} is a folder; name a file, e.g. --json={os.path.join(path, 'report.json')} "
                    f"(or --json=- for stdout).")
  folder = os.path.dirname(os.path.abspath(path))
  if not os.path.isdir(folder):
    raise UserError(f"--json={path}: its folder {folder} does not exist; create it or name another file.")
  if not os.access(folder, os.W_OK):
    raise UserError(f"--json={path}: its folder {folder} is not writable; name another file.")


def main(config):
  """Compiles the checked config for each pod asked for; prints the reports (and writes --json). Exit 1 with one
  sentence where the compiler refuses a program, or anything else fails unexpectedly."""
  try:
    _compile_and_report(config)
  except UserError:
    raise
  except CompileError as e:
    fail(str(e), code=1)
  except Exception as e:  # noqa: BLE001 (a tool's user gets one sentence, never a traceback)
    fail(f"compiling failed unexpectedly: {_reason(e)}", code=1)


def _compile_and_report(config) -> None:
  _quiet_libtpu()
  to_json = _JSON.value == "-"
  tables = sys.stderr if to_json else sys.stdout  # --json=-: stdout is the JSON report alone
  if not [name for name in (_TOPOLOGY.value or "").split(",") if name.strip()]:
    raise UserError(f"--topology is empty; name the pod to compile for, e.g. --topology=v5e-64 (known pods: "
                    f"{', '.join(chips.known_names())}).")
  chosen = resolve_pods(_TOPOLOGY.value)
  what = [w.strip() for w in _WHAT.value if w.strip()]
  if not what or set(what) - set(PROGRAMS):
    raise UserError(f"--what={','.join(_WHAT.value)}: choose one or more of step, eval, orbit.")
  _check_json_path(_JSON.value)
  check_slices(_SLICES.value)
  reports = []
  for pod in chosen:
    report = compile_pod(config, pod, tuple(what), _SLICES.value)
    print(format_report(report), file=tables, flush=True)
    reports.append(report)
  text = json.dumps(reports if len(reports) > 1 else reports[0], indent=2)
  if to_json:
    print(text, flush=True)
  elif _JSON.value:
    try:
      with open(_JSON.value, "w") as f:
        f.write(text + "\n")
    except OSError as e:
      raise UserError(f"could not write --json={_JSON.value} ({e.strerror or e}).") from None


def run(argv: list[str] | None = None) -> None:
  """`nerfpod aot ...` and `python -m nerfpod.pod.aot ...` (argv: the words after it; None: sys.argv[1:])."""
  Command("nerfpod aot", ABOUT, FLAGS, required=("config", "topology"), check=schema.validate,
          examples={"config": "configs/default.py", "topology": "v5e-64", "what": "step,eval"}).run(argv, main)


if __name__ == "__main__":
  run()
