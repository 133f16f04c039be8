"""What each host holds with data.shards: the shared lego at 400 x 400 with data.shards=4, trained 6 steps by
the smoke job on P processes x D CPU devices (127.0.0.1), each process's peak resident memory (VmHWM, from
/usr/bin/time -v) and its memory just before and after loading the scene.

  python -m tools.shard_memory --processes=1 --devices=4
  python -m tools.shard_memory --processes=4 --devices=1

Prints one line per process: its exit status, its `host P holds K of N training images` line, the load's
RSS before -> after, the whole run's peak RSS and wall time. --data names the lego folder (default
../shared/data/lego_400). Each process is `python -m tools.shard_memory --child ...`: nerfpod.main with
scenes.load wrapped to report its memory.
"""
import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OVERRIDES = {"data.kind": "blender", "data.downscale": 1, "data.shards": 4, "eval.split": "val",
             "train.num_steps": 6, "train.batch_size": 128, "checkpoint.every_steps": 6, "train.log_every": 1,
             "train.image_every": 0, "eval.max_views": 1, "orbit.render_after_training": False}


def _rss_mib() -> float:
  with open("/proc/self/status") as f:
    return int(next(line for line in f if line.startswith("VmRSS")).split()[1]) / 1024


def _child(argv: list[str]) -> None:
  """nerfpod.main with scenes.load reporting the process's memory around it on stderr."""
  from nerfpod import scenes
  original = scenes.load

  def load(*args, **kwargs):
    before = _rss_mib()
    out = original(*args, **kwargs)
    after = _rss_mib()
    print(f"MEM scenes.load: RSS {before:.0f} -> {after:.0f} MiB (+{after - before:.0f}), peak so far "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB", file=sys.stderr, flush=True)
    return out

  scenes.load = load
  from nerfpod import main
  sys.argv = ["nerfpod.main", *argv]
  main.run()


def main() -> None:
  if len(sys.argv) > 1 and sys.argv[1] == "--child":
    _child(sys.argv[2:])
    return
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--processes", type=int, default=1)
  parser.add_argument("--devices", type=int, default=4, help="CPU devices per process")
  parser.add_argument("--data", default=os.path.join(os.path.dirname(REPO), "shared", "data", "lego_400"))
  args = parser.parse_args()
  import portpicker
  workdir = os.path.join(tempfile.mkdtemp(prefix="shard-memory-"), "run")
  flags = ["--config=configs/default.py:smoke", f"--workdir={workdir}", f"--config.data.path={args.data}",
           *[f"--config.{key}={value}" for key, value in OVERRIDES.items()]]
  if args.processes > 1:
    flags += [f"--coordinator_address=127.0.0.1:{portpicker.pick_unused_port()}",
              f"--num_processes={args.processes}"]
  env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES=str(args.devices), PYTHONUNBUFFERED="1")
  env["PYTHONPATH"] = os.pathsep.join(filter(None, [REPO, env.get("PYTHONPATH", "")]))
  procs = []
  for index in range(args.processes):
    argv = ["/usr/bin/time", "-v", sys.executable, "-m", "tools.shard_memory", "--child", *flags]
    argv += [f"--process_id={index}"] if args.processes > 1 else []
    procs.append(subprocess.Popen(argv, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  text=True))
  for index, proc in enumerate(procs):
    out, _ = proc.communicate(timeout=900)
    peak = re.search(r"Maximum resident set size \(kbytes\): (\d+)", out)
    held = re.search(r"host \d+ holds .*", out)
    load = re.search(r"MEM .*", out)
    wall = re.search(r"Elapsed \(wall clock\) time.*: (\S+)", out)
    print(f"{args.processes} x {args.devices}: process {index}: exit {proc.returncode}, "
          f"{held.group(0) if held else 'no holds line'}; {load.group(0) if load else 'no load line'}; "
          f"peak RSS {int(peak.group(1)) / 1024 if peak else float('nan'):.0f} MiB, "
          f"wall {wall.group(1) if wall else '?'}", flush=True)


if __name__ == "__main__":
  main()
