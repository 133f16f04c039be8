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


@pytest.mark.parametrize("capacity,microbatches,rows,evals", [
    (0.0, 1, None, 1 * 512 * 48),         # dense: every region of the chip renders its group's R rays
    (0.75, 1, 384, 1 * 384 * 48),         # C = ceil(0.75 x 512) = 384
    (0.3, 1, 160, 1 * 160 * 48),          # ceil(153.6) = 154, up to a multiple of 8: 160
    (0.5, 2, 128, 1 * 128 * 48 * 2),      # two micro-batches of R = 256: C of each
    (1.0, 1, 512, 1 * 512 * 48),          # the whole of R: as many evaluations as dense
])
def test_region_figures_per_chip(capacity, microbatches, rows, evals):
  """The street at K = 4 on 8 chips, 2 data x 4 regions, 1,024 rays: a chip holds its region group's 512 rays
  (not 1,024 / 8) and renders its one region; 48 field samples per ray (32 proposal + 16)."""
  figures = aot.region_figures(1024, 2, 4, 4, 48, microbatches, capacity)
  assert figures["rays_per_chip"] == 512 and figures["regions_per_chip"] == 1
  assert figures["rows_per_region"] == 512 // microbatches
  assert figures["capacity_rows"] == rows
  assert figures["field_evals_per_chip_dense"] == 512 * 48
  assert figures["field_evals_per_chip"] == evals


def test_region_figures_are_the_steps_metric():
  """The figures are those the step logs as regions/field_evals_per_chip (step.region_metrics, dense and
  compacted), for 2 regions per chip (K = 8 over a region axis of 4) and 2 micro-batches."""
  import jax.numpy as jnp
  from nerfpod.nerf import regions
  from nerfpod.run import step
  for capacity in (0.0, 0.6):
    figures = aot.region_figures(2048, 4, 8, 4, 40, 2, capacity)
    rays = 2048 // 4 // 2
    rows = regions.capacity_rows(capacity, rays) if capacity else 0
    dropped = jnp.zeros((8, rays)) if capacity else None
    metric = step.region_metrics(jnp.ones((8,)), rays, dropped, rows, 2, 40, 2, 2 * 4)
    assert figures["field_evals_per_chip"] == int(metric["regions/field_evals_per_chip"])
    assert figures["capacity_rows"] == (rows or None)


def test_the_report_prints_the_region_figures():
  report = {"pod": "v5e-8", "topology": "2x4", "chips": 8, "hosts": 1, "chip": {"kind": "TPU v5e",
            "hbm_bytes": 16 * 2**30, "source": "test"}, "batch": 1024, "rays_per_chip": 512, "microbatches": 1,
            "compute_dtype": "float32", "hashgrid_matmul_max_rows": 0, "host_rows_contiguous": True,
            "regions": aot.region_figures(1024, 2, 4, 4, 48, 1, 0.75)}
  text = aot.format_report(report)
  assert "batch 1024 rays, 512 per chip" in text
  assert "regions: 4 over a region axis of 4, 1 per chip; each chip holds its region group's 512 rays" in text
  assert ("field evaluations per chip and step: 1 region(s) x 384 rows x 48 samples x 1 micro-batch(es) = 18,432 "
          "at model.region_capacity=0.75 (0.75 of dense: 1 region(s) x 512 rows x 48 samples x 1 micro-batch(es) "
          "= 24,576 dense)") in text


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
  # A chip holds its region group's rays (256 / 2 data chips, not / 8) and renders its one region with the
  # smoke model's 16 + 16 samples per ray (region_figures' arithmetic: the quick tests above).
  assert report["rays_per_chip"] == 128
  assert report["regions"]["regions_per_chip"] == 1
  assert report["regions"]["field_evals_per_chip"] == report["regions"]["field_evals_per_chip_dense"] == 128 * 32
  assert "256 rays, 128 per chip" in out.stderr
  assert "field evaluations per chip and step: 1 region(s) x 128 rows x 32 samples x 1 micro-batch(es) = 4,096 dense" \
      in out.stderr
  step = report["step"]
  assert step["unexpected_collectives"] == []
  traffic = step["region_traffic"]
  assert traffic["gathered_bytes"] == 4 * (report["batch"] // 2) * 10 * 4
  assert 0 < traffic["gradient_mean_bytes"] <= report["param_bytes"]
  assert traffic["other_region_bytes"] == 0
  assert {tuple(c["axes"]) for c in step["collectives"] if c["op"] == "all-gather"} == {("region",)}
  assert "region traffic per step and chip: 20.0 KiB of partial sums all-gathered over the region axis" in out.stderr
  assert "over 4 chips (region axis)" in out.stderr and "over 2 chips (data axis)" in out.stderr
