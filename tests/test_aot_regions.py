"""The pod compile tool's report of a region model's traffic between its regions (model.regions > 1): each
collective of the compiled step named by the mesh axes it runs over (nerfpod.pod.hlo_cost), and the bytes
all-gathered over the region axis and reduced per step (nerfpod.pod.aot.region_traffic)."""
import json

import pytest

from nerfpod.pod import aot, hlo_cost
from test_aot import _aot, needs_libtpu

# A (data 2, region 4) mesh: the region axis the minor one, devices numbered row by row.
MESH = {"data": 2, "region": 4}


@pytest.mark.parametrize("attributes,group,axes", [
    ("replica_groups={{0,1,2,3},{4,5,6,7}}, dimensions={0}", (0, 1, 2, 3), ("region",)),
    ("replica_groups={{0,4},{1,5},{2,6},{3,7}}, to_apply=%add", (0, 4), ("data",)),
    ("replica_groups={{0,1,2,3,4,5,6,7}}, to_apply=%add", tuple(range(8)), ("data", "region")),
    ("replica_groups=[2,4]<=[8], dimensions={0}", (0, 1, 2, 3), ("region",)),  # the iota form of the first
    ("replica_groups=[4,2]<=[2,4]T(1,0), to_apply=%add", (0, 4), ("data",)),
    ("source_target_pairs={{0,2},{2,0},{1,3},{3,1}}", (0, 2), ("region",)),  # a butterfly round's partners
    ("replica_groups={{5}}", (5,), ()),
    ("to_apply=%add", None, ("data", "region")),  # no groups named: every device
])
def test_a_collectives_group_and_the_mesh_axes_it_runs_over(attributes, group, axes):
  assert hlo_cost.first_group(attributes) == group
  assert hlo_cost.mesh_axes_of(group, MESH) == axes


def test_the_axes_are_named_in_the_costed_program_only_where_the_mesh_is_given():
  text = """HloModule m

ENTRY %main (x: f32[4,128,9]) -> f32[16,128,9] {
  %x = f32[4,128,9]{2,1,0} parameter(0)
  ROOT %g = f32[16,128,9]{2,1,0} all-gather(%x), replica_groups=[2,4]<=[8], dimensions={0}
}
"""
  from test_hlo_cost import CHIP
  plain = hlo_cost.HloProgram(text, CHIP, 8).cost().collectives
  assert plain == [{"op": "all-gather", "bytes": 16 * 128 * 9 * 4, "group": 4, "network": "ici", "count": 1}]
  named = hlo_cost.HloProgram(text, CHIP, 8, mesh_axes=MESH).cost().collectives
  assert named == [dict(plain[0], axes=("region",))]


def _step(*collectives) -> dict:
  return {"collectives": [dict(zip(("op", "bytes", "group", "axes", "count"), c), network="ici")
                          for c in collectives]}


def test_region_traffic_sums_the_gathers_over_the_region_axis_and_the_reductions_apart():
  step = _step(("all-gather", 18432, 4, ["region"], 2), ("all-gather", 2048, 4, ["region"], 2),
               ("all-reduce", 150000, 2, ["data"], 1), ("all-reduce", 4, 4, ["region"], 1),
               ("collective-permute", 64, 2, ["region"], 1))
  assert aot.region_traffic(step) == {"gathered_bytes": 2 * 18432 + 2 * 2048, "gathers": 4,
                                      "region_reduce_bytes": 4, "gradient_mean_bytes": 150000,
                                      "other_region_bytes": 64}
  # The gathers over the region axis are the region step's own; elsewhere an all-gather is still reported.
  assert aot.check_collectives(step, state_bytes=200000, regions=True) == ["collective-permute of 64 bytes"]
  assert "all-gather of 18432 bytes" in aot.check_collectives(step, state_bytes=200000)
  stray = _step(("all-gather", 512, 2, ["data"], 1))
  assert aot.check_collectives(stray, state_bytes=200000, regions=True) == ["all-gather of 512 bytes"]


@pytest.mark.slow  # a whole TPU compile of the region step in a process of its own (~20 s)
@needs_libtpu
def test_a_region_models_step_reports_its_partial_sums_gathered_over_the_region_axis():
  """4 regions on v5e-8 (data 2 x region 4), the smoke step: its partial sums are 10 numbers per ray and
  region (segment start, colour, optical depth, depth, opacity, the distortion loss's 2 sums; and the
  interlevel loss's 1), gathered over the region axis for the 128 rays of each data group: 4 x 128 x 10
  float32 per chip and step. The gradients' mean runs over the data axis."""
  out = _aot("--config=configs/default.py:smoke", "--config.model.regions=4", "--topology=v5e-8", "--what=step",
             "--json=-")
  assert out.returncode == 0, out.stderr
  report = json.loads(out.stdout)
  assert report["mesh"] == {"data": 2, "region": 4}
  step = report["step"]
  assert step["unexpected_collectives"] == []
  traffic = step["region_traffic"]
  assert traffic["gathered_bytes"] == 4 * (report["batch"] // 2) * 10 * 4
  assert 0 < traffic["gradient_mean_bytes"] <= report["param_bytes"]
  assert traffic["other_region_bytes"] == 0
  assert {tuple(c["axes"]) for c in step["collectives"] if c["op"] == "all-gather"} == {("region",)}
  assert "region traffic per step and chip: 20.0 KiB of partial sums all-gathered over the region axis" in out.stderr
  assert "over 4 chips (region axis)" in out.stderr and "over 2 chips (data axis)" in out.stderr
