import numpy as np
import pytest

from nerfpod import data
from nerfpod.scenes import procedural


@pytest.fixture(scope="module")
def split():
  return procedural.make(image_size=16).split("train")


def _global_batch(split, step, processes, batch_size=64, seed=3):
  """What `processes` hosts load at `step`, concatenated in process order."""
  per = batch_size // processes
  pieces = [data.LocalRayBatch(split, seed, batch_size, slice(p * per, (p + 1) * per), 0.5).map(step)
            for p in range(processes)]
  return {k: np.concatenate([np.atleast_1d(p[k]) for p in pieces]) for k in ("origins", "directions", "rgb",
                                                                               "ray_ids")}


def test_global_batches_do_not_depend_on_the_number_of_hosts(split):
  for step in (0, 5):
    one = _global_batch(split, step, 1)
    for processes in (2, 4, 8):
      many = _global_batch(split, step, processes)
      for key in one:
        np.testing.assert_array_equal(many[key], one[key])


def test_each_host_loads_only_its_own_disjoint_rows_and_names_them_by_global_row(split):
  whole = data.LocalRayBatch(split, 3, 64, slice(0, 64), 0.5).map(2)
  per_host = [data.LocalRayBatch(split, 3, 64, slice(p * 16, (p + 1) * 16), 0.5).map(2) for p in range(4)]
  assert all(len(b["rgb"]) == 16 for b in per_host)
  ids = np.concatenate([b["ray_ids"] for b in per_host])
  assert sorted(ids.tolist()) == list(range(64))  # disjoint, and together the whole batch
  # A ray's id is its row in the global batch (the step's per-ray randomness is drawn from it): a host's
  # rays are the global batch's rows at its ids, not its first rows.
  for b in per_host:
    for key in ("origins", "directions", "rgb"):
      np.testing.assert_array_equal(b[key], whole[key][b["ray_ids"]])
  assert not np.array_equal(per_host[1]["origins"], whole["origins"][:16])


def test_batches_are_exact_rays_of_random_pixels_from_all_images(split):
  batch = data.LocalRayBatch(split, 0, 4096, slice(0, 4096), 0.5).map(7)
  # The procedural scene is rendered exactly: the batch's colours are its rays' true colours, to the half
  # level of the uint8 images kept in memory.
  np.testing.assert_allclose(procedural.trace(batch["origins"], batch["directions"]), batch["rgb"],
                             atol=0.5 / 255 + 1e-6)
  flat = data.global_pixel_indices(0, 7, 4096, split.num_pixels)
  images = np.unique(flat // (16 * 16))
  assert len(images) > 90  # drawn from (almost) all 100 images, not one image per step


def test_sequence_depends_on_seed_and_step_only_and_resumes_anywhere(split):
  dataset = data.ray_batches(split, 1, 32, slice(0, 32), 0.5, num_steps=10)
  full = [b["rgb"] for b in data.iterator(dataset, 0)]
  resumed = [b["rgb"] for b in data.iterator(data.ray_batches(split, 1, 32, slice(0, 32), 0.5, 10), 6)]
  assert len(full) == 10 and len(resumed) == 4
  for a, b in zip(full[6:], resumed):
    np.testing.assert_array_equal(a, b)
  # Made in the caller's thread (CPUs) or ahead in a background thread (accelerators): the same batches.
  inline = [b["rgb"] for b in data.iterator(dataset, 0, background=False)]
  assert len(inline) == 10
  for a, b in zip(full, inline):
    np.testing.assert_array_equal(a, b)
  other_seed = data.ray_batches(split, 2, 32, slice(0, 32), 0.5, 10)[0]["rgb"]
  assert not np.array_equal(other_seed, full[0])
  assert not np.array_equal(full[1], full[0])


def test_batches_carry_alpha_where_the_data_have_it(split):
  batch = data.LocalRayBatch(split, 0, 512, slice(0, 512), 0.5).map(1)
  _, alpha = procedural.trace(batch["origins"], batch["directions"], return_alpha=True)
  np.testing.assert_array_equal(batch["alpha"], alpha)
  assert 0 < alpha.mean() < 1
  np.testing.assert_array_equal(batch["rgb"][alpha == 0], 1.0)  # background rays are white
