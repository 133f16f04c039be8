"""`nerfpod bench`: a config's throughput, achieved FLOP/s against the measured matmul peak, time to quality.

  nerfpod bench --config=configs/tiny_fast.py:path=tiny_nerf_data.npz --steps=30
  nerfpod bench --config=configs/tiny_fast.py:path=... --quality --max_seconds=600

Throughput mode times `--steps` train steps after compilation, each waited for alone (rays/s, samples/s, the
step's and the data's time), then as many again as the training loop runs them, the next dispatched while
one is in flight (`pipelined_rays_per_s`: what training gets; an accelerator's steps overlap), the step's FLOPs as
XLA counts them (cost analysis of the lowered step, 2 per multiply-add; over all devices) divided by its
time and the device count (FLOP/s per device), the float32 matmul peak of one device measured in the same
process (a jitted 2048^3 matmul, best of several under XLA's default
compile options and the step's), their ratio (and with `model.compute_dtype=bfloat16`, the same against the
bfloat16 matmul peak), the share of time spent loading data, and peak memory (host RSS; device memory where
the backend reports it).
Quality mode trains the config from scratch and evaluates the held-out split every `--eval_every` steps,
recording the wall time since the process started (evaluation pauses excluded; also the process's CPU time,
less disturbed by other load) at which the mean PSNR first
reaches 20, 25, 28 and 30 dB (and any --targets), the training's rays/s, and at its end which samples matter: how many samples per ray each field
spends (proposal rounds apart) and the share of the NeRF field's samples that carry a non-negligible weight
(> 1% of the ray's light) on the first held-out views. Results print as a JSON line (and go to --out if
given).
"""
import json
import platform
import resource
import time

_START = time.perf_counter()

from absl import flags  # noqa: E402
from ml_collections import config_flags  # noqa: E402

from nerfpod.errors import Command  # noqa: E402

ABOUT = "benchmark a config: throughput, FLOP/s against the peak, time to quality"
FLAGS = flags.FlagValues()  # its own: `config` is also nerfpod.main's flag, and the aot tool's


def _psnrs(values) -> bool:
  try:
    return all(float(value) > 0 for value in values)
  except ValueError:
    return False


config_flags.DEFINE_config_file("config", None, "Config file to benchmark.", flag_values=FLAGS,
                                          lock_config=True)
_STEPS = flags.DEFINE_integer("steps", 30, "Timed train steps (throughput mode).", lower_bound=1, flag_values=FLAGS)
_QUALITY = flags.DEFINE_bool("quality", False, "Measure time to held-out PSNR 20/25/28/30 dB instead.",
                             flag_values=FLAGS)
_MAX_SECONDS = flags.DEFINE_float("max_seconds", 600.0, "Quality mode: stop after this much wall time.",
                                  lower_bound=0.0, flag_values=FLAGS)
_EVAL_EVERY = flags.DEFINE_integer("eval_every", 250, "Quality mode: steps between held-out evaluations.",
                                   lower_bound=1, flag_values=FLAGS)
_OUT = flags.DEFINE_string("out", None, "Also write the JSON result to this file.", flag_values=FLAGS)
_PEAK_SIZE = flags.DEFINE_integer("peak_matmul_size", 2048, "Throughput mode: n of the n x n x n matmul whose "
                                  "FLOP/s is the peak (a large accelerator needs a larger one to be busy).",
                                  lower_bound=1, flag_values=FLAGS)
_TARGETS = flags.DEFINE_list("targets", [], "Quality mode: more held-out PSNRs (dB) to time, beside 20, 25, 28 "
                             "and 30, e.g. --targets=31,33.", flag_values=FLAGS)
flags.register_validator("targets", _psnrs, "not a list of PSNRs in dB", flag_values=FLAGS)
THRESHOLDS = (20.0, 25.0, 28.0, 30.0)
NEGLIGIBLE_WEIGHT = 0.01  # a sample below this share of its ray's light hardly changes the pixel


def matmul_peak_flops(compiler_options: dict | None = None, n: int = 2048, repeats: int = 5,
                      dtype: str = "float32") -> float:
  """FLOP/s of a jitted n x n x n `dtype` matmul on the default device, best of `repeats`, compiled both
  with XLA's defaults and with `compiler_options` (the step's), whichever is faster: the peak is the
  machine's, not that of the step's compile settings."""
  import jax
  a = jax.random.normal(jax.random.key(0), (n, n), dtype)
  b = jax.random.normal(jax.random.key(1), (n, n), dtype)
  best = float("inf")
  for options in ({}, compiler_options or {}):
    f = jax.jit(lambda x, y: x @ y, compiler_options=options)
    f(a, b).block_until_ready()
    for _ in range(repeats):
      t = time.perf_counter()
      f(a, b).block_until_ready()
      best = min(best, time.perf_counter() - t)
  return 2.0 * n**3 / best


def _peak_memory() -> dict:
  import jax
  out = {"host_peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
  stats = jax.local_devices()[0].memory_stats() or {}
  if "peak_bytes_in_use" in stats:
    out["device_peak_mib"] = stats["peak_bytes_in_use"] / 2**20
  return out


def _first(cost):
  """XLA's cost analysis as one dict (older JAX gave a list of one)."""
  return cost[0] if isinstance(cost, (list, tuple)) and cost else cost


class _Trainer:
  """A config's components (nerfpod.run.components), its train step and a batch stream from step 0."""

  def __init__(self, config):
    from nerfpod import distributed
    from nerfpod.run import components, step, train_state
    self.config = config
    self.comps = components.build(config)
    compiling = step.start_compiling(self.comps)  # as a run starts: the step compiles during the init
    self.state = self.comps.init_state()
    self.step_fn, self.comps = compiling.result()
    # The same step without micro-batches, only ever lowered: XLA's cost analysis counts a loop body
    # once, so the FLOPs of a step with a micro-batch scan are read off this one.
    self.unlooped_step_fn = step.for_program(self.comps, microbatches=1)
    self.batches = self.comps.batches(0)
    self.key = train_state.rays_key(config.train.seed, self.comps.mesh)
    self._to_global = lambda local: distributed.to_global(self.comps.mesh, local)

  def next_batch(self):
    local = next(self.batches)
    local.pop("step")
    return self._to_global(local)

  def step(self, batch):
    self.state, metrics = self.step_fn(self.state, batch, self.key)
    return metrics

  def flops_per_step(self, batch) -> float:
    """The whole step's FLOPs over all devices as XLA counts them (2 per multiply-add), whatever the
    micro-batching. (XLA's cost analysis of a sharded step counts one device's share.)"""
    lowered = self.unlooped_step_fn.lower(self.state, batch, self.key)
    cost = _first(lowered.cost_analysis())
    if not cost:  # a GPU's lowered program has none (JAX 0.11, an H200): the compiled one's
      cost = _first(lowered.compile().cost_analysis())
    return float((cost or {}).get("flops", float("nan"))) * self.comps.mesh.size

  def heldout_psnr(self) -> float:
    import numpy as np
    from nerfpod.render import metrics
    from nerfpod.run import evaluate
    split = self.comps.scene.split(self.config.eval.split)
    return float(np.mean([metrics.psnr(np.clip(out["rgb"], 0, 1), split.image(index))
                          for index, out in evaluate.render_views(self.comps, self.state.params)]))


def throughput(config, steps: int, peak_size: int | None = None) -> dict:
  import jax
  from nerfpod.run import compilation
  trainer = _Trainer(config)
  flops_per_step = trainer.flops_per_step(trainer.next_batch())
  for _ in range(3):  # warm-up
    jax.block_until_ready(trainer.step(trainer.next_batch()))
  data_s = step_s = 0.0
  for _ in range(steps):
    t0 = time.perf_counter()
    batch = trainer.next_batch()
    jax.block_until_ready(batch)
    t1 = time.perf_counter()
    jax.block_until_ready(trainer.step(batch))
    t2 = time.perf_counter()
    data_s, step_s = data_s + t1 - t0, step_s + t2 - t1
  # The same number of steps as the training loop runs them: the next batch loaded and the next step
  # dispatched while one is in flight. On an accelerator this is what training gets (an H200's lego step:
  # 5.8 ms waited for alone, 3.9 ms in the loop); on a CPU the two agree.
  previous = None
  t0 = time.perf_counter()
  for _ in range(steps):
    metrics = trainer.step(trainer.next_batch())
    if previous is not None:
      jax.block_until_ready(previous)
    previous = metrics
  jax.block_until_ready(previous)
  pipelined_s = time.perf_counter() - t0
  options = compilation.compiler_options(config)
  size = {} if peak_size is None else {"n": peak_size}  # None: matmul_peak_flops's own default
  peak = matmul_peak_flops(options, **size)
  rays = steps * config.train.batch_size
  samples = samples_per_ray(config)
  achieved = flops_per_step * steps / step_s / trainer.comps.mesh.size  # per device, as the peak is
  return {"rays_per_s": rays / (data_s + step_s), "samples_per_s": rays * samples["field"] / (data_s + step_s),
          "samples_per_ray": samples,
          "step_ms": 1e3 * step_s / steps, "data_ms": 1e3 * data_s / steps,
          "pipelined_rays_per_s": rays / pipelined_s, "pipelined_step_ms": 1e3 * pipelined_s / steps,
          "data_fraction": data_s / (data_s + step_s), "flops_per_step": flops_per_step,
          "achieved_flops": achieved, "matmul_peak_flops": peak, "fraction_of_peak": achieved / peak,
          **_compute_dtype_peak(config, options, achieved, size), **_peak_memory()}


def _compute_dtype_peak(config, options: dict, achieved: float, size: dict | None = None) -> dict:
  """With mixed precision, also the peak of matmuls in the compute dtype (e.g. bfloat16 on TPU/GPU, where
  it is several times the float32 one) and the ratio to it."""
  dtype = config.model.compute_dtype
  if dtype == "float32":
    return {}
  peak = matmul_peak_flops(options, dtype=dtype, **(size or {}))
  return {f"matmul_peak_flops_{dtype}": peak, f"fraction_of_{dtype}_peak": achieved / peak}


def samples_per_ray(config) -> dict:
  """Samples per ray each kind of field is queried at in a train step: `field` (NeRF fields: coarse, and
  fine over the union of coarse and importance samples) and `proposal` (cheap density-only fields)."""
  r = config.render
  field = r.num_samples + (r.num_samples + r.num_importance if r.num_importance else 0)
  return {"field": field, "proposal": int(sum(r.proposal_samples))}


def weight_share(trainer, views: int = 2, chunk: int = 4096) -> dict:
  """Where the light is: on the first `views` held-out views, the final NeRF field's samples per ray and
  the share of them whose compositing weight exceeds NEGLIGIBLE_WEIGHT (evaluation sampling)."""
  import jax
  import jax.numpy as jnp
  import numpy as np
  from nerfpod.nerf import cameras
  comps = trainer.comps
  split = comps.scene.split(trainer.config.eval.split)
  apply = jax.jit(lambda p, o, d: comps.render_model.apply(p, o, d, comps.near, comps.far,
                                                           jnp.asarray(comps.scene.background))[-1]["weights"])
  above = total = 0
  for index in range(min(views, len(split))):
    origins, directions = cameras.image_rays(split.poses[index], split.intrinsics, trainer.config.data.pixel_center)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    for start in range(0, len(origins), chunk):
      weights = np.asarray(apply(trainer.state.params, origins[start:start + chunk], directions[start:start + chunk]))
      above += int(np.sum(weights > NEGLIGIBLE_WEIGHT))
      total += weights.size
      per_ray = weights.shape[-1]
  return {"samples_per_ray": per_ray, "share_above_negligible": above / total,
          "samples_above_negligible_per_ray": per_ray * above / total}


def _db(threshold: float) -> str:
  return f"{threshold:g}db"  # 28.0 -> "28db", 25.5 -> "25.5db"


def time_to_quality(config, max_seconds: float, eval_every: int, started: float | None = None,
                    thresholds=THRESHOLDS) -> dict:
  """Trains from scratch, evaluating every `eval_every` steps; the wall time (and this process's CPU time,
  which a loaded machine disturbs less) since start-up, evaluations excluded, at which each of `thresholds`
  (held-out PSNR, dB) is first reached, and the training's rays/s (from the end of the first step, which
  compiles, to the last). `started`: the perf_counter() reading taken as start-up (default: when this module
  was imported, as `nerfpod bench` does it; a caller that imported it long before passes its own)."""
  import jax
  thresholds = tuple(sorted(set(float(t) for t in thresholds)))
  start = _START if started is None else started
  trainer = _Trainer(config)
  paused = paused_cpu = 0.0  # time spent in the benchmark's own evaluations
  reached, reached_cpu, history = {}, {}, []
  previous = None
  first_step_done = None  # elapsed (evaluations excluded) when step 1 was done
  for step in range(1, config.train.num_steps + 1):
    # As the training loop does: the next step is dispatched (and its batch loaded) while this one runs,
    # with at most one step in flight; the clock is read once the step is done.
    metrics = trainer.step(trainer.next_batch())
    if previous is not None:
      jax.block_until_ready(previous)
    previous = metrics
    elapsed = time.perf_counter() - start - paused
    if step == 2:
      first_step_done = elapsed  # step 1's result was waited for just above
    if step % eval_every == 0 or step == config.train.num_steps or elapsed > max_seconds:
      jax.block_until_ready(metrics)
      elapsed, cpu = time.perf_counter() - start - paused, time.process_time() - paused_cpu
      t, c = time.perf_counter(), time.process_time()
      psnr = trainer.heldout_psnr()
      paused, paused_cpu = paused + time.perf_counter() - t, paused_cpu + time.process_time() - c
      last_elapsed = elapsed
      history.append({"step": step, "seconds": round(elapsed, 1), "cpu_seconds": round(cpu, 1),
                      "psnr": round(psnr, 2)})
      print(json.dumps(history[-1]), flush=True)
      for threshold in thresholds:
        if psnr >= threshold and threshold not in reached:
          reached[threshold], reached_cpu[threshold] = elapsed, cpu
      if elapsed > max_seconds or all(t in reached for t in thresholds):
        break
  last = history[-1]
  trained_rays = (last["step"] - 1) * config.train.batch_size
  rays_per_s = (trained_rays / (last_elapsed - first_step_done)
                if first_step_done is not None and last_elapsed > first_step_done else None)
  return {f"seconds_to_{_db(t)}": reached.get(t) for t in thresholds} | {
      f"cpu_seconds_to_{_db(t)}": reached_cpu.get(t) for t in thresholds} | {
      "rays_per_s": rays_per_s,
      "final_psnr": last["psnr"], "final_step": last["step"], "history": history,
      "samples_per_ray": samples_per_ray(config), "weights": weight_share(trainer), **_peak_memory()}


def _check(config) -> None:
  from nerfpod import schema  # (not at import: `nerfpod bench --help` stays quick)
  schema.validate(config)


def main(config):
  """The benchmark of a checked config: one JSON line (and --out)."""
  import jax
  from nerfpod import distributed
  from nerfpod.run import compilation
  distributed.keep_off_absent_tpu()  # libtpu installed (the `tpu` extra) on a machine without a TPU
  compilation.tune_host(config)  # process-wide, as a training process sets it
  result = {"config": {"field": config.model.field, "samples": config.render.num_samples,
                       "importance": config.render.num_importance,
                       "proposal_samples": list(config.render.proposal_samples),
                       "batch_size": config.train.batch_size, "steps": config.train.num_steps,
                       "data": config.data.kind, "downscale": config.data.downscale},
            "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                        "backend": jax.default_backend(), "devices": jax.device_count(),
                        "device_kind": jax.devices()[0].device_kind},
            "compiler_options": compilation.compiler_options(config)}
  if _QUALITY.value:
    targets = [float(t) for t in _TARGETS.value]
    result["quality"] = time_to_quality(config, _MAX_SECONDS.value, _EVAL_EVERY.value,
                                        thresholds=THRESHOLDS + tuple(targets))
  else:
    result["throughput"] = throughput(config, _STEPS.value, _PEAK_SIZE.value)
  line = json.dumps(result)
  print(line)
  if _OUT.value:
    with open(_OUT.value, "w") as f:
      f.write(line + "\n")


def run(argv=None):
  """`nerfpod bench ...` and `python -m nerfpod.bench ...` (argv: the words after it; None: sys.argv[1:])."""
  Command("nerfpod bench", ABOUT, FLAGS, required=("config",), check=_check,
          examples={"config": "configs/default.py", "targets": "31,33"}).run(argv, main)


if __name__ == "__main__":
  run()
