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

Names are the Cloud TPU accelerator types (`gcloud ... --accelerator-type`): v4 and v5p count
TensorCores (two per chip, one JAX device per chip in megacore mode), v5e (`v5litepod-N`, also `v5e-N`)
and v6e count chips. Multi-host pods have 4 chips per host, as their TPU VMs do.

Standard library only: the launchers import it for a pod's size.
"""
import dataclasses

GB, GiB = 1e9, 2**30


@dataclasses.dataclass(frozen=True)
class Chip:
  """One chip's published figures: what hlo_cost's roofline runs on and what aot's memory is held against."""
  name: str                  # JAX's device_kind family, for reports
  bf16_flops: float          # peak matmul FLOP/s, bf16
  hbm_bytes: float
  hbm_bytes_per_s: float
  allreduce_bytes_per_s: float  # per chip (see the module's docstring)
  source: str
  dcn_bytes_per_s: float | None = None  # per chip, between slices; None where Google publishes no figure


CHIPS = {
    "v4": Chip("TPU v4", 275e12, 32 * GiB, 1200 * GB, 1.1e15 / 4096, "https://cloud.google.com/tpu/docs/v4"),
    "v5e": Chip("TPU v5 lite", 197e12, 16 * GiB, 819 * GB, 51.2e12 / 256, "https://cloud.google.com/tpu/docs/v5e",
                6.4e12 / 8 / 256),
    "v5p": Chip("TPU v5", 459e12, 95 * GiB, 2765 * GB, 1200 * GB / 2, "https://cloud.google.com/tpu/docs/v5p"),
    "v6e": Chip("TPU v6 lite", 918e12, 32 * GiB, 1638 * GB, 102.4e12 / 256, "https://cloud.google.com/tpu/docs/v6e"),
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
