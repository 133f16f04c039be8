"""The device check: one call on an accelerator machine measures what nerfpod does there.

    bash tools/device_check.sh [--tiny] [--out=DIR] [--data=DIR] [--budget_s=540]

(tools/device_check.sh installs the wheels tools/device_wheels.sh put in .whl/, then runs this.) Stages,
each a process of its own with a time limit, so that one that fails or overruns leaves the others' figures:

  env        the card (nvidia-smi), the driver, JAX's version, backend, device kind and count
  bench      `nerfpod bench` of the accelerator lego config (configs/blender_fast.py) at 4,096 and 16,384
             rays a step: rays/s, step time, FLOP/s against the measured matmul peak, device memory
  default    the default job end to end (train, evaluate, orbit, archive, videos): wall time and metrics
  quality    time to 30 / 32 / 33 dB held-out PSNR on lego_400's val split at 400x400 (`nerfpod bench
             --quality`), with whatever budget is left after the other stages' reserve
  capture    a real capture at the accelerator size (configs/capture.py:path=DIR,big; the cup, exported by
             tools/device_wheels.sh as a transforms.json) for 8,000 steps: as it is (with the proposal
             sampler's guards), as it was before them (what an H200 showed: a loss spike, then held-out PSNR
             18.5 dB against 29.2 dB on a CPU), at 512 rays a step, then older candidates where time is left:
             held-out PSNR, training PSNR, loss spikes, the interlevel term and the NeRF's window of each, and
             its events (scalars, depth previews) and metrics.json kept in DIR/capture_NAME/
  pod        a pod-shaped run: launch/local.py's 2 processes, each on one GPU where there are two, else on
             simulated CPU devices (a one-GPU machine cannot give two processes a GPU each)

The figures go to DIR/device_check.json and DIR/device_check.md (DIR: --out, else $OUT where set, else
./device_check), rewritten after every stage, with every stage's output in DIR/device_check.log.
`--tiny` runs the same stages on the CPU in about a minute, on the procedural scene (tests/test_device_check.py:
the script never rots). Where lego_400 is absent (--data, else .devdata/lego_400, else
../shared/data/lego_400) the lego stages are skipped, saying so.
"""
import argparse
import datetime
import json
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PYTHON = sys.executable

# The accelerator lego config, its data and overrides: 400x400 lego, evaluated on val (the shared copy has no
# test split); evaluation renders 32,768 rays a call (an accelerator's calls, not a CPU's cache-sized ones).
LEGO_CONFIG = "configs/blender_fast.py:scene=lego"
LEGO_OVERRIDES = ("--config.eval.split=val", "--config.eval.chunk=32768", "--config.orbit.chunk=32768")
TINY_CONFIG = "configs/default.py:smoke"


def _now() -> str:
  return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


class Check:
  """The report being built: stages in order, each {'status', 'seconds', ...figures}, written out after each."""

  def __init__(self, out: str, tiny: bool):
    self.out, self.tiny = out, tiny
    os.makedirs(out, exist_ok=True)
    self.log_path = os.path.join(out, "device_check.log")
    open(self.log_path, "w").close()
    self.report = {"started": _now(), "tiny": tiny, "commit": _commit(), "stages": {}}

  def run(self, args: list[str], timeout: float, env: dict | None = None, cwd: str = REPO) -> tuple[int, str, float]:
    """(exit status, output, seconds) of a child process; status 124 when it ran past `timeout`."""
    started = time.perf_counter()
    with open(self.log_path, "a") as log:
      log.write(f"\n$ {' '.join(args)}\n")
      log.flush()
      child_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
      child_env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO, child_env.get("PYTHONPATH", "")) if p)
      try:
        done = subprocess.run(args, cwd=cwd, env=child_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True, timeout=max(timeout, 1.0))
        code, output = done.returncode, done.stdout
      except subprocess.TimeoutExpired as e:
        code = 124
        output = (e.stdout.decode(errors="replace") if isinstance(e.stdout, bytes) else e.stdout or "")
        output += f"\n[device_check: stopped after {timeout:.0f} s]\n"
      log.write(output)
    return code, output, time.perf_counter() - started

  def record(self, name: str, result: dict) -> None:
    self.report["stages"][name] = result
    self.report["finished"] = _now()
    with open(os.path.join(self.out, "device_check.json"), "w") as f:
      json.dump(self.report, f, indent=1)
    with open(os.path.join(self.out, "device_check.md"), "w") as f:
      f.write(markdown(self.report))
    print(f"device_check: {name}: {result.get('status')} ({result.get('seconds', 0):.0f} s)", flush=True)


def _commit() -> str | None:
  try:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                            timeout=10).stdout.strip()
  except (OSError, subprocess.SubprocessError):
    commit = ""
  return os.environ.get("NERFPOD_COMMIT") or commit  # a copy of the tree whose .git is not its own: the caller says


def _last_json(output: str) -> dict | None:
  """The last line of `output` that is a JSON object (nerfpod bench prints its result as one)."""
  for line in reversed(output.splitlines()):
    line = line.strip()
    if line.startswith("{") and line.endswith("}"):
      try:
        return json.loads(line)
      except json.JSONDecodeError:
        continue
  return None


def _tail(output: str, lines: int = 15) -> str:
  return "\n".join(output.rstrip().splitlines()[-lines:])


ENV_PROBE = r"""
import json, platform, sys
import jax, jaxlib
out = {"python": platform.python_version(), "jax": jax.__version__, "jaxlib": jaxlib.__version__,
       "backend": jax.default_backend(), "device_count": jax.device_count(),
       "device_kind": jax.devices()[0].device_kind, "platform": jax.devices()[0].platform}
from importlib import metadata
for name in ("flax", "optax", "orbax-checkpoint", "grain", "tensorstore", "numpy"):
  try:
    out[name] = metadata.version(name)
  except metadata.PackageNotFoundError:
    out[name] = "missing"
from nerfpod.render import lpips, video  # what the default job will find: an ffmpeg for mp4s, LPIPS's weights
out["ffmpeg"], out["lpips_weights"] = video.mp4_available(), lpips.available("alex")
stats = jax.local_devices()[0].memory_stats() or {}
if "bytes_limit" in stats:
  out["device_memory_gib"] = round(stats["bytes_limit"] / 2**30, 1)
print(json.dumps({k: v if isinstance(v, (bool, int, float)) else str(v) for k, v in out.items()}))
"""


def stage_env(check: Check) -> dict:
  result = {}
  if shutil.which("nvidia-smi"):
    code, output, _ = check.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total",
                                 "--format=csv,noheader"], 30)
    if code == 0 and output.strip():
      name, driver, memory = [s.strip() for s in output.strip().splitlines()[0].split(",")][:3]
      result.update(gpu=name, driver=driver, gpu_memory=memory, gpus=len(output.strip().splitlines()))
  code, output, seconds = check.run([PYTHON, "-c", ENV_PROBE], 120)
  probe = _last_json(output)
  result.update(probe or {})
  return {"status": "ok" if code == 0 and probe else "failed", "seconds": seconds, **result,
          **({} if code == 0 else {"tail": _tail(output)})}


def stage_bench(check: Check, config: list[str], batch_size: int, steps: int, timeout: float,
                peak_size: int, backend: str | None) -> dict:
  args = [PYTHON, "-m", "nerfpod.bench", *config, f"--config.train.batch_size={batch_size}", f"--steps={steps}",
          f"--peak_matmul_size={peak_size}"]
  code, output, seconds = check.run(args, timeout)
  result = _last_json(output)
  if code != 0 or not result or "throughput" not in result:
    return {"status": "timeout" if code == 124 else "failed", "seconds": seconds, "tail": _tail(output)}
  t = result["throughput"]
  keep = ("rays_per_s", "samples_per_s", "step_ms", "data_ms", "data_fraction", "pipelined_rays_per_s",
          "pipelined_step_ms", "flops_per_step", "achieved_flops",
          "matmul_peak_flops", "fraction_of_peak", "device_peak_mib", "host_peak_rss_mib")
  ran_on = (result.get("machine") or {}).get("backend")
  return {"status": "ok" if backend in (None, ran_on) else f"ran on {ran_on}, not {backend}", "seconds": seconds,
          "batch_size": batch_size, "steps": steps, **{k: t[k] for k in keep if k in t},
          "machine": result.get("machine")}


def _job(check: Check, config: str, workdir: str, timeout: float, backend: str | None, extra: tuple = (),
         env: dict | None = None) -> tuple[dict, str]:
  """(result, output) of `nerfpod train` of `config` into a fresh `workdir`: status, seconds, exit code, the
  first line (which names the backend: a run on another than `backend` is marked) and eval/metrics.json's
  step, view count and means; the output's tail where it did not end well. The stages add their own."""
  shutil.rmtree(workdir, ignore_errors=True)
  args = [PYTHON, "-m", "nerfpod.main", f"--config={config}", f"--workdir={workdir}", *extra]
  code, output, seconds = check.run(args, timeout, env=env)
  result = {"status": "ok" if code == 0 else ("timeout" if code == 124 else "failed"), "seconds": seconds,
            "exit_code": code}
  first = [line for line in output.splitlines() if line.startswith("nerfpod: JAX ")]
  if first:
    result["first_line"] = first[0]
    if backend and f" on {backend}:" not in first[0] and result["status"] == "ok":
      result["status"] = f"not on {backend}"
  try:
    with open(os.path.join(workdir, "eval", "metrics.json")) as f:
      metrics = json.load(f)
    result.update(step=metrics["step"], views=len(metrics["views"]), **{k: v for k, v in metrics["mean"].items()})
  except (OSError, KeyError, ValueError):
    result["status"] = "failed" if result["status"] == "ok" else result["status"]
  if result["status"] != "ok":
    result["tail"] = _tail(output)
  return result, output


def stage_default(check: Check, config: str, workdir: str, timeout: float, lpips: bool,
                  backend: str | None) -> dict:
  result, output = _job(check, config, workdir, timeout, backend,
                        () if lpips else ("--config.eval.lpips_net=none",))
  result["lpips"] = lpips
  renders = os.path.join(workdir, "renders")
  result["renders"] = sorted(os.listdir(renders)) if os.path.isdir(renders) else []
  for line in output.splitlines():
    if "rendered" in line and "s/frame" in line:
      result["orbit_line"] = line.strip()
  return result


def stage_quality(check: Check, config: list[str], max_seconds: float, eval_every: int, targets: str,
                  timeout: float) -> dict:
  args = [PYTHON, "-m", "nerfpod.bench", *config, "--quality", f"--max_seconds={max_seconds:.0f}",
          f"--eval_every={eval_every}", f"--targets={targets}"]
  code, output, seconds = check.run(args, timeout)
  result = _last_json(output)
  if code != 0 or not result or "quality" not in result:
    # the evaluations it printed before it stopped still say when each target was reached
    history = [json.loads(line) for line in output.splitlines() if line.startswith('{"step"')]
    reached = {}
    for target in ["20", "25", "28", "30", *targets.split(",")]:
      first = next((h["seconds"] for h in history if h["psnr"] >= float(target)), None)
      reached[f"seconds_to_{float(target):g}db"] = first
    return {"status": "timeout" if code == 124 else "failed", "seconds": seconds, "history": history,
            **reached, **({"final_psnr": history[-1]["psnr"], "final_step": history[-1]["step"]} if history else {}),
            "tail": _tail(output)}
  q = result["quality"]
  return {"status": "ok", "seconds": seconds, "max_seconds": max_seconds,
          **{k: v for k, v in q.items() if k.startswith("seconds_to_") or k in (
              "rays_per_s", "final_psnr", "final_step", "history", "device_peak_mib")}}


# The capture stage's variants: (name, overrides, environment). On an H200 the cup at `big` spiked (loss x10 at
# step 2,000-2,900), after which its proposal and distortion losses were gone and held-out PSNR fell to 18.5 dB
# (the same grid on a CPU, 512 rays a step: 29.2 dB): proposal resampling's trap (stepfun.resampling_weights).
# `big` now pads and anneals its resampling and keeps the density's gradient above its clamp: the cup at `big`
# as it is, as it was before those guards, and at the CPU's 512 rays a step on the same schedule; then the
# older candidates (TF32 matmuls, Adam's b2), where time is left.
AS_WAS = ("--config.render.proposal_padding=0", "--config.train.proposal_anneal_steps=0",
          "--config.model.trunc_exp=false")
CAPTURE_VARIANTS = (
    ("fixed", (), {}),
    ("as_was", AS_WAS, {}),
    ("rays_512", ("--config.train.batch_size=512",), {}),
    ("as_was_matmul_highest", AS_WAS, {"JAX_DEFAULT_MATMUL_PRECISION": "highest"}),
    ("as_was_adam_b2_0.999", AS_WAS + ("--config.train.adam_b2=0.999",), {}),
)
# --tiny: the stage's mechanics on the procedural scene, with one override (as it is, the variant would be the
# default stage's job again)
TINY_CAPTURE_VARIANTS = (("padded", ("--config.render.proposal_padding=0.01",), {}),)
STEP_LINE = re.compile(r"^step\s+(\d+)/\d+ \| loss ([-+.\deE]+) \| psnr\s+([-+.\deE]+) dB")
# The proposal diagnostics of the same line (monitor.Monitor.scalars): the interlevel term and the NeRF's window.
PROPOSAL_LINE = re.compile(r"^step\s+(\d+)/.*\| interlevel ([-+.\deE]+) \| window ([-+.\deE]+)")


def loss_spikes(steps: list[int], losses: list[float], factor: float = 4.0, window: int = 5) -> list[int]:
  """The logged steps whose loss is over `factor` times the median of the `window` logged before it."""
  return [steps[i] for i in range(window, len(losses))
          if losses[i] > factor * statistics.median(losses[i - window:i])]


def stage_capture(check: Check, config: str, overrides: tuple, env: dict, workdir: str, timeout: float,
                  backend: str | None, keep: str, image_every: int) -> dict:
  """One capture variant: its held-out metrics, training PSNR, losses and spikes, and per logged step the
  interlevel term and the NeRF's sampling window; its TensorBoard events (every scalar, and the held-out
  preview's colour and depth every `image_every` steps) and eval/metrics.json copied into `keep`."""
  result, output = _job(check, config, workdir, timeout, backend, ("--config.orbit.render_after_training=False",
                                                                    "--config.eval.lpips_net=none",
                                                                    f"--config.train.image_every={image_every}",
                                                                    *overrides), env)
  result.update(overrides=list(overrides), env=env)
  logged = [STEP_LINE.match(line) for line in output.splitlines()]
  logged = [(int(m[1]), float(m[2]), float(m[3])) for m in logged if m]
  if logged:
    steps, losses, psnrs = zip(*logged)
    result.update(train_psnr=psnrs[-1], loss_spikes=loss_spikes(list(steps), list(losses)),
                  losses={str(k): v for k, v in zip(steps, losses)})
  proposal = [PROPOSAL_LINE.match(line) for line in output.splitlines()]
  proposal = [m for m in proposal if m]
  if proposal:
    result.update(interlevel={m[1]: float(m[2]) for m in proposal}, window={m[1]: float(m[3]) for m in proposal})
  result["collapse_warning"] = any("proposal sampling has collapsed" in line for line in output.splitlines())
  os.makedirs(keep, exist_ok=True)
  kept = []
  for name in sorted(os.listdir(workdir)) if os.path.isdir(workdir) else []:
    if name.startswith("events.out.tfevents"):
      shutil.copy(os.path.join(workdir, name), keep)
      kept.append(name)
  if os.path.exists(os.path.join(workdir, "eval", "metrics.json")):
    shutil.copy(os.path.join(workdir, "eval", "metrics.json"), keep)
    kept.append("metrics.json")
  result["kept"] = kept
  return result


def stage_pod(check: Check, gpus: int, workdir: str, timeout: float, tiny: bool) -> dict:
  shutil.rmtree(workdir, ignore_errors=True)
  forwarded = ["--", f"--config={TINY_CONFIG}", f"--workdir={workdir}"]
  if tiny:  # (the default stage renders the previews and the orbit; the test suite renders them from two processes)
    forwarded += ["--config.train.image_every=0", "--config.orbit.render_after_training=False"]
  if gpus >= 2:
    # One GPU a process: the launcher's CPU settings are replaced by each process's own visible GPU.
    args = [PYTHON, os.path.join(REPO, "launch", "local.py"), "--num_processes=2", "--devices_per_process=1",
            "--platform=gpu", *forwarded]
    how = "2 processes x 1 GPU"
  else:
    per = 1 if tiny else 4
    args = [PYTHON, os.path.join(REPO, "launch", "local.py"), "--num_processes=2", f"--devices_per_process={per}",
            *forwarded]
    how = f"2 processes x {per} simulated CPU devices" + (" (one GPU: two processes cannot each have one)"
                                                          if gpus == 1 else "")
  code, output, seconds = check.run(args, timeout)
  result = {"status": "ok" if code == 0 else ("timeout" if code == 124 else "failed"), "seconds": seconds,
            "how": how, "exit_code": code}
  try:
    with open(os.path.join(workdir, "eval", "metrics.json")) as f:
      result["psnr"] = json.load(f)["mean"]["psnr"]
  except (OSError, KeyError, ValueError):
    result["status"] = "failed" if result["status"] == "ok" else result["status"]
  if result["status"] != "ok":
    result["tail"] = _tail(output)
  return result


def _fmt(value, digits: int = 0) -> str:
  if value is None:
    return "-"
  if isinstance(value, float) and not math.isfinite(value):
    return str(value)
  return f"{value:,.{digits}f}" if isinstance(value, (int, float)) else str(value)


def markdown(report: dict) -> str:
  """One table of the figures, for docs/results.md."""
  s = report["stages"]
  env = s.get("env", {})
  lines = [f"Device check ({'tiny, ' if report['tiny'] else ''}{report['started']}; commit {report['commit'] or '-'}): "
           f"{env.get('gpu', env.get('device_kind', '?'))}, driver {env.get('driver', '-')}, JAX {env.get('jax', '?')} "
           f"({env.get('backend', '?')}, {env.get('device_count', '?')} device(s)), Python {env.get('python', '?')}.",
           "", "| stage | status | figures |", "| --- | --- | --- |"]
  for name, r in s.items():
    if name == "env":
      figures = (f"flax {r.get('flax')}, optax {r.get('optax')}, orbax {r.get('orbax-checkpoint')}, "
                 f"grain {r.get('grain')}, tensorstore {r.get('tensorstore')}; device memory "
                 f"{_fmt(r.get('device_memory_gib'), 1)} GiB; ffmpeg {'yes' if r.get('ffmpeg') else 'no'}")
    elif name.startswith("bench") and "rays_per_s" in r:
      figures = (f"{r['batch_size']:,} rays/step: {_fmt(r.get('rays_per_s'))} rays/s, step {_fmt(r.get('step_ms'), 2)} ms "
                 f"(data {_fmt(r.get('data_ms'), 2)} ms) waited for alone; in the training loop's order "
                 f"{_fmt(r.get('pipelined_rays_per_s'))} rays/s, {_fmt(r.get('pipelined_step_ms'), 2)} ms a step; {_fmt(r.get('achieved_flops', 0) / 1e12, 2)} TFLOP/s = "
                 f"{_fmt(100 * r.get('fraction_of_peak', 0), 1)}% of the f32 matmul peak "
                 f"({_fmt(r.get('matmul_peak_flops', 0) / 1e12, 1)} TFLOP/s), device peak "
                 f"{_fmt(r.get('device_peak_mib'))} MiB")
    elif name == "default" and "psnr" in r:
      figures = (f"{_fmt(r['seconds'], 1)} s end to end; step {r.get('step')}: PSNR {_fmt(r['psnr'], 2)} dB, SSIM "
                 f"{_fmt(r.get('ssim'), 4)}" + (f", LPIPS {_fmt(r['lpips'], 4)}" if isinstance(r.get('lpips'), float)
                                                else "") + f" over {r.get('views')} views; "
                 f"{', '.join(r.get('renders', []))}")
    elif name == "quality" and r.get("history"):
      reached = ", ".join(f"{k.removeprefix('seconds_to_')} in {_fmt(v, 1)} s" if v is not None else
                          f"{k.removeprefix('seconds_to_')} not reached" for k, v in r.items()
                          if k.startswith("seconds_to_"))
      figures = (f"{reached}; {_fmt(r.get('final_psnr'), 2)} dB at step {r.get('final_step')} (within "
                 f"{_fmt(r.get('max_seconds'))} s); {_fmt(r.get('rays_per_s'))} rays/s")
    elif name.startswith("capture_") and "psnr" in r:
      figures = (f"{' '.join(r['overrides'] + [f'{k}={v}' for k, v in r['env'].items()]) or 'as it is'}: "
                 f"held-out PSNR {_fmt(r['psnr'], 2)} dB, SSIM {_fmt(r.get('ssim'), 4)} at step {r.get('step')}; "
                 f"training PSNR {_fmt(r.get('train_psnr'), 2)} dB; loss spikes at steps "
                 f"{', '.join(map(str, r.get('loss_spikes', []))) or 'none'}; NeRF window at the end "
                 f"{_fmt(list(r.get('window', {}).values() or [None])[-1], 3)}"
                 f"{'; collapse warned' if r.get('collapse_warning') else ''}; {_fmt(r['seconds'], 1)} s")
    elif name == "pod" and r.get("status") == "ok":
      figures = f"{r['how']}: {_fmt(r['seconds'], 1)} s, PSNR {_fmt(r.get('psnr'), 2)} dB"
    else:
      figures = r.get("reason") or (r.get("tail", "").splitlines() or ["-"])[-1][:200]
    lines.append(f"| {name} | {r.get('status')} | {figures} |")
  return "\n".join(lines) + "\n"


MIN_STAGE_S = 30  # a stage with less time than this left is skipped, not started to be stopped


def spent(budget_s: float) -> dict:
  return {"status": "skipped", "seconds": 0,
          "reason": f"the budget (--budget_s={budget_s:g}) was spent by the stages before it"}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--tiny", action="store_true", help="the same stages on the CPU in about a minute")
  parser.add_argument("--out", default=os.environ.get("OUT") or "device_check", help="folder of the report")
  parser.add_argument("--data", default="", help="folder holding lego_400/ (default: .devdata, ../shared/data)")
  parser.add_argument("--budget_s", type=float, default=540.0, help="wall time all stages together may take")
  parser.add_argument("--capture", default="", help="a capture folder for the capture stage (default: "
                      ".devdata/cup, which tools/device_wheels.sh writes)")
  parser.add_argument("--stages", default="env,bench,default,capture,quality,pod", help="which stages, in order")
  args = parser.parse_args(argv)
  started = time.perf_counter()
  out = os.path.abspath(args.out)
  check = Check(out, args.tiny)
  work = os.path.join(out, "..", "device_check_work") if not os.environ.get("OUT") else "/tmp/device_check_work"
  work = os.path.abspath(work)
  os.makedirs(work, exist_ok=True)
  left = lambda: args.budget_s - (time.perf_counter() - started)  # noqa: E731
  stages = args.stages.split(",")

  lego = None
  for candidate in (args.data, os.path.join(REPO, ".devdata"), os.path.join(REPO, "..", "shared", "data")):
    if candidate and os.path.exists(os.path.join(candidate, "lego_400", "transforms_train.json")):
      lego = os.path.abspath(os.path.join(candidate, "lego_400"))
      break
  capture = None
  for candidate in (args.capture, os.path.join(REPO, ".devdata", "cup")):
    if candidate and os.path.isdir(candidate):
      capture = os.path.abspath(candidate)
      break
  if args.tiny:
    bench_config = [f"--config={TINY_CONFIG}"]
    batch_sizes, steps = (64, 128), 3
    quality_config, quality_targets, eval_every = [f"--config={TINY_CONFIG}", "--config.train.num_steps=40"], "8,9", 10
    default_config = TINY_CONFIG
    capture_config, capture_steps, variants, image_every = TINY_CONFIG, 20, TINY_CAPTURE_VARIANTS, 10
    # seconds each stage may take at most, and what later stages keep in reserve
    limits = {"env": 120, "bench": 120, "default": 180, "capture": 120, "quality": 120, "pod": 240}
  else:
    bench_config = ([f"--config={LEGO_CONFIG}", f"--config.data.path={lego}", *LEGO_OVERRIDES] if lego else None)
    batch_sizes, steps = (4096, 16384), 30
    quality_config, quality_targets, eval_every = bench_config, "32,33", 2000
    default_config = "configs/default.py"
    capture_config = f"configs/capture.py:path={capture},big" if capture else None
    capture_steps, variants, image_every = 8000, CAPTURE_VARIANTS, 2000
    limits = {"env": 120, "bench": 120, "default": 200, "capture": 150, "quality": 300, "pod": 60}

  env = {}
  if "env" in stages:
    env = stage_env(check)
    check.record("env", env)
  if "bench" in stages:
    for batch_size in batch_sizes:
      name = f"bench_{batch_size}"
      if bench_config is None:
        check.record(name, {"status": "skipped", "seconds": 0, "reason": "lego_400 not found (--data)"})
        continue
      check.record(name, stage_bench(check, bench_config, batch_size, steps, min(limits["bench"], left()),
                                           256 if args.tiny else 8192, env.get("backend")))
  if "default" in stages:
    check.record("default", stage_default(check, default_config, os.path.join(work, "default"),
                                          min(limits["default"], left()), bool(env.get("lpips_weights")),
                                          env.get("backend")))
  if "capture" in stages:
    for name, overrides, variant_env in variants:
      stage = f"capture_{name}"
      if capture_config is None:
        check.record(stage, {"status": "skipped", "seconds": 0, "reason": "no capture (--capture, .devdata/cup)"})
        continue
      if left() < MIN_STAGE_S:
        check.record(stage, spent(args.budget_s))
        continue
      check.record(stage, stage_capture(check, capture_config, (f"--config.train.num_steps={capture_steps}",
                                                                *overrides), variant_env,
                                        os.path.join(work, stage), min(limits["capture"], left()),
                                        env.get("backend"), os.path.join(out, stage), image_every))
  if "quality" in stages:
    if quality_config is None:
      check.record("quality", {"status": "skipped", "seconds": 0, "reason": "lego_400 not found (--data)"})
    else:
      reserve = limits["pod"] if "pod" in stages else 0
      timeout = min(limits["quality"], left() - reserve)
      # its held-out evaluations, the process's start and the final report come on top of max_seconds
      max_seconds = max(timeout - 15 if args.tiny else 0.65 * timeout, 5)
      check.record("quality", spent(args.budget_s) if timeout < MIN_STAGE_S else
                   stage_quality(check, quality_config, max_seconds, eval_every, quality_targets, timeout))
  if "pod" in stages:
    check.record("pod", spent(args.budget_s) if left() < MIN_STAGE_S else
                 stage_pod(check, int(env.get("gpus", 0) or 0), os.path.join(work, "pod"),
                           min(limits["pod"], left()), args.tiny))
  failed = [name for name, r in check.report["stages"].items() if r["status"] not in ("ok", "skipped")]
  print(markdown(check.report))
  return 1 if failed else 0


if __name__ == "__main__":
  sys.exit(main())
