"""nerfpod.pod.hlo_cost: the per-op roofline of an optimised HLO module, on hand-written HLO with known answers."""
import pytest

from nerfpod.pod import chips, hlo_cost

CHIP = chips.Chip("test chip", bf16_flops=100e12, hbm_bytes=16 * chips.GiB, hbm_bytes_per_s=1e12,
                  allreduce_bytes_per_s=100e9, source="round figures", gather_indices_per_s=1e8,
                  vmem_gather_speedup=4.0, vmem_bytes_per_s=10e12)


def _cost(text: str, devices: int = 4) -> hlo_cost.Cost:
  return hlo_cost.HloProgram(text, CHIP, devices).cost()


def test_layout_padding_and_tile_rows():
  padded = hlo_cost.parse_shape("f32[100,2]{1,0:T(8,128)}")[0]
  assert padded.bytes == 104 * 128 * 4            # rows to 8, the 2 features to 128 lanes
  assert padded.payload_bytes == 100 * 2 * 4
  compact = hlo_cost.parse_shape("f32[4096,2]{0,1:T(2,128)}")[0]
  assert compact.bytes == 4096 * 2 * 4            # the rows are the minor dim: no padding
  assert padded.slice_bytes([1, 2]) == 128 * 4    # one gathered row touches a tile row of 128 values
  assert hlo_cost.parse_shape("(f32[3]{0}, s32[])")[1].bytes == 4


def test_a_dot_is_bound_by_the_larger_of_its_flops_and_bytes():
  m, k, n = 512, 256, 128
  text = f"""HloModule m

ENTRY %main (a: f32[{m},{k}], b: f32[{k},{n}]) -> f32[{m},{n}] {{
  %a = f32[{m},{k}]{{1,0}} parameter(0)
  %b = f32[{k},{n}]{{1,0}} parameter(1)
  ROOT %d = f32[{m},{n}]{{1,0}} dot(%a, %b), lhs_contracting_dims={{1}}, rhs_contracting_dims={{0}}
}}
"""
  cost = _cost(text)
  flops, moved = 2 * m * k * n, 4 * (m * k + k * n + m * n)
  assert cost.flops == flops and cost.bytes == moved
  assert cost.seconds == pytest.approx(max(flops / CHIP.bf16_flops, moved / CHIP.hbm_bytes_per_s))
  highest = _cost(text.replace("rhs_contracting_dims={0}", "rhs_contracting_dims={0}, "
                                                            "operand_precision={highest,highest}"))
  assert highest.flops == 6 * flops  # float32 at HIGHEST: six bf16 passes


def test_a_convolution_over_a_padded_window_counts_only_real_taps():
  # XLA's TPU form of (N, 17) x (17, 17*17*2): output (N, 17, 17, 2), window 17x2 padded by 16 and 1.
  text = """HloModule m

ENTRY %main (x: f32[64,17,1,1], w: f32[17,17,17,2]) -> f32[64,17,17,2] {
  %x = f32[64,17,1,1]{3,2,1,0} parameter(0)
  %w = f32[17,17,17,2]{3,2,1,0} parameter(1)
  ROOT %c = f32[64,17,17,2]{3,2,1,0} convolution(%x, %w), window={size=17x2 pad=16_16x1_1 rhs_reversal=1x1}, dim_labels=bf01_0oi1->b0f1
}
"""
  assert _cost(text).flops == 2 * 64 * 17 * 17 * 17 * 2  # N side^3 F multiply-adds, not the padded window's


def test_a_gather_moves_its_rows_not_its_table_and_a_scatter_its_updates():
  text = """HloModule m

%add (a: f32[], b: f32[]) -> f32[] {
  %a = f32[] parameter(0)
  %b = f32[] parameter(1)
  ROOT %s = f32[] add(%a, %b)
}

ENTRY %main (t: f32[1048576,2], i: s32[1000,1], u: f32[1000,2]) -> (f32[1000,2], f32[1048576,2]) {
  %t = f32[1048576,2]{0,1:T(2,128)} parameter(0)
  %i = s32[1000,1]{1,0} parameter(1)
  %u = f32[1000,2]{1,0} parameter(2)
  %g = f32[1000,2]{1,0} gather(%t, %i), offset_dims={1}, collapsed_slice_dims={0}, start_index_map={0}, index_vector_dim=1, slice_sizes={1,2}
  %s = f32[1048576,2]{0,1:T(2,128)} scatter(%t, %i, %u), update_window_dims={1}, inserted_window_dims={0}, scatter_dims_to_operand_dims={0}, index_vector_dim=1, to_apply=%add
  ROOT %r = (f32[1000,2]{1,0}, f32[1048576,2]{0,1:T(2,128)}) tuple(%g, %s)
}
"""
  cost = _cost(text)
  table = 1048576 * 2 * 4
  # Gather: 1000 slices of [1, 2] in a layout whose minor dim is the rows (tile (2, 128)): 2 x 128 values
  # each, plus the indices and its result. Scatter: its updates read and written, plus the indices.
  gather = 1000 * 2 * 128 * 4 + 1000 * 4 + 1000 * 2 * 4
  scatter = 2 * 1000 * 2 * 4 + 1000 * 4
  assert cost.bytes == gather + scatter
  assert cost.bytes < table / 2
  assert cost.gather_scatter_seconds == pytest.approx(cost.seconds)


def test_a_loop_counts_its_body_trip_count_times_and_collectives_their_ring_traffic():
  text = """HloModule m

%body (p: (s32[], f32[1024])) -> (s32[], f32[1024]) {
  %p = (s32[], f32[1024]{0}) parameter(0)
  %i = s32[] get-tuple-element(%p), index=0
  %x = f32[1024]{0} get-tuple-element(%p), index=1
  %y = f32[1024]{0} exponential(%x)
  ROOT %t = (s32[], f32[1024]{0}) tuple(%i, %y)
}

%cond (p: (s32[], f32[1024])) -> pred[] {
  %p = (s32[], f32[1024]{0}) parameter(0)
  ROOT %c = pred[] constant(true)
}

ENTRY %main (x: f32[1024]) -> f32[1024] {
  %x = f32[1024]{0} parameter(0)
  %z = s32[] constant(0)
  %t = (s32[], f32[1024]{0}) tuple(%z, %x)
  %w = (s32[], f32[1024]{0}) while(%t), condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"10"}}
  %y = f32[1024]{0} get-tuple-element(%w), index=1
  ROOT %r = f32[1024]{0} all-reduce(%y), replica_groups={{0,1,2,3}}, to_apply=%add
}
"""
  cost = _cost(text)
  assert cost.bytes == 10 * 2 * 1024 * 4  # the body's exp, read and written, ten times
  assert cost.collectives == [{"op": "all-reduce", "bytes": 4096, "group": 4, "network": "ici", "count": 1}]
  assert cost.collective_seconds == pytest.approx(2 * 3 / 4 * 4096 / CHIP.allreduce_bytes_per_s)
  assert cost.seconds == pytest.approx(cost.collective_seconds + 10 * 8192 / CHIP.hbm_bytes_per_s)


def test_a_fusion_crosses_memory_once_and_reads_a_gathered_operand_in_part():
  text = """HloModule m

%fused (p0: f32[65536,2], p1: s32[100,1], p2: f32[100,2]) -> f32[100,2] {
  %p0 = f32[65536,2]{0,1:T(2,128)} parameter(0)
  %p1 = s32[100,1]{1,0} parameter(1)
  %p2 = f32[100,2]{1,0} parameter(2)
  %g = f32[100,2]{1,0} gather(%p0, %p1), offset_dims={1}, collapsed_slice_dims={0}, start_index_map={0}, index_vector_dim=1, slice_sizes={1,2}
  %m = f32[100,2]{1,0} multiply(%g, %p2)
  ROOT %e = f32[100,2]{1,0} exponential(%m)
}

ENTRY %main (t: f32[65536,2], i: s32[100,1], w: f32[100,2]) -> f32[100,2] {
  %t = f32[65536,2]{0,1:T(2,128)} parameter(0)
  %i = s32[100,1]{1,0} parameter(1)
  %w = f32[100,2]{1,0} parameter(2)
  ROOT %f = f32[100,2]{1,0} fusion(%t, %i, %w), kind=kLoop, calls=%fused
}
"""
  cost = _cost(text)
  gathered = 100 * 2 * 128 * 4  # the rows' tile rows (the gathered values stay inside the fusion)
  assert cost.bytes == gathered + 100 * 4 + 100 * 2 * 4 + 100 * 2 * 4  # + indices, weights, result
  assert cost.flops == 0


def test_a_cross_slice_reduction_is_a_dcn_collective_of_each_chips_share():
  """Multi-slice: the TPU compiler reduces within the slice (ICI), sends each chip's share to the megascale
  runtime to be reduced across the slices (DCN), and gathers the shares again; the send is the DCN
  collective (its recv and -dones cost nothing), costed at the chip's DCN bandwidth over the slices."""
  attrs = ('is_host_transfer=true, frontend_attributes={_xla_host_transfer_handler_name="xla_megascale_runtime",'
           '_xla_host_transfer_rendezvous="all-reduce.1_0",_xla_megascale_reduce_operation="SUM",'
           '_xla_megascale_target="{1,2}x{0:3}",_xla_megascale_transfer_type="ALL_REDUCE"}')
  done = 'is_host_transfer=true, frontend_attributes={_xla_host_transfer_handler_name="xla_megascale_runtime"}'
  text = f"""HloModule m

ENTRY %main (x: f32[4096,2]) -> f32[4096,2] {{
  %x = f32[4096,2]{{0,1:T(2,128)}} parameter(0)
  %r = f32[4096,2]{{0,1:T(2,128)}} all-reduce(%x), channel_id=1, replica_groups={{{{0,1,2,3}}}}, to_apply=%add
  %share = f32[8,2,128]{{2,1,0:T(2,128)}} bitcast(%r)
  %token = token[] after-all()
  %send = (f32[8,2,128]{{2,1,0:T(2,128)}}, u32[], token[]) send(%share, %token), channel_id=2, {attrs}
  %recv = (f32[8,2,128]{{2,1,0:T(2,128)}}, u32[], token[]) recv(%token), channel_id=1, {attrs}
  %send-done = token[] send-done(%send), channel_id=2, {done}
  %recv-done = (f32[8,2,128]{{2,1,0:T(2,128)}}, token[]) recv-done(%recv), channel_id=1, {done}
  %sum = f32[8,2,128]{{2,1,0:T(2,128)}} get-tuple-element(%recv-done), index=0
  %flat = f32[2048]{{0}} bitcast(%sum)
  ROOT %g = f32[8192]{{0}} all-gather(%flat), channel_id=3, replica_groups={{{{0,1,2,3}}}}, dimensions={{0}}
}}
"""
  chip = chips.CHIPS["v5e"]
  cost = hlo_cost.HloProgram(text, chip, 8, num_slices=2).cost()
  assert cost.collectives == [  # in program order
      {"op": "all-reduce", "bytes": 4096 * 2 * 4, "group": 4, "network": "ici", "count": 1},
      {"op": "all-reduce", "bytes": 2048 * 4, "group": 2, "network": "dcn", "count": 1},
      {"op": "all-gather", "bytes": 8192 * 4, "group": 4, "network": "ici", "count": 1}]
  # A ring all-reduce over 2 slices sends and receives the share once: 8 KiB at 3.125 GB/s per chip
  # (v5e: 6.4 Tbps of DCN per 256-chip pod, cloud.google.com/tpu/docs/v5e).
  assert chip.dcn_bytes_per_s == pytest.approx(3.125e9)
  assert cost.dcn_seconds == pytest.approx(2 * 1 / 2 * 8192 / 3.125e9)
  ici = (2 * 3 / 4 * 32768 + 3 / 4 * 32768) / chip.allreduce_bytes_per_s
  assert cost.collective_seconds == pytest.approx(ici + cost.dcn_seconds)
  # Where Google publishes no DCN figure (v4), the collective is still reported, its time left out.
  v4 = hlo_cost.HloProgram(text, chips.CHIPS["v4"], 8, num_slices=2).cost()
  assert [c["network"] for c in v4.collectives].count("dcn") == 1 and v4.dcn_seconds == 0.0


_ADD = """%add (a: f32[], b: f32[]) -> f32[] {
  %a = f32[] parameter(0)
  %b = f32[] parameter(1)
  ROOT %s = f32[] add(%a, %b)
}
"""


def test_a_gather_of_many_narrow_rows_is_bound_by_its_indices_and_of_few_wide_rows_by_its_bytes():
  narrow = """HloModule m

ENTRY %main (t: f32[1048576,2], i: s32[10,100,1]) -> f32[10,100,2] {
  %t = f32[1048576,2]{0,1:T(2,128)} parameter(0)
  %i = s32[10,100,1]{2,1,0} parameter(1)
  ROOT %g = f32[10,100,2]{2,1,0} gather(%t, %i), offset_dims={2}, collapsed_slice_dims={0}, start_index_map={0}, index_vector_dim=2, slice_sizes={1,2}
}
"""
  cost = _cost(narrow)
  indices = 10 * 100  # the result's batch dims (not offset_dims): one index per row gathered
  moved = indices * 2 * 128 * 4 + indices * 4 + indices * 2 * 4  # tile rows, indices, result
  assert cost.indices == indices and cost.vmem_indices == 0 and cost.bytes == moved
  assert indices / CHIP.gather_indices_per_s > moved / CHIP.hbm_bytes_per_s  # 10 us against 1.04 us
  assert cost.seconds == pytest.approx(indices / CHIP.gather_indices_per_s)
  assert cost.index_bound_seconds == cost.gather_scatter_seconds == cost.index_seconds == cost.seconds
  assert cost.memory_seconds == 0 and cost.gather_scatter_bytes == moved

  wide = """HloModule m

ENTRY %main (t: f32[4096,4096], i: s32[64,1]) -> f32[64,4096] {
  %t = f32[4096,4096]{1,0:T(8,128)} parameter(0)
  %i = s32[64,1]{1,0} parameter(1)
  ROOT %g = f32[64,4096]{1,0:T(8,128)} gather(%t, %i), offset_dims={1}, collapsed_slice_dims={0}, start_index_map={0}, index_vector_dim=1, slice_sizes={1,4096}
}
"""
  cost = _cost(wide)
  moved = 64 * 4096 * 4 + 64 * 4 + 64 * 4096 * 4  # 64 rows of 16 KiB read, the indices, the result
  assert cost.indices == 64 and cost.bytes == moved
  assert cost.seconds == pytest.approx(moved / CHIP.hbm_bytes_per_s)  # 2.1 us against 0.64 us of indices
  assert cost.index_seconds == pytest.approx(64 / CHIP.gather_indices_per_s)
  assert cost.memory_seconds == cost.gather_scatter_seconds == cost.seconds and cost.index_bound_seconds == 0


def test_a_scatter_add_of_many_narrow_rows_is_bound_by_its_indices_and_of_few_wide_rows_by_its_bytes():
  def scatter(table: str, rows: int, width: int, layout: str) -> str:
    return f"""HloModule m

{_ADD}
ENTRY %main (t: f32[{table}], i: s32[{rows},1], u: f32[{rows},{width}]) -> f32[{table}] {{
  %t = f32[{table}]{layout} parameter(0)
  %i = s32[{rows},1]{{1,0}} parameter(1)
  %u = f32[{rows},{width}]{{1,0}} parameter(2)
  ROOT %s = f32[{table}]{layout} scatter(%t, %i, %u), update_window_dims={{1}}, inserted_window_dims={{0}}, scatter_dims_to_operand_dims={{0}}, index_vector_dim=1, to_apply=%add
}}
"""
  narrow = _cost(scatter("1048576,2", 1000, 2, "{0,1:T(2,128)}"))
  moved = 2 * 1000 * 2 * 4 + 1000 * 4  # the updates read and written, the indices
  assert narrow.indices == 1000 and narrow.bytes == moved
  assert narrow.seconds == pytest.approx(1000 / CHIP.gather_indices_per_s)  # 10 us against 0.02 us
  assert narrow.index_bound_seconds == narrow.gather_scatter_seconds == narrow.seconds

  wide = _cost(scatter("4096,4096", 64, 4096, "{1,0:T(8,128)}"))
  moved = 2 * 64 * 4096 * 4 + 64 * 4
  assert wide.indices == 64 and wide.bytes == moved
  assert wide.seconds == pytest.approx(moved / CHIP.hbm_bytes_per_s)  # 2.1 us against 0.64 us
  assert wide.memory_seconds == wide.seconds and wide.index_bound_seconds == 0


def test_a_table_in_vmem_moves_no_hbm_bytes_and_is_indexed_faster():
  """XLA copies a small table into VMEM (memory space S(1) in its layout) and gathers from it there (in a
  fusion, as the TPU compiler writes a gather): the copy reads it from HBM once, the gather moves no bytes of
  it and takes vmem_gather_speedup times less time per index."""
  text = """HloModule m

%fused (p0: f32[1024,2], p1: s32[1000,1]) -> f32[1000,2] {
  %p0 = f32[1024,2]{0,1:T(2,128)S(1)} parameter(0)
  %p1 = s32[1000,1]{1,0} parameter(1)
  ROOT %g = f32[1000,2]{1,0} gather(%p0, %p1), offset_dims={1}, collapsed_slice_dims={0}, start_index_map={0}, index_vector_dim=1, slice_sizes={1,2}
}

ENTRY %main (t: f32[1024,2], i: s32[1000,1]) -> f32[1000,2] {
  %t = f32[1024,2]{0,1:T(2,128)} parameter(0)
  %i = s32[1000,1]{1,0} parameter(1)
  %v = f32[1024,2]{0,1:T(2,128)S(1)} copy(%t)
  ROOT %f = f32[1000,2]{1,0} fusion(%v, %i), kind=kCustom, calls=%fused
}
"""
  cost = _cost(text)
  table = 1024 * 2 * 4  # read from HBM once, by the copy into VMEM
  gather = 1000 * 4 + 1000 * 2 * 4  # the indices and the result only
  assert cost.bytes == table + gather
  assert cost.vmem_bytes == 2 * table  # the copy writes it into VMEM, the gather reads it there (whole at most)
  assert cost.indices == cost.vmem_indices == 1000
  index = 1000 / (CHIP.gather_indices_per_s * CHIP.vmem_gather_speedup)
  assert cost.index_seconds == pytest.approx(index)
  assert cost.seconds == pytest.approx(table / CHIP.hbm_bytes_per_s + index)
  # The same table left in HBM: the copy writes it there too, the gather reads it (whole: 1,000 tile rows would
  # be more), and its indices take 4 times as long.
  in_hbm = _cost(text.replace("S(1)", ""))
  assert in_hbm.vmem_indices == 0 and in_hbm.index_seconds == pytest.approx(1000 / CHIP.gather_indices_per_s)
  assert in_hbm.bytes == 2 * table + min(table, 1000 * 2 * 128 * 4) + gather
  assert hlo_cost.parse_shape("s32[64]{0:T(1024)S(1)SC(0:8192)}")[0].in_vmem
  assert not hlo_cost.parse_shape("u32[]{:S(2)}")[0].in_vmem
  # VMEM traffic runs at the chip's VMEM bandwidth: zeros broadcast into a padded table there (64 MiB).
  zeros = _cost("""HloModule m

ENTRY %main () -> f32[131072,2] {
  %c = f32[] constant(0)
  ROOT %b = f32[131072,2]{1,0:T(8,128)S(1)} broadcast(%c), dimensions={}
}
""")
  assert zeros.bytes == 4 and zeros.vmem_bytes == 131072 * 128 * 4
  assert zeros.seconds == pytest.approx(131072 * 128 * 4 / CHIP.vmem_bytes_per_s)


def test_a_pallas_kernel_is_costed_by_its_cost_estimate():
  config = ('{"custom_call_config":{"body":"TUzvUgE=","cost_estimate":{"flops":"4000000000",'
            '"transcendentals":"5","bytes_accessed":"65536","remote_bytes_transferred":"0"}}}')
  text = f"""HloModule m

ENTRY %main (x: f32[256,128]) -> f32[256,128] {{
  %x = f32[256,128]{{1,0:T(8,128)}} parameter(0)
  ROOT %k = f32[256,128]{{1,0:T(8,128)}} custom-call(%x), custom_call_target="tpu_custom_call", backend_config={config}
}}
"""
  cost = _cost(text)
  assert cost.flops == 4e9 and cost.bytes == 65536
  assert cost.seconds == pytest.approx(max(4e9 / CHIP.bf16_flops, 65536 / CHIP.hbm_bytes_per_s))
  without = _cost(text.replace(',"cost_estimate":{"flops":"4000000000","transcendentals":"5","bytes_accessed":'
                               '"65536","remote_bytes_transferred":"0"}', ""))
  assert without.flops == 0 and without.bytes == 2 * 256 * 128 * 4  # as any op: its operand and result
