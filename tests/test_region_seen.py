"""A region model whose partition holds a region that no training camera sees is refused before training, in
one sentence naming the region and the fix; regions.unseen on designed rays."""
import types

import jax
import numpy as np
import pytest

from conftest import smoke_config
from nerfpod.errors import UserError
from nerfpod.nerf import cameras, regions
from nerfpod.run import components
from nerfpod.scenes.base import Split


def test_unseen_lists_the_regions_no_ray_crosses():
  cut = regions.grid(4, 1.5)  # a 2 x 2 grid of the ground plane: x < 0 or > 0, y < 0 or > 0
  ids = np.asarray(jax.jit(regions.region_of)(np.float32([[1, 1, 0], [-1, 1, 0], [1, -1, 0], [-1, -1, 0]]), cut))
  # One ray along +x at y = 0.5: it crosses the two cells of y > 0 only.
  along = (np.float32([[-3, 0.5, 0]]), np.float32([[1, 0, 0]]))
  assert regions.unseen(cut, *along, 0.0, 6.0) == sorted(ids[2:].tolist())
  # The same ray over [0, 2.5] ends at x = -0.5: the cell of x > 0, y > 0 is not reached either.
  assert regions.unseen(cut, *along, 0.0, 2.5) == sorted(ids[[0, 2, 3]].tolist())
  # A second ray along +y at x = -0.5 adds the cells of x < 0.
  both = (np.float32([[-3, 0.5, 0], [-0.5, -3, 0]]), np.float32([[1, 0, 0], [0, 1, 0]]))
  assert regions.unseen(cut, *both, 0.0, 6.0) == [int(ids[2])]


def _one_camera_comps(centres=None, cut="cameras", count=3, y=0.0):
  """What check_regions_seen reads of a run's components: one 32 x 32 training camera at (3, y, 0) looking
  down -x with a narrow view (within 0.45 of the line y, z = 0 anywhere in the box [-1.5, 1.5]^3), and `count`
  regions around `centres` (cut 'cameras') or the model's grid (cut 'grid')."""
  config = smoke_config(**{"model.regions": count, "model.region_cut": cut, "model.hashgrid.bound": 1.5})
  pose = cameras.look_at(np.array([3.0, y, 0.0]), (0.0, y, 0.0), (0.0, 0.0, 1.0))
  intr = cameras.Intrinsics(32, 32, 160.0, 160.0, 16.0, 16.0)
  split = Split.from_images(np.zeros((1, 32, 32, 3), np.uint8), pose[None].astype(np.float32), intr, ("a",))
  scene = types.SimpleNamespace(split=lambda name: split)
  partition = regions.voronoi(np.float32(centres)) if cut == "cameras" else components.region_partition(config)
  return types.SimpleNamespace(config=config, scene=scene, model=types.SimpleNamespace(partition=partition),
                               near=0.5, far=6.0)


def test_a_region_no_camera_sees_is_one_sentence_before_training():
  # Cells around (1, 0), (-1, 0) and (0, 2.5): the third holds y > 1.05 at most, where the camera never looks
  # (|y| < 0.45 anywhere in the box).
  comps = _one_camera_comps([[1.0, 0.0], [-1.0, 0.0], [0.0, 2.5]])
  with pytest.raises(UserError) as refused:
    components.check_regions_seen(comps)
  message = str(refused.value)
  assert message.startswith("model.regions=3 (cameras cut) makes 1 region(s) that no training camera sees "
                            "(region 2: x ")
  assert message.endswith("whose fields could learn nothing; use fewer regions (--config.model.regions) or the "
                          "other cut (--config.model.region_cut=grid).")
  assert "\n" not in message
  # Centres along the camera's line of sight: every cell is crossed.
  components.check_regions_seen(_one_camera_comps([[1.0, 0.0], [-1.0, 0.0], [0.0, 0.05]]))
  # A 2 x 2 grid seen from y = 0.8 only: its two cells of y < 0 are refused, each with its bounds.
  with pytest.raises(UserError) as refused:
    components.check_regions_seen(_one_camera_comps(cut="grid", count=4, y=0.8))
  message = str(refused.value)
  assert message.startswith("model.regions=4 (grid cut) makes 2 region(s) that no training camera sees (region ")
  assert message.count("y -1.50..0.00") == 2 and "y 0.00..1.50" not in message
  assert message.endswith("or the other cut (--config.model.region_cut=cameras).")
  # A cell that misses the field's box altogether (centres far out, as around cameras on a ring outside it).
  with pytest.raises(UserError) as refused:
    components.check_regions_seen(_one_camera_comps([[0.5, 0.0], [-0.5, 0.0], [0.0, 9.0]]))
  assert "(region 2: its cell misses the field's box (x and y within +-1.50))" in str(refused.value)


@pytest.mark.slow  # (a process of 16 devices, ~15 s; the quick loop checks the refusal's sentences above,
# test_a_region_no_camera_sees_is_one_sentence_before_training, and the command's refusals path in test_main)
def test_the_command_refuses_it_with_exit_2_and_leaves_no_workdir(tmp_path):
  """The smoke scene's cameras ring the field's box from outside: cut around 16 k-means centres of them, most
  cells miss the box. `nerfpod train` says so in one line, exits 2, and leaves no workdir behind."""
  import procs
  workdir = tmp_path / "run"
  done = procs.run_main("--config=configs/default.py:smoke", f"--workdir={workdir}", "--config.model.regions=16",
                        "--config.model.region_cut=cameras", devices_per_process=16, timeout=300)
  assert done.returncode == 2, done.stderr[-2000:]
  lines = done.stderr.strip().splitlines()
  assert lines[-1].startswith("nerfpod: error: model.regions=16 (cameras cut) makes "), done.stderr[-2000:]
  assert lines[-1].endswith("(--config.model.region_cut=grid).") and not workdir.exists()
