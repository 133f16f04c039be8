"""Every program of a run spans every device of every process: the train step, evaluation, the previews,
the orbit, checkpoints. A TPU pod refuses a program on some of a slice's chips (v5e pods of 32 chips and
more), so no per-host program may hide in a run. The hook (tests/compiles.py) records the devices of each
program a process compiles; one device alone (eager operations: keys, scalars) is allowed, as the TPU
compiler allows it (tests/test_pod_sweep.py compiles both kinds for a v5e-32)."""
import jax
import numpy as np
import pytest
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

import compiles
import procs


def test_the_hook_records_each_programs_devices_and_flags_a_subset(tmp_path):
  path = tmp_path / "compiles.jsonl"
  devices = jax.devices()
  with compiles.recording(path):
    for mesh_devices in (devices[:4], devices, devices[:1]):
      mesh = Mesh(np.array(mesh_devices), ("data",))
      x = jax.device_put(np.arange(8 * 3, dtype=np.float32).reshape(8, 3), NamedSharding(mesh, P("data")))
      jax.jit(lambda x: x * 3.0 + 1.0)(x).block_until_ready()
  records = compiles.read(path)
  assert [r["devices"] for r in records] == [[d.id for d in devices[:4]], [d.id for d in devices], [devices[0].id]]
  assert compiles.subset_programs(records, [d.id for d in devices]) == records[:1]


@pytest.mark.slow
def test_a_two_host_run_compiles_no_program_for_one_hosts_devices(tmp_path):
  """Train (with previews and checkpoints), evaluate and render the orbit on 2 processes x 2 devices."""
  overrides = {"train.num_steps": 4, "train.image_every": 2, "checkpoint.every_steps": 2, "eval.max_views": 1,
               "orbit.num_frames": 3, "orbit.width": 12, "orbit.height": 8}
  with procs.Run(tmp_path / "pod", overrides, num_processes=2, devices_per_process=2,
                 compiles_dir=tmp_path) as run:
    run.wait_ok(150)
  assert "orbit: wrote" in run.output(0)
  records = compiles.read(*sorted(tmp_path.glob("compiles_process_*.jsonl")))
  every = sorted({i for r in records for i in r["devices"]})
  assert len(every) == 4, every
  subsets = compiles.subset_programs(records, every)
  assert subsets == [], f"programs on some of the devices only: {subsets}"
  on_all = {r["name"] for r in records if r["devices"] == every}
  assert len(on_all) >= 3, on_all  # at least the step, the renderer and a barrier, each on every device
