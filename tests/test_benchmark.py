"""nerfpod bench (nerfpod/bench.py): its throughput report, and FLOPs that count every micro-batch."""
import time

import pytest

from conftest import smoke_config
from nerfpod import bench as benchmark

pytestmark = pytest.mark.slow


@pytest.fixture(autouse=True)
def small_peak_matmul(monkeypatch):
  """The machine's matmul peak from 512^3 matmuls instead of 2048^3: these tests check how the report uses the
  peak, not its value, and a 2048^3 bfloat16 matmul takes seconds on a CPU."""
  peak = benchmark.matmul_peak_flops
  monkeypatch.setattr(benchmark, "matmul_peak_flops", lambda options=None, n=512, repeats=2, dtype="float32":
                      peak(options, n=n, repeats=repeats, dtype=dtype))

# An MLP small enough to benchmark in seconds, big enough that its matmuls are most of its FLOPs.
MLP = {"model.field": "mlp", "model.mlp.depth": 2, "model.mlp.width": 64, "model.mlp.skips": (),
       "model.mlp.num_frequencies": 6, "render.num_samples": 32, "train.batch_size": 256}


def _matmul_flops_per_step(config) -> float:
  """The MLP's matmul FLOPs per train step, by hand: per layer and sample, 2 * (in x out) forward, as many
  for the weights' gradient, and as many for the gradient of the layer's input, but the first's (the
  encoded points need none)."""
  m = config.model.mlp
  widths = [3 * (1 + 2 * m.num_frequencies)] + [m.width] * m.depth + [4]
  layers = [2 * a * b for a, b in zip(widths[:-1], widths[1:])]
  return (3 * sum(layers) - layers[0]) * config.render.num_samples * config.train.batch_size


def test_throughput_report_and_flops_that_count_every_micro_batch():
  config = smoke_config(**MLP)
  one = benchmark.throughput(config, steps=2)
  for key in ("rays_per_s", "samples_per_s", "step_ms", "data_ms", "achieved_flops", "matmul_peak_flops",
              "pipelined_rays_per_s", "pipelined_step_ms"):
    assert one[key] > 0, key
  assert 0 <= one["data_fraction"] < 1 and one["host_peak_rss_mib"] > 0
  assert one["pipelined_rays_per_s"] == pytest.approx(
      config.train.batch_size / (one["pipelined_step_ms"] / 1e3))
  assert one["fraction_of_peak"] == pytest.approx(one["achieved_flops"] / one["matmul_peak_flops"])
  assert "matmul_peak_flops_bfloat16" not in one  # float32 matmuls: no bfloat16 peak (next test: with them)
  # The hand count of the matmuls, plus the encoding, activations and compositing that XLA counts too,
  # over all 8 devices of the tests.
  by_hand = _matmul_flops_per_step(config)
  assert 1.0 <= one["flops_per_step"] / by_hand < 1.15, (one["flops_per_step"], by_hand)
  # With 4 micro-batches the step loops over a scan, whose body XLA's cost analysis counts once: the
  # benchmark must still report the FLOPs of all four (a quarter of them would fail the hand count).
  config.train.microbatches = 4
  four = benchmark.throughput(config, steps=1)
  assert 1.0 <= four["flops_per_step"] / by_hand < 1.15, (four["flops_per_step"], by_hand)


def test_flops_come_from_the_compiled_step_where_the_lowered_one_has_no_cost_analysis(monkeypatch):
  """On a GPU (JAX 0.11, an H200) a lowered program's cost_analysis() is None: the report took it for a
  dict and failed. The compiled step's count is the same program's."""
  import jax
  config = smoke_config(**MLP)
  trainer = benchmark._Trainer(config)
  batch = trainer.next_batch()
  lowered_count = trainer.flops_per_step(batch)
  monkeypatch.setattr(jax.stages.Lowered, "cost_analysis", lambda self: None)
  compiled_count = trainer.flops_per_step(batch)
  assert compiled_count > 0 and compiled_count == pytest.approx(lowered_count, rel=0.05)


def test_mixed_precision_is_also_measured_against_the_bfloat16_peak():
  config = smoke_config(**{"train.batch_size": 64, "model.compute_dtype": "bfloat16"})
  result = benchmark.throughput(config, steps=1)
  assert result["matmul_peak_flops_bfloat16"] > 0
  assert result["fraction_of_bfloat16_peak"] == pytest.approx(
      result["achieved_flops"] / result["matmul_peak_flops_bfloat16"])


def test_quality_mode_reports_thresholds_and_the_samples_that_matter():
  config = smoke_config(**{"render.proposal_samples": (16,), "render.num_samples": 8, "train.num_steps": 4})
  # (The clock starts now: this module may have been imported long before the test runs.)
  result = benchmark.time_to_quality(config, max_seconds=600, eval_every=2, started=time.perf_counter(),
                                     thresholds=benchmark.THRESHOLDS + (31.5, 20))
  assert set(result) >= {"seconds_to_20db", "seconds_to_25db", "seconds_to_28db", "seconds_to_30db",
                         "seconds_to_31.5db", "cpu_seconds_to_30db", "cpu_seconds_to_31.5db"}
  assert len([k for k in result if k.startswith("seconds_to_")]) == 5  # 20 once
  # Rays/s over steps 2..4, timed without the first step's compilation.
  seconds = result["history"][-1]["seconds"]
  assert 3 * config.train.batch_size / seconds < result["rays_per_s"] < 1e8
  assert [h["step"] for h in result["history"]] == [2, 4]
  assert result["samples_per_ray"] == {"field": 8, "proposal": 16}
  weights = result["weights"]
  assert weights["samples_per_ray"] == 8 and 0.0 <= weights["share_above_negligible"] <= 1.0
  assert weights["samples_above_negligible_per_ray"] == pytest.approx(8 * weights["share_above_negligible"])
  assert benchmark.samples_per_ray(smoke_config(**{"render.num_importance": 16, "render.proposal_samples": ()})) == {"field": 48, "proposal": 0}
