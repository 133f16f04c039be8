#!/usr/bin/env python3
"""Run on each host of a pod before training: exits 0 when JAX sees this host's TPU chips and the pod's,
else 1 with one sentence saying what it sees instead. It starts JAX as a run does (nerfpod.distributed),
so every host of the pod must run it at the same time.

    python launch/check_devices.py --pod=v4-32 --chips=16 --per-host=4
"""
import argparse
import socket
import sys


def main(argv: list[str]) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--pod", required=True, help="the accelerator type, for the message")
  p.add_argument("--chips", type=int, required=True, help="TPU chips in the whole pod")
  p.add_argument("--per-host", type=int, required=True, help="TPU chips each host holds")
  args = p.parse_args(argv)
  import jax
  try:
    from nerfpod import distributed  # the run's own start-up: on a pod, jax.distributed finds the peers
    distributed.initialize(initialization_timeout=120)
    local, total = jax.local_devices(), jax.device_count()
  except Exception as e:  # no backend, or peers that never came
    local, total = [], 0
    print(f"{socket.gethostname()}: JAX could not start ({' '.join(str(e).split())[:200]})", file=sys.stderr)
  ok = bool(local) and all(d.platform == "tpu" for d in local) and len(local) == args.per_host \
      and total == args.chips
  if ok:
    print(f"{socket.gethostname()}: sees its {args.per_host} TPU chips of the pod's {args.chips}", flush=True)
    return 0
  kinds = sorted({f"{d.platform}:{d.device_kind}" for d in local}) or ["nothing"]
  print(f"{socket.gethostname()}: expected {args.per_host} TPU chips here and {args.chips} in all ({args.pod}) "
        f"but JAX sees {len(local)} device(s) here ({', '.join(kinds)}) and {total} in all: check the pod type, "
        f"that no other process holds the chips, and that libtpu matches jax (pip install -c constraints.txt "
        f"-e '.[tpu]').", file=sys.stderr, flush=True)
  return 1


if __name__ == "__main__":
  sys.exit(main(sys.argv[1:]))
