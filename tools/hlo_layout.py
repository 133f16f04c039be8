"""Which large arrays of a compiled TPU train step keep a narrow minor dimension, and what its ops cost.

    python -m tools.hlo_layout --config=configs/blender_fast.py:scene=lego --topology=v5e-8 \
        [--config.compile.hashgrid_layout=lane_dense] [--min_bytes=1048576] [--top=25] [--hlo=FILE] [--json=FILE]

Compiles the config's train step for the pod as `nerfpod aot` does (the one builder a run uses,
components.build_program, and step.compile_fitted: micro-batches fitted to 85% of a chip's HBM where
train.microbatches=0), then reads the optimised HLO:

- narrow arrays: every array an op outside a fusion writes (a buffer in HBM or VMEM) of at least
  `--min_bytes` in its layout whose physical minor dimension (the first of the layout's minor_to_major) has
  at most 8 elements under a tile 128 lanes wide, e.g. `f32[65536,8,2]{1,0,2:T(8,128)}`: 8 values in each
  128-lane row, 16 times its values' bytes. `narrow_arrays(hlo_text)` is the check, for tests;
- the ops that cost most under nerfpod.pod.hlo_cost's roofline (seconds, bound, bytes, indices), each with
  its result's layout and the JAX operation it came from (its metadata's op_name), and the step's time split
  by what the ops came from (`by_source`: the optimiser's update, the lookups and their gradient, the rest).

`--hlo=FILE` keeps the HLO text. Nothing runs on a TPU: libtpu compiles for the topology here (as `nerfpod
aot`; docs/pod-compile.md, "Lane-dense hash-grid lookups", has what it found).
"""
import dataclasses
import json
import re
import sys

from absl import app, flags
from ml_collections import config_flags

FLAGS = flags.FlagValues()
_CONFIG = config_flags.DEFINE_config_file("config", None, "Config file, e.g. configs/blender_fast.py:scene=lego",
                                          flag_values=FLAGS, lock_config=True)
_TOPOLOGY = flags.DEFINE_string("topology", "v5e-8", "The pod, as nerfpod aot names it.", flag_values=FLAGS)
_MIN_BYTES = flags.DEFINE_integer("min_bytes", 1 << 20, "Narrow arrays of at least this many bytes (in their "
                                  "layout) are listed.", flag_values=FLAGS)
_TOP = flags.DEFINE_integer("top", 25, "The ops that cost most: how many to list.", flag_values=FLAGS)
_HLO = flags.DEFINE_string("hlo", None, "Write the optimised HLO text to this file.", flag_values=FLAGS)
_JSON = flags.DEFINE_string("json", None, "Write the report as JSON to this file.", flag_values=FLAGS)

NARROW = 8  # a physical minor dimension of at most this many elements under a 128-lane tile is "narrow"


@dataclasses.dataclass(frozen=True)
class Narrow:
  """An array whose minor dimension fills at most NARROW of a tile's 128 lanes."""
  computation: str
  instruction: str
  opcode: str
  array: str       # e.g. f32[65536,8,2]{1,0,2:T(8,128)S(1)}
  bytes: int       # in its layout (padded)
  values_bytes: int
  source: str      # the JAX operation it came from (metadata op_name), '' where none

  @property
  def padding(self) -> float:
    return self.bytes / max(self.values_bytes, 1)


def _fused_computations(computations) -> set[str]:
  """Computations called by fusions (their ops write no buffers of their own)."""
  fused = set()
  for instrs in computations.values():
    for i in instrs:
      if i.opcode == "fusion" and i.attr("calls"):
        fused.add(i.attr("calls").lstrip("%"))
  return fused


def _source(instr) -> str:
  match = re.search(r'op_name="([^"]*)"', instr.attributes)
  return match.group(1) if match else ""


def narrow_arrays(hlo_text: str, min_bytes: int = 1 << 20) -> list[Narrow]:
  """The arrays of at least `min_bytes` (in their layout) that ops outside fusions write, whose physical minor
  dimension has at most NARROW elements under a tile 128 lanes (or more) wide; largest first."""
  from nerfpod.pod import hlo_cost
  computations, _ = hlo_cost.parse_module(hlo_text)
  fused = _fused_computations(computations)
  found = []
  for name, instrs in computations.items():
    if name in fused:
      continue
    for instr in instrs:
      if instr.opcode in ("parameter", "get-tuple-element", "tuple", "bitcast", "constant"):
        continue  # no buffer of their own (parameters: the entry's are listed as the ops that use them write)
      for array in instr.shape:
        tile = array.tile()
        physical = array.physical_dims()
        if len(physical) < 2 or len(tile) < 2 or tile[-1] < 128 or physical[-1] > NARROW:
          continue
        if array.bytes < min_bytes:
          continue
        text = f"{array.dtype}[{','.join(map(str, array.dims))}]{array.layout}"
        found.append(Narrow(name, instr.name, instr.opcode, text, array.bytes, array.payload_bytes, _source(instr)))
  return sorted(found, key=lambda n: -n.bytes)


def _kind(source: str) -> str:
  """What a JAX operation (its op_name) belongs to, for the step's time split."""
  if re.search(r"gather|scatter|_take", source):
    return "lookups (gathers, scatter-adds)"
  if "transpose(jvp(NeRF" in source:
    return "NeRF backward (the rest)"
  if "NeRF" in source:
    return "NeRF forward (the rest)"
  if re.search(r"threefry|_uniform", source):
    return "random numbers"
  return "optimiser, gradient mean, loss" if source else "copies and prefetches (no source)"


def op_costs(hlo_text: str, chip, num_devices: int) -> list[dict]:
  """Every top-level op of the entry computation (a loop as one op: its body times its trips) with its
  roofline cost (nerfpod.pod.hlo_cost), dearest first."""
  from nerfpod.pod import hlo_cost
  program = hlo_cost.HloProgram(hlo_text, chip, num_devices)
  out = []
  for instr in program.computations[program.entry]:
    cost = program._instruction(program.entry, instr)  # noqa: SLF001 (the roofline's own per-op cost)
    if cost.seconds <= 0:
      continue
    bound = ("collective" if cost.collective_seconds else "index" if cost.index_bound_seconds else
             "memory" if cost.memory_seconds else "matmul")
    shape = " ".join(f"{a.dtype}[{','.join(map(str, a.dims))}]{a.layout}" for a in instr.shape[:3])
    out.append({"op": instr.name, "opcode": instr.opcode, "seconds": cost.seconds, "bound": bound,
                "hbm_bytes": cost.bytes, "vmem_bytes": cost.vmem_bytes, "indices": cost.indices,
                "shape": shape, "source": _source(instr), "kind": _kind(_source(instr))})
  return sorted(out, key=lambda o: -o["seconds"])


def compile_step(config, topology: str):
  """(the compiled train step's HLO text, the pod, its chips, micro-batches) as `nerfpod aot` compiles it."""
  from nerfpod.pod import aot
  aot._quiet_libtpu()  # noqa: SLF001 (the pod tool's own set-up)
  import jax
  from nerfpod import distributed, schema
  from nerfpod.run import compilation, components, step
  pod = aot.resolve_pods(topology)[0]
  schema.validate(config, pod.num_chips)
  devices = aot.topology_devices(pod)
  mesh = distributed.make_mesh(devices, num_slices=config.mesh.slices or None, regions=config.model.regions)
  program = components.build_program(config, mesh, backend="tpu")
  key = jax.ShapeDtypeStruct((), jax.random.key(0).dtype, sharding=distributed.replicated(mesh))
  budget = int(compilation.ACCELERATOR_MEMORY_SHARE * pod.chip.hbm_bytes)
  microbatches, compiled, _ = step.compile_fitted(program, key, budget, backend="tpu")
  return compiled.as_text(), pod, pod.num_chips, microbatches


def report(hlo_text: str, chip, num_devices: int, min_bytes: int, top: int) -> dict:
  ops = op_costs(hlo_text, chip, num_devices)
  by_source = {}
  for o in ops:
    by_source[o["kind"]] = by_source.get(o["kind"], 0.0) + o["seconds"]
  narrow = narrow_arrays(hlo_text, min_bytes)
  return {"seconds": sum(o["seconds"] for o in ops), "by_source": by_source,
          "narrow": [dict(dataclasses.asdict(n), padding=round(n.padding, 1)) for n in narrow],
          "top_ops": ops[:top]}


def _mib(n: float) -> str:
  return f"{n / 2**20:.1f} MiB"


def main(argv) -> None:
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {' '.join(argv[1:])}")
  config = _CONFIG.value
  hlo_text, pod, chips_, microbatches = compile_step(config, _TOPOLOGY.value)
  if _HLO.value:
    with open(_HLO.value, "w") as f:
      f.write(hlo_text)
  out = report(hlo_text, pod.chip, chips_, _MIN_BYTES.value, _TOP.value)
  out.update(pod=pod.name, microbatches=microbatches, layout=config.compile.hashgrid_layout,
             batch=config.train.batch_size)
  print(f"{pod.name}: train step of {config.train.batch_size} rays, {microbatches} micro-batch(es), hash-grid "
        f"layout {out['layout']}: {out['seconds'] * 1e3:.2f} ms by the roofline")
  for kind, seconds in sorted(out["by_source"].items(), key=lambda kv: -kv[1]):
    print(f"  {kind:<34} {seconds * 1e3:8.3f} ms")
  print(f"narrow arrays (minor dimension <= {NARROW} under a 128-lane tile, >= {_mib(_MIN_BYTES.value)}): "
        f"{len(out['narrow'])}")
  for n in out["narrow"]:
    print(f"  {n['array']:<48} {_mib(n['bytes']):>10} ({n['padding']:.0f}x) {n['opcode']:<12} {n['source'][:90]}")
  print(f"the {_TOP.value} dearest ops:")
  for o in out["top_ops"]:
    print(f"  {o['seconds'] * 1e3:7.3f} ms {o['bound']:<6} {o['opcode']:<14} {o['shape'][:60]:<60} "
          f"{o['source'][-70:]}")
  if _JSON.value:
    with open(_JSON.value, "w") as f:
      json.dump(out, f, indent=2)


def run(argv=None) -> None:
  from nerfpod.errors import UserError, fail
  argv = list(sys.argv if argv is None else argv)
  try:
    main(FLAGS(argv))
  except (UserError, flags.Error, app.UsageError) as e:  # a bad flag, topology or config: one sentence
    fail(e if isinstance(e, UserError) else str(e), program="tools.hlo_layout", code=2)


if __name__ == "__main__":
  run()
