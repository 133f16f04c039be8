"""The TPU chips' published figures, and the pods nerfpod knows by name: their topologies, chips and hosts.

Chip figures are Google Cloud's own, per chip, from the Cloud TPU system-architecture pages:
https://cloud.google.com/tpu/docs/v4, https://cloud.google.com/tpu/docs/v5e,
https://cloud.google.com/tpu/docs/v5p, https://cloud.google.com/tpu/docs/v6e. Where a page gives a pod's
"all-reduce bandwidth" (v4: 1.1 PB/s over 4096 chips; v5e: 51.2 TB/s and v6e: 102.4 TB/s over 256
chips), the per-chip all-reduce bandwidth is that divided by the pod's chips; for v5p, whose page gives
none, it is half the chip's bidirectional ICI bandwidth (1200 GB/s), the same ratio v5e (400 GB/s ICI,
200 GB/s all-reduce) and v6e (800, 400) show. HBM capacities are GiB (the pages write "16 GB" and
"95 GiB" for the same kind of figure; XLA's own compiler reports 15.75 GiB usable of a v5e's 16 GiB);
bandwidths are 10^9 bytes/s.

Between slices (multi-slice: slices joined by the data-centre network, DCN), the per-chip DCN bandwidth is
a pod's published "Data center network bandwidth per Pod" divided by its chips: v5e 6.4 Tbps over 256 chips
(https://cloud.google.com/tpu/docs/v5e; the same page gives each host 2 x 100 Gbps NICs, the same 25 Gbps,
3.125 GB/s, per chip). The other generations' pages give no such figure: their DCN time is left out (None).

Gathers and scatters take time per index (per gathered or scattered slice), not only per byte. Google
publishes no such rate; the figures here are measured ones (JAX 0.10.2, TensorCore
gathers of random rows, table in HBM) from the public study github.com/areporeporepo/tpu-irregular-memory-study:
v6e, 262,144 indices of 1 float32 from a 1M-row table in 1.6912 ms (data/gather_20260816T192359Z.json; rows of
8 values took 0.9511 ms: 1.55-2.76 x 10^8 indices/s, the slower taken, as for the hash grid's 2-value rows);
v5p, 16,384 indices of 128 float32 from a 128 MiB table in 0.1094 ms (data/gather_locality_v5p.json). A table
XLA keeps in VMEM (memory space S(1) in the compiled HLO's layouts: at most about 96 MiB on v6e,
data/hlo_bisect_v6e.json, and between 40 and 48 MiB on v5p, data/hlo_v5p.json) is gathered faster: the same 16,384
indices from a 2-32 MiB table took 0.0508 ms against 0.1446 ms from a 128 MiB one on v6e
(data/sparsecore_v6e.json: 2.85 times), 0.0329 against 0.1094 ms on v5p (data/gather_locality_v5p.json:
3.33 times). v4 and v5e have no published figure: each takes its nearest measured relative's (see CHIPS).
VMEM's own bandwidth has no per-generation figure either; Google DeepMind's "How to Scale Your Model"
(https://jax-ml.github.io/scaling-book/tpus/, source github.com/jax-ml/scaling-book, tpus.md) gives it as
"around 22x higher than HBM bandwidth", which is taken for every generation.

Names are the Cloud TPU accelerator types (`gcloud ... --accelerator-type`): v4 and v5p count
TensorCores (two per chip, one JAX device per chip in megacore mode), v5e (`v5litepod-N`, also `v5e-N`)
and v6e count chips. Multi-host pods have 4 chips per host, as their TPU VMs do.

Standard library only: the launchers import it for a pod's size.
"""
import dataclasses

GB, GiB = 1e9, 2**30


@dataclasses.dataclass(frozen=True)
class Chip:
  """One chip's figures (published; the per-index rates measured, see the module's docstring): what hlo_cost's
  roofline runs on and what aot's memory is held against."""
  name: str                  # JAX's device_kind family, for reports
  bf16_flops: float          # peak matmul FLOP/s, bf16
  hbm_bytes: float
  hbm_bytes_per_s: float
  allreduce_bytes_per_s: float  # per chip (see the module's docstring)
  source: str
  dcn_bytes_per_s: float | None = None  # per chip, between slices; None where Google publishes no figure
  gather_indices_per_s: float | None = None  # gathered or scattered slices a second, table in HBM; None: not charged
  vmem_gather_speedup: float = 1.0  # how many times faster a table in VMEM (S(1)) is indexed than one in HBM
  vmem_bytes_per_s: float | None = None  # VMEM's bandwidth (22 x HBM's, module docstring); None: VMEM is free


# Per-index rates (module docstring): measured on v6e and v5p (tpu-irregular-memory-study, data/*.json).
_V6E_INDICES_PER_S, _V6E_VMEM_SPEEDUP = 262144 / 1.6912e-3, 0.1446 / 0.0508
_V5P_INDICES_PER_S, _V5P_VMEM_SPEEDUP = 16384 / 0.1094e-3, 0.1094 / 0.0329
# v4, v5e unmeasured: their family's (v5e: v6e's; v4: v5p's); not HBM-scaled, as v5p (1.7x v6e's HBM) indexes alike.
_VMEM_OVER_HBM = 22  # "How to Scale Your Model" (module docstring), for every generation
CHIPS = {
    "v4": Chip("TPU v4", 275e12, 32 * GiB, 1200 * GB, 1.1e15 / 4096, "https://cloud.google.com/tpu/docs/v4",
               gather_indices_per_s=_V5P_INDICES_PER_S, vmem_gather_speedup=_V5P_VMEM_SPEEDUP,
               vmem_bytes_per_s=_VMEM_OVER_HBM * 1200 * GB),
    "v5e": Chip("TPU v5 lite", 197e12, 16 * GiB, 819 * GB, 51.2e12 / 256, "https://cloud.google.com/tpu/docs/v5e",
                6.4e12 / 8 / 256, gather_indices_per_s=_V6E_INDICES_PER_S, vmem_gather_speedup=_V6E_VMEM_SPEEDUP,
                vmem_bytes_per_s=_VMEM_OVER_HBM * 819 * GB),
    "v5p": Chip("TPU v5", 459e12, 95 * GiB, 2765 * GB, 1200 * GB / 2, "https://cloud.google.com/tpu/docs/v5p",
                gather_indices_per_s=_V5P_INDICES_PER_S, vmem_gather_speedup=_V5P_VMEM_SPEEDUP,
                vmem_bytes_per_s=_VMEM_OVER_HBM * 2765 * GB),
    "v6e": Chip("TPU v6 lite", 918e12, 32 * GiB, 1638 * GB, 102.4e12 / 256, "https://cloud.google.com/tpu/docs/v6e",
                gather_indices_per_s=_V6E_INDICES_PER_S, vmem_gather_speedup=_V6E_VMEM_SPEEDUP,
                vmem_bytes_per_s=_VMEM_OVER_HBM * 1638 * GB),
}


@dataclasses.dataclass(frozen=True)
class Pod:
  name: str            # the accelerator type
  generation: str      # key of CHIPS
  topology: str        # chips along each axis, as libtpu names it
  chips_per_host: tuple[int, ...]

  @property
  def chip(self) -> Chip:
    return CHIPS[self.generation]

  @property
  def num_chips(self) -> int:
    count = 1
    for side in self.topology.split("x"):
      count *= int(side)
    return count

  @property
  def num_hosts(self) -> int:
    per_host = 1
    for side in self.chips_per_host:
      per_host *= side
    return max(1, self.num_chips // per_host)

  @property
  def topology_name(self) -> str:
    return f"{self.generation}:{self.topology}"

  @property
  def chip_config(self) -> str:
    """libtpu's chip configuration: v4 and v5p chips run as one device (megacore), as on their VMs."""
    return "megacore" if self.generation in ("v4", "v5p") else "default"


def _pods() -> dict[str, Pod]:
  pods = {}
  for cores, topology in ((8, "2x2x1"), (16, "2x2x2"), (32, "2x2x4"), (64, "2x4x4"), (128, "4x4x4"),
                          (256, "4x4x8"), (512, "4x8x8")):
    pods[f"v4-{cores}"] = Pod(f"v4-{cores}", "v4", topology, (2, 2, 1))
    pods[f"v5p-{cores}"] = Pod(f"v5p-{cores}", "v5p", topology, (2, 2, 1))
  for chips, topology in ((4, "2x2"), (8, "2x4"), (16, "4x4"), (32, "4x8"), (64, "8x8"), (128, "8x16"),
                          (256, "16x16")):
    host = (2, 4, 1) if chips == 8 else (2, 2, 1)
    pods[f"v5litepod-{chips}"] = Pod(f"v5litepod-{chips}", "v5e", topology, host)
    pods[f"v6e-{chips}"] = Pod(f"v6e-{chips}", "v6e", topology, host)
  return pods


PODS = _pods()
ALIASES = {f"v5e-{name.split('-')[1]}": name for name in PODS if name.startswith("v5litepod-")}


def lookup(name: str) -> Pod | None:
  """The pod of an accelerator type (or its v5e-N alias); None if unknown."""
  return PODS.get(ALIASES.get(name, name))


def known_names() -> list[str]:
  return sorted(PODS, key=lambda n: (n.split("-")[0], int(n.split("-")[1])))
