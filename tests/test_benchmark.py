"""tools/benchmark.py: its throughput report, and FLOPs that do not depend on micro-batching."""
import pytest

from conftest import smoke_config
from tools import benchmark


def test_throughput_report_and_flops_independent_of_microbatches():
  config = smoke_config(**{"train.batch_size": 256})
  one = benchmark.throughput(config, steps=2)
  for key in ("rays_per_s", "samples_per_s", "step_ms", "data_ms", "achieved_flops", "matmul_peak_flops"):
    assert one[key] > 0, key
  assert 0 <= one["data_fraction"] < 1 and one["host_peak_rss_mib"] > 0
  assert one["fraction_of_peak"] == pytest.approx(one["achieved_flops"] / one["matmul_peak_flops"])
  # XLA's cost analysis counts a loop body once: a step with a 4-slice scan must still report all FLOPs.
  config.train.microbatches = 4
  four = benchmark.throughput(config, steps=1)
  assert four["flops_per_step"] == pytest.approx(one["flops_per_step"], rel=1e-6)


def test_mixed_precision_is_also_measured_against_the_bfloat16_peak():
  config = smoke_config(**{"train.batch_size": 256, "model.compute_dtype": "bfloat16"})
  result = benchmark.throughput(config, steps=1)
  assert result["matmul_peak_flops_bfloat16"] > 0
  assert result["fraction_of_bfloat16_peak"] == pytest.approx(
      result["achieved_flops"] / result["matmul_peak_flops_bfloat16"])
  assert "matmul_peak_flops_bfloat16" not in benchmark.throughput(smoke_config(**{"train.batch_size": 256}),
                                                                   steps=1)
