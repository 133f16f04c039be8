"""What is equal across topologies: one job trained on 1 process x 8 CPU devices and on 2 processes x 4
(launch/local.py), from the same seed, compared leaf by leaf.

  python -m tools.topology --config=configs/default.py --steps=40 --out_dir=/tmp/topology

Prints a JSON line: for each parameter leaf, whether the two runs' values are bitwise equal, the norm of the
difference relative to the leaf's norm, and the fraction of entries off by more than 1e-3 of the leaf's
largest magnitude; and both runs' last logged loss and eval/metrics.json means. Other arguments
(`--config.train.batch_size=2048`) go to both runs. Each run is a real `python -m nerfpod.main` on
simulated CPU devices.
"""
import argparse
import json
import os
import re
import shutil
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(argv: list[str], devices: int) -> str:
  env = dict(os.environ, JAX_NUM_CPU_DEVICES=str(devices), JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1")
  env["PYTHONPATH"] = os.pathsep.join(filter(None, [REPO, env.get("PYTHONPATH", "")]))
  done = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True)
  if done.returncode != 0:
    sys.exit(f"tools/topology.py: {' '.join(argv)} failed with status {done.returncode}:\n{done.stderr[-3000:]}")
  return done.stdout + done.stderr


def compare(a: dict, b: dict) -> dict:
  """{leaf path: {"bitwise_equal", "relative_difference", "entries_off"}} of two parameter trees."""
  import jax
  import numpy as np
  out = {}
  for (path, x), (_, y) in zip(jax.tree.leaves_with_path(a), jax.tree.leaves_with_path(b)):
    x, y = np.asarray(x), np.asarray(y)
    out[jax.tree_util.keystr(path)] = {
        "bitwise_equal": bool(np.array_equal(x, y)),
        "relative_difference": float(np.linalg.norm(x - y) / max(np.linalg.norm(y), 1e-30)),
        "entries_off": float(np.mean(np.abs(x - y) > 1e-3 * np.abs(y).max()))}
  return out


def main(argv: list[str]) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="configs/default.py")
  parser.add_argument("--steps", type=int, default=40)
  parser.add_argument("--out_dir", default="/tmp/nerfpod-topology")
  args, overrides = parser.parse_known_args(argv)  # the rest (--config.x=y) goes to both runs
  flags = [f"--config={args.config}", f"--config.train.num_steps={args.steps}", "--config.train.log_every=1",
           "--config.train.image_every=0", "--config.orbit.render_after_training=false",
           f"--config.checkpoint.every_steps={args.steps}", *overrides]
  shutil.rmtree(args.out_dir, ignore_errors=True)
  runs = {"1x8": ([sys.executable, "-m", "nerfpod.main"], 8),
          "2x4": ([sys.executable, os.path.join(REPO, "launch", "local.py"), "--num_processes=2",
                   "--devices_per_process=4", f"--log_dir={os.path.join(args.out_dir, 'logs')}", "--"], 4)}
  result = {"config": args.config, "steps": args.steps, "overrides": overrides}
  for name, (command, devices) in runs.items():
    out = _run([*command, *flags, f"--workdir={os.path.join(args.out_dir, name)}"], devices)
    losses = re.findall(r"step +\d+/\d+ \| loss ([\d.]+)", out)
    metrics = json.load(open(os.path.join(args.out_dir, name, "eval", "metrics.json")))
    result[name] = {"last_loss": losses[-1] if losses else None, "eval_mean": metrics["mean"]}
  from nerfpod.workdir import checkpoints
  params = {name: checkpoints.read_numpy(os.path.join(args.out_dir, name))[0]["params"] for name in runs}
  result["leaves"] = compare(params["1x8"], params["2x4"])
  leaves = result["leaves"].values()
  result["summary"] = {"bitwise_equal_leaves": sum(v["bitwise_equal"] for v in leaves),
                       "leaves": len(result["leaves"]),
                       "max_relative_difference": max(v["relative_difference"] for v in leaves),
                       "max_entries_off": max(v["entries_off"] for v in leaves)}
  print(json.dumps(result))


if __name__ == "__main__":
  main(sys.argv[1:])
