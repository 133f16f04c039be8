"""A roofline time estimate of a compiled XLA program, op by op, from its optimised HLO text.

XLA's own `cost_analysis()` for TPU programs is not usable as it comes for nerfpod's steps: its
`optimal_seconds` came back negative, and its `bytes accessed` counts a gather or scatter-add as touching
its whole table (hundreds of GB per step for the Instant-NGP grid). This module costs each executed HLO
instruction itself:

- time = max(FLOPs / matmul peak, bytes / HBM bandwidth, indices / index rate) per instruction (a roofline
  per op: each op is bound by the one it needs more of), summed over the program; collectives at the chip's
  all-reduce bandwidth instead (over ICI, within a slice);
- multi-slice programs: the TPU compiler writes a reduction across slices as a host transfer to the
  megascale runtime (a `send` whose frontend attributes name `_xla_megascale_transfer_type`, with its
  `recv` and `-done`s), after a reduction within each slice; that `send` is the DCN collective: its bytes
  are its operand's, each chip's share, reduced over the slices as a ring all-reduce at the chip's share of
  the data-centre network (chips.Chip.dcn_bytes_per_s; its time is left out where no figure is published);
- FLOPs are the matmuls' (`dot` and `convolution`: 2 per multiply-add), at the chip's bf16 peak; a float32
  dot at HIGHEST precision is counted as the 6 bf16 passes it takes (HIGH: 3). Elementwise work runs on the
  vector unit, whose peak Google does not publish: it is costed by its memory traffic only;
- bytes are each op's operands and results as laid out in HBM (padded to the layout's tiles, which the HLO
  names), except that a gather moves only the slices it gathers, a scatter only its updates (read and
  written), a dynamic slice or update only its slice, an asynchronous slice (`slice-start`, whose result
  tuple names its whole source) only its slice read and written; each slice counts at least one tile row of
  its operand's layout (the unit XLA lays memory out in);
- indices: a gather or scatter (alone or in a fusion) also takes time per slice it gathers or scatters (the
  result's batch dims, those not in `offset_dims`; the updates' not in `update_window_dims`), at the chip's
  measured rate (chips.Chip.gather_indices_per_s), `vmem_gather_speedup` times faster where its table is in
  VMEM; scatters at the gathers' rate (no scatter figure is published). A dynamic slice or update, one index,
  stays costed by its bytes (no op here pays a fixed cost per call);
- VMEM: an array whose layout names memory space 1 (`S(1)`, e.g. `f32[1024,2]{1,0:T(8,128)S(1)}`: a table
  XLA prefetched into the TensorCore's vector memory, or a result it keeps there) moves no HBM bytes: its
  bytes are VMEM's, at the chip's VMEM bandwidth (chips.Chip.vmem_bytes_per_s, 22 times HBM's), and an op's
  memory term is the larger of its HBM and VMEM times. The prefetch itself is a copy (or copy-start) from
  HBM, charged its HBM side;
- a Pallas kernel (`custom-call` to `tpu_custom_call`) is costed by the `cost_estimate` its author gave
  `pallas_call` (the compiled HLO keeps it in the call's backend_config: flops at the matmul peak,
  bytes_accessed at HBM bandwidth); one without is costed as any op, by its operands' and results' bytes;
- a fusion is costed as one op: its operands and results cross HBM once, its inner ops are free except for
  their matmul FLOPs and their gathers' and scatters' indices; loops with a known trip count multiply their
  body; a conditional costs its dearest branch.

What it leaves out: overlap of independent ops (an upper bound for compute-bound and a fair figure for
bandwidth-bound programs), vector-unit limits, collective latency (the all-reduce term is
bandwidth only), and the host (input pipeline). The estimate is XLA's program on the chip's published peaks
and measured per-index rates (chips.Chip), not a measurement.
"""
import dataclasses
import math
import re

from nerfpod.pod.chips import Chip

_DTYPE_BYTES = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4, "u32": 4,
                "f32": 4, "s64": 8, "u64": 8, "f64": 8, "c64": 8, "c128": 16, "f8e4m3fn": 1, "f8e5m2": 1,
                "s4": 1, "u4": 1, "token": 0}
_ARRAY = re.compile(r"([a-z][a-z0-9]*)\[([0-9,]*)\](\{[^}]*\})?")
_LINE = re.compile(r"^\s*(ROOT\s+)?%?([\w.\-]+)\s*=\s*(.+?)\s+([a-z][\w\-]*)\((.*)$")
# A host transfer to the megascale runtime: the cross-slice (DCN) part of a multi-slice collective.
_MEGASCALE = re.compile(r'_xla_megascale_transfer_type="?(\w+)')
_FREE = {"parameter", "constant", "get-tuple-element", "tuple", "bitcast", "after-all", "partition-id",
         "replica-id", "iota", "copy-done", "slice-done", "all-reduce-done", "all-gather-done",
         "collective-permute-done", "async-done", "async-update", "send-done", "recv-done", "opt-barrier"}
COLLECTIVES = ("all-reduce", "all-gather", "reduce-scatter", "all-to-all", "collective-permute",
               "collective-broadcast", "ragged-all-to-all")
# Passes of the bf16 matmul unit a float32 dot takes at each precision (DEFAULT: one bf16 pass on TPU).
_PRECISION_PASSES = {"default": 1, "high": 3, "highest": 6}


@dataclasses.dataclass(frozen=True)
class Array:
  dtype: str
  dims: tuple[int, ...]
  layout: str  # e.g. "{1,0:T(8,128)}"

  @property
  def elements(self) -> int:
    return math.prod(self.dims)

  @property
  def in_vmem(self) -> bool:
    """Whether the layout places it in memory space 1, the TensorCore's VMEM (`...:T(8,128)S(1)}`)."""
    return re.search(r"(?<![A-Z])S\(1\)", self.layout) is not None

  @property
  def hbm_bytes(self) -> int:
    """Bytes it takes in HBM: its bytes, or none where it lives in VMEM."""
    return 0 if self.in_vmem else self.bytes

  def tile(self) -> tuple[int, ...]:
    match = re.search(r"T\(([0-9,]+)\)", self.layout)
    return tuple(int(t) for t in match.group(1).split(",")) if match else ()

  def physical_dims(self) -> list[int]:
    """Dims from major to minor (the layout's minor_to_major, reversed)."""
    match = re.match(r"\{([0-9,]*)", self.layout)
    if not match or not match.group(1):
      return list(self.dims)
    order = [int(i) for i in match.group(1).split(",")]
    return [self.dims[i] for i in reversed(order)] if len(order) == len(self.dims) else list(self.dims)

  @property
  def payload_bytes(self) -> int:
    """Bytes of the values alone (what a collective sends), without layout padding."""
    return self.elements * _DTYPE_BYTES.get(self.dtype, 4)

  @property
  def bytes(self) -> int:
    """Bytes in memory: the minor dims padded to the layout's (first) tile."""
    dims = self.physical_dims()
    tile = self.tile()
    for k, t in enumerate(reversed(tile[:len(dims)])):
      dims[-1 - k] = -(-dims[-1 - k] // t) * t
    return math.prod(dims) * _DTYPE_BYTES.get(self.dtype, 4)

  def slice_bytes(self, slice_dims) -> int:
    """Bytes a slice of `slice_dims` (same rank) touches: its minor dim padded to the layout tile's minor
    size, i.e. at least one tile row (e.g. 128 values of an (8, 128) tile: 512 bytes of float32)."""
    order = re.match(r"\{([0-9,]*)", self.layout)
    ranks = [int(i) for i in order.group(1).split(",")][::-1] if order and order.group(1) else list(
        range(len(self.dims)))
    sliced = [slice_dims[i] for i in ranks] if len(ranks) == len(slice_dims) else list(slice_dims)
    tile = self.tile()
    if tile and sliced:
      minor = self.physical_dims()[-1]
      sliced[-1] = min(-(-minor // tile[-1]) * tile[-1], -(-sliced[-1] // tile[-1]) * tile[-1])
    return math.prod(sliced) * _DTYPE_BYTES.get(self.dtype, 4)


def parse_shape(text: str) -> list[Array]:
  """The arrays of a shape string, a tuple's flattened."""
  return [Array(m.group(1), tuple(int(d) for d in m.group(2).split(",") if d), m.group(3) or "")
          for m in _ARRAY.finditer(re.sub(r"/\*.*?\*/", "", text)) if m.group(1) in _DTYPE_BYTES]


@dataclasses.dataclass
class Instruction:
  name: str
  opcode: str
  shape: list[Array]
  operands: list[str]
  attributes: str
  root: bool
  raw_operands: str = ""

  def attr(self, key: str) -> str | None:
    match = re.search(rf"\b{re.escape(key)}=(%?[\w.\-]+|\{{[^}}]*\}})", self.attributes)
    return match.group(1) if match else None

  @property
  def bytes_out(self) -> int:
    return sum(a.bytes for a in self.shape)

  def bytes_in(self, hbm: bool) -> int:
    """Bytes of its result: in HBM only (hbm), or wherever they are."""
    return sum(a.hbm_bytes if hbm else a.bytes for a in self.shape)

  @property
  def in_vmem(self) -> bool:
    return bool(self.shape) and all(a.in_vmem for a in self.shape)


def _split_call(rest: str) -> tuple[str, str]:
  """'a, b), attr=...' -> ('a, b', 'attr=...'): the operand list up to its closing parenthesis."""
  depth = 1
  for i, ch in enumerate(rest):
    depth += {"(": 1, ")": -1}.get(ch, 0)
    if depth == 0:
      return rest[:i], rest[i + 1:]
  return rest, ""


def parse_module(text: str) -> tuple[dict[str, list[Instruction]], str]:
  """{computation name: its instructions}, and the entry computation's name."""
  computations, entry, current = {}, None, None
  for line in text.splitlines():
    header = re.match(r"^(ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$", line)
    if header and not line.startswith(" "):
      current = header.group(2)
      computations[current] = []
      if header.group(1):
        entry = current
      continue
    match = _LINE.match(line)
    if match and current is not None:
      operands, attributes = _split_call(match.group(5))
      computations[current].append(Instruction(
          name=match.group(2), opcode=match.group(4), shape=parse_shape(match.group(3)),
          operands=re.findall(r"%([\w.\-]+)", operands), attributes=attributes, root=bool(match.group(1)),
          raw_operands=operands))
  return computations, entry


@dataclasses.dataclass
class Cost:
  flops: float = 0.0
  bytes: float = 0.0             # HBM's
  vmem_bytes: float = 0.0        # VMEM's (arrays whose layout names S(1))
  seconds: float = 0.0
  compute_seconds: float = 0.0   # the ops whose matmul term was the largest
  memory_seconds: float = 0.0    # the ops whose memory term was the largest
  index_bound_seconds: float = 0.0  # the ops whose per-index term was the largest
  collective_seconds: float = 0.0
  gather_scatter_seconds: float = 0.0  # the ops that gather or scatter, whichever term bound them
  gather_scatter_bytes: float = 0.0    # their HBM bytes
  indices: float = 0.0           # slices gathered and scattered
  vmem_indices: float = 0.0      # of indices: from or into a table in VMEM
  index_seconds: float = 0.0     # the per-index terms of the ops that gather or scatter, bound or not
  dcn_seconds: float = 0.0        # of collective_seconds: the cross-slice (DCN) collectives'
  collectives: list = dataclasses.field(default_factory=list)  # {"op", "bytes", "group", "network", "count"}

  def add(self, other: "Cost", times: float = 1.0) -> None:
    for f in ("flops", "bytes", "vmem_bytes", "seconds", "compute_seconds", "memory_seconds", "index_bound_seconds",
              "collective_seconds", "gather_scatter_seconds", "gather_scatter_bytes", "indices", "vmem_indices",
              "index_seconds", "dcn_seconds"):
      setattr(self, f, getattr(self, f) + times * getattr(other, f))
    for c in other.collectives:
      self.collectives.append(dict(c, count=c["count"] * times))


def first_group(attributes: str) -> tuple[int, ...] | None:
  """The device ids of a collective's first group: its first replica group, written out
  (`replica_groups={{0,1},{2,3}}`) or as an iota (`replica_groups=[2,2]<=[2,2]T(1,0)`: the ids 0..N-1 laid
  out as the dims, transposed, cut into rows), or a collective-permute's first source and target. None
  where the HLO names none (every device)."""
  listed = re.search(r"replica_groups=\{\{([0-9,]+)\}", attributes)
  if listed:
    return tuple(int(i) for i in listed.group(1).split(","))
  iota = re.search(r"replica_groups=\[(\d+),(\d+)\]<=\[([0-9,]+)\](?:T\(([0-9,]+)\))?", attributes)
  if iota:
    import numpy as np
    dims = [int(d) for d in iota.group(3).split(",")]
    ids = np.arange(math.prod(dims)).reshape(dims)
    if iota.group(4):
      ids = ids.transpose([int(a) for a in iota.group(4).split(",")])
    return tuple(int(i) for i in ids.reshape(int(iota.group(1)), int(iota.group(2)))[0])
  pair = re.search(r"source_target_pairs=\{\{(\d+),(\d+)\}", attributes)
  if pair:
    return int(pair.group(1)), int(pair.group(2))
  return None


def mesh_axes_of(group: tuple[int, ...] | None, mesh_axes: dict) -> tuple[str, ...]:
  """The axes of a device mesh (`mesh_axes`: name -> size, major first, the devices numbered in that
  order, as a program's device ids are) along which a group's devices lie: those where their places on the
  mesh differ (a group of one device: none; no group named: every axis)."""
  names, sizes = list(mesh_axes), list(mesh_axes.values())
  if group is None:
    return tuple(names)
  import numpy as np
  places = np.stack(np.unravel_index(np.asarray(group) % math.prod(sizes), sizes), axis=-1)
  return tuple(name for i, name in enumerate(names) if len(set(places[:, i].tolist())) > 1)


def pallas_cost_estimate(instr: Instruction) -> tuple[float, float] | None:
  """(FLOPs, bytes) of a Pallas TPU kernel (a `custom-call` to `tpu_custom_call`) from the `cost_estimate` its
  author gave `pallas_call`, which the compiled HLO keeps in the call's backend_config
  (`"cost_estimate":{"flops":"1234","transcendentals":"5","bytes_accessed":"65536",...}`); None for any other
  op, or a kernel without one."""
  if instr.opcode != "custom-call" or 'custom_call_target="tpu_custom_call"' not in instr.attributes:
    return None
  estimate = re.search(r'"cost_estimate"\s*:\s*\{([^}]*)\}', instr.attributes)
  if not estimate:
    return None
  fields = dict(re.findall(r'"(\w+)"\s*:\s*"?(\d+)', estimate.group(1)))
  return float(fields.get("flops", 0)), float(fields.get("bytes_accessed", 0))


class HloProgram:
  """A compiled program's optimised HLO module, costed on a chip: `HloProgram(compiled.as_text(), chip,
  num_devices).cost()`. The chip's peaks are its published figures (chips.Chip: bf16_flops,
  hbm_bytes_per_s, allreduce_bytes_per_s, dcn_bytes_per_s) and its measured per-index rates
  (gather_indices_per_s, vmem_gather_speedup); `num_devices` is the collectives' group where the HLO names
  none; `num_slices` the slices a DCN collective reduces over. With `mesh_axes` (the program's
  device mesh, name -> size, major first), each collective within a slice also names the mesh `axes` it runs
  over (mesh_axes_of: e.g. ('region',) for a region model's gather of partial sums)."""

  def __init__(self, hlo_text: str, chip: Chip, num_devices: int, num_slices: int = 1,
               mesh_axes: dict | None = None):
    self.computations, self.entry = parse_module(hlo_text)
    self.chip, self.num_devices, self.num_slices = chip, num_devices, num_slices
    self.mesh_axes = dict(mesh_axes) if mesh_axes else None
    self._shapes = {c: {i.name: i for i in instrs} for c, instrs in self.computations.items()}

  def cost(self) -> Cost:
    return self._computation(self.entry)

  def _computation(self, name: str) -> Cost:
    total = Cost()
    for instr in self.computations.get(name, []):
      total.add(self._instruction(name, instr))
    return total

  def _operand(self, computation: str, name: str) -> Instruction | None:
    return self._shapes[computation].get(name)

  def _instruction(self, computation: str, instr: Instruction) -> Cost:
    op = instr.opcode
    if op in _FREE:
      return Cost()
    if op == "while":
      trips = re.search(r'"known_trip_count":\{"n":"(\d+)"', instr.attributes)
      body = self._computation(instr.attr("body").lstrip("%"))
      cost = Cost()
      cost.add(body, int(trips.group(1)) if trips else 1)
      return cost
    if op in ("call", "async-start"):
      called = instr.attr("to_apply") or instr.attr("calls")
      return self._computation(called.lstrip("%")) if called else Cost()
    if op == "conditional":
      branches = re.findall(r"%([\w.\-]+)", instr.attr("branch_computations") or "")
      costs = [self._computation(b) for b in branches] or [Cost()]
      return max(costs, key=lambda c: c.seconds)
    if op in ("send", "recv", "send-done", "recv-done") and "is_host_transfer=true" in instr.attributes:
      megascale = _MEGASCALE.search(instr.attributes)
      if op == "send" and megascale:
        return self._dcn_collective(computation, instr, megascale.group(1))
      if megascale or "xla_megascale_runtime" in instr.attributes:
        return Cost()  # the same transfer's other half: counted at its send
    base = op.removesuffix("-start")
    if base in COLLECTIVES:
      return self._collective(computation, instr, base)
    flops, moved, gathers = self._flops_and_bytes(computation, instr, hbm=True)
    # VMEM traffic: the op's bytes wherever they are, less those in HBM.
    vmem = max(0.0, self._flops_and_bytes(computation, instr, hbm=False)[1] - moved)
    indices, vmem_indices, index = self._lookups(computation, instr)
    gathers = gathers or indices > 0
    compute, vmem_rate = flops / self.chip.bf16_flops, self.chip.vmem_bytes_per_s
    memory = max(moved / self.chip.hbm_bytes_per_s, vmem / vmem_rate if vmem_rate else 0.0)
    seconds = max(compute, memory, index)
    bound = "compute" if compute == seconds else "memory" if memory == seconds else "index"
    return Cost(flops=flops, bytes=moved, vmem_bytes=vmem, seconds=seconds,
                compute_seconds=seconds if bound == "compute" else 0.0,
                memory_seconds=seconds if bound == "memory" else 0.0,
                index_bound_seconds=seconds if bound == "index" else 0.0,
                gather_scatter_seconds=seconds if gathers else 0.0,
                gather_scatter_bytes=moved if gathers else 0.0,
                indices=indices, vmem_indices=vmem_indices, index_seconds=index)

  def _collective(self, computation: str, instr: Instruction, base: str) -> Cost:
    operands = [self._operand(computation, n) for n in instr.operands]
    size = (sum(a.payload_bytes for o in operands if o for a in o.shape) if base != "all-gather"
            else sum(a.payload_bytes for a in instr.shape[-1:]))
    groups = re.search(r"replica_groups=\{\{([0-9,]+)\}", instr.attributes)
    iota = re.search(r"replica_groups=\[(\d+),(\d+)\]", instr.attributes)
    group = (len(groups.group(1).split(",")) if groups else int(iota.group(2)) if iota else self.num_devices)
    # A ring all-reduce sends and receives 2 (n - 1) / n of the data per chip; the others (n - 1) / n.
    factor = (2.0 if base == "all-reduce" else 1.0) * (group - 1) / max(group, 1)
    seconds = factor * size / self.chip.allreduce_bytes_per_s
    collective = {"op": base, "bytes": size, "group": group, "network": "ici", "count": 1}
    if self.mesh_axes:
      collective["axes"] = mesh_axes_of(first_group(instr.attributes), self.mesh_axes)
    return Cost(seconds=seconds, collective_seconds=seconds, collectives=[collective])

  def _dcn_collective(self, computation: str, instr: Instruction, transfer: str) -> Cost:
    """The cross-slice part of a collective: each chip's share (the send's operand) over the slices."""
    operand = self._operand(computation, instr.operands[0]) if instr.operands else None
    size = sum(a.payload_bytes for a in operand.shape) if operand else 0
    op = {"ALL_REDUCE": "all-reduce", "ALL_GATHER": "all-gather", "REDUCE_SCATTER": "reduce-scatter",
          "ALL_TO_ALL": "all-to-all"}.get(transfer, transfer.lower().replace("_", "-"))
    group = self.num_slices
    factor = (2.0 if op == "all-reduce" else 1.0) * (group - 1) / max(group, 1)
    bandwidth = self.chip.dcn_bytes_per_s
    seconds = factor * size / bandwidth if bandwidth else 0.0
    return Cost(seconds=seconds, collective_seconds=seconds, dcn_seconds=seconds,
                collectives=[{"op": op, "bytes": size, "group": group, "network": "dcn", "count": 1}])

  def _flops_and_bytes(self, computation: str, instr: Instruction, hbm: bool) -> tuple[float, float, bool]:
    """(matmul FLOPs, bytes, whether it gathers or scatters) of one top-level op or fusion: its HBM bytes
    (hbm), or its bytes wherever they are (VMEM's too)."""
    operands = [self._operand(computation, n) for n in instr.operands]
    if instr.opcode == "fusion":
      fused = instr.attr("calls").lstrip("%")
      inner = self.computations.get(fused, [])
      flops = sum(self._matmul_flops(fused, i) for i in inner)
      params = self._parameter_numbers(fused)
      moved, gathers = 0.0, False
      for pname, number in params.items():
        if number >= len(operands) or operands[number] is None:
          continue
        full = operands[number].bytes_in(hbm)
        partial = self._partial_read(fused, pname, operands[number], hbm)
        gathers |= partial is not None and partial[1]
        moved += min(full, partial[0]) if partial is not None else full
      root = next((i for i in inner if i.root), None)
      written = self._written_bytes(fused, root, hbm) if root is not None else None
      gathers |= written is not None and written[1]
      moved += written[0] if written is not None else instr.bytes_in(hbm)
      return flops, moved, gathers
    estimate = pallas_cost_estimate(instr)
    if estimate is not None:  # its author's bytes_accessed: HBM's
      return estimate[0], estimate[1], False
    flops = self._matmul_flops(computation, instr)
    table = operands[0] if operands else None
    into_vmem = hbm and table is not None and table.in_vmem  # an update or slice of an array in VMEM
    if instr.opcode == "gather" and table is not None:
      return flops, (self._gather_bytes(instr, table, hbm) + instr.bytes_in(hbm)
                     + self._operand_bytes_from(operands[1:], hbm)), True
    if instr.opcode == "scatter" and table is not None:  # its updates read, and written into the table
      updates = operands[-1]
      moved = updates.bytes_in(hbm) + (0 if into_vmem else updates.bytes_out) if updates else 0
      return flops, moved + self._operand_bytes_from(operands[1:-1], hbm), True
    if instr.opcode == "copy-start":  # an asynchronous copy: its result tuple holds destination and source
      destination = instr.shape[0].hbm_bytes if hbm else instr.shape[0].bytes
      return flops, self._operand_bytes_from(operands, hbm) + destination, False
    if instr.opcode == "slice-start" and len(instr.shape) > 1:
      # An asynchronous slice (XLA moves a table into VMEM so, piece by piece): its result tuple holds its
      # source (the whole array, not moved), the slice and a context; it reads the slice of the source and
      # writes the slice (its -done is free, as a copy-done).
      source, destination = instr.shape[0], instr.shape[1]
      read = 0 if hbm and source.in_vmem else destination.bytes
      return flops, read + (destination.hbm_bytes if hbm else destination.bytes), False
    if instr.opcode in ("dynamic-slice", "slice"):
      return flops, (0 if into_vmem else instr.bytes_out) + instr.bytes_in(hbm), False
    if instr.opcode == "dynamic-update-slice":
      update = operands[1] if len(operands) > 1 else None
      return flops, (update.bytes_in(hbm) + (0 if into_vmem else update.bytes_out) if update else 0), False
    return flops, self._operand_bytes_from(operands, hbm) + instr.bytes_in(hbm), False

  @staticmethod
  def _operand_bytes_from(operands, hbm: bool) -> int:
    return sum(o.bytes_in(hbm) for o in operands if o is not None)

  def _parameter_numbers(self, computation: str) -> dict[str, int]:
    return {i.name: int(i.raw_operands) for i in self.computations.get(computation, [])
            if i.opcode == "parameter" and i.raw_operands.strip().isdigit()}

  def _gather_bytes(self, gather: Instruction, table: Instruction, hbm: bool) -> float:
    """Slices gathered x the bytes each touches (at least a tile row of the table's layout); none of HBM's from
    a table in VMEM."""
    sizes = re.search(r"slice_sizes=\{([0-9,]*)\}", gather.attributes)
    array = table.shape[0] if table.shape else None
    if hbm and array is not None and array.in_vmem:
      return 0
    if not sizes or array is None:
      return gather.bytes_out
    slice_dims = [int(s) for s in sizes.group(1).split(",") if s]
    slice_elements = max(1, math.prod(slice_dims))
    count = max(1, gather.shape[0].elements // slice_elements) if gather.shape else 1
    return count * array.slice_bytes(slice_dims)

  def _partial_read(self, fused: str, param: str, operand: Instruction, hbm: bool) -> tuple[float, bool] | None:
    """Bytes a fusion reads of parameter `param` when every use reads only part of it (gather, slices,
    scatter's in-place operand), with whether a gather or scatter does; None when some use reads it whole."""
    users = [i for i in self.computations[fused] if param in i.operands]
    if not users:
      return 0.0, False
    total, gathers = 0.0, False
    for user in users:
      first = user.operands and user.operands[0] == param
      if user.opcode == "gather" and first:
        total += self._gather_bytes(user, operand, hbm)
        gathers = True
      elif user.opcode in ("dynamic-slice", "slice") and first:
        total += user.bytes_in(hbm)
      elif user.opcode in ("scatter", "dynamic-update-slice") and first:
        gathers |= user.opcode == "scatter"  # in place: its updates are counted where it writes
      else:
        return None
    return total, gathers

  def _written_bytes(self, fused: str, root: Instruction, hbm: bool) -> tuple[float, bool] | None:
    """Bytes a fusion writes when its result is an in-place update (scatter: updates read and written); none of
    HBM's into an array in VMEM."""
    shapes = self._shapes[fused]
    roots = [shapes[n] for n in root.operands if n in shapes] if root.opcode == "tuple" else [root]
    total, any_partial, gathers = 0.0, False, False
    for r in roots:
      into_vmem = hbm and (r.in_vmem or bool(r.operands) and r.operands[0] in shapes
                           and shapes[r.operands[0]].in_vmem)
      if r.opcode == "scatter":
        updates = shapes.get(r.operands[-1])
        total += 0 if into_vmem else 2 * (updates.bytes_out if updates else 0)
        any_partial = gathers = True
      elif r.opcode == "dynamic-update-slice":
        update = shapes.get(r.operands[1])
        total += 0 if into_vmem else 2 * (update.bytes_out if update else 0)
        any_partial = True
      else:
        total += r.bytes_in(hbm)
    return (total, gathers) if any_partial else None

  def _lookups(self, computation: str, instr: Instruction) -> tuple[int, int, float]:
    """(slices gathered and scattered, of which from or into a table in VMEM, their time at the chip's
    per-index rates) of one top-level op or fusion: every gather and scatter in it."""
    rate = self.chip.gather_indices_per_s
    where, ops, outer = computation, [instr], []
    if instr.opcode == "fusion":
      where = instr.attr("calls").lstrip("%")
      ops = self.computations.get(where, [])
      outer = [self._operand(computation, n) for n in instr.operands]
    params = self._parameter_numbers(where) if outer else {}
    indices = vmem_indices = 0
    seconds = 0.0
    for op in ops:
      if op.opcode not in ("gather", "scatter") or not op.operands:
        continue
      count = self._index_count(where, op)
      table = self._shapes[where].get(op.operands[0])
      number = params.get(op.operands[0], len(outer))
      vmem = (table is not None and table.in_vmem) or (number < len(outer) and outer[number] is not None
                                                         and outer[number].in_vmem)
      indices += count
      vmem_indices += count if vmem else 0
      if rate:
        seconds += count / (rate * (self.chip.vmem_gather_speedup if vmem else 1.0))
    return indices, vmem_indices, seconds

  def _index_count(self, computation: str, op: Instruction) -> int:
    """The slices a gather gathers (its result's dims that are not `offset_dims`) or a scatter scatters (its
    updates' dims that are not `update_window_dims`)."""
    if op.opcode == "gather":
      array, window = (op.shape[0] if op.shape else None), op.attr("offset_dims")
    else:
      updates = self._shapes[computation].get(op.operands[-1])
      array, window = (updates.shape[0] if updates and updates.shape else None), op.attr("update_window_dims")
    if array is None:
      return 0
    if window is None:  # not named (XLA always names them): one slice per element
      return array.elements
    window_dims = {int(d) for d in re.findall(r"\d+", window)}
    return math.prod(d for i, d in enumerate(array.dims) if i not in window_dims)

  def _matmul_flops(self, computation: str, instr: Instruction) -> float:
    if instr.opcode not in ("dot", "convolution") or not instr.shape:
      return 0.0
    operands = [self._operand(computation, n) for n in instr.operands]
    if any(o is None or not o.shape for o in operands[:2]):
      return 0.0
    lhs, rhs, out = operands[0].shape[0], operands[1].shape[0], instr.shape[0]
    labels = re.search(r"dim_labels=(\w+)_(\w+)->(\w+)", instr.attributes)
    if instr.opcode == "dot":
      dims = re.search(r"lhs_contracting_dims=\{([0-9,]*)\}", instr.attributes)
      macs = out.elements * (math.prod(lhs.dims[int(d)] for d in dims.group(1).split(",") if d) if dims else 1)
    elif labels and len(labels.group(1)) == len(lhs.dims) and len(labels.group(2)) == len(rhs.dims) \
        and len(labels.group(3)) == len(out.dims):
      macs = self._convolution_macs(lhs, rhs, out, *labels.groups())
    else:
      macs = out.elements
    precision = re.search(r"operand_precision=\{(\w+)", instr.attributes)
    passes = _PRECISION_PASSES.get(precision.group(1), 1) if precision and lhs.dtype == "f32" else 1
    return 2.0 * macs * passes

  @staticmethod
  def _convolution_macs(lhs: Array, rhs: Array, out: Array, lhs_labels: str, rhs_labels: str,
                        out_labels: str) -> float:
    """Multiply-adds of a convolution that touch real input, padding excluded: XLA on TPU writes some
    matmuls as convolutions over zero-padded windows (e.g. a window of 17 padded by 16 on each side of a
    single input position), whose padded taps are no work. Per spatial dimension, the (input, output)
    position pairs a window covers: at most input x window, and at most output x window."""
    macs = lhs.dims[lhs_labels.index("b")] * rhs.dims[rhs_labels.index("o")] * rhs.dims[rhs_labels.index("i")]
    for label in rhs_labels:
      if label.isdigit() and label in lhs_labels and label in out_labels:
        window, size_in, size_out = (rhs.dims[rhs_labels.index(label)], lhs.dims[lhs_labels.index(label)],
                                     out.dims[out_labels.index(label)])
        macs *= min(size_in * min(window, size_out), size_out * window)
    return macs
