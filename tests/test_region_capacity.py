"""model.region_capacity: each chip renders, per region, only the rays whose segment meets it, up to C rows
(nerf/regions.py's dispatch, NeRF.render_partials' capacity, run/step.py's _region_loss_fn): the same step as the
dense one where nothing is dropped, whole rays dropped where a region overflows, counted, and the training loop's
refusal; the step's regions/* scalars (per-frame tables and stratified samples at a capacity:
tests/test_region_step.py); and model.region_capacity=auto, measured on the training rays before the
first step, recorded in config.json and kept by a resume."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import Mesh

import procs
from conftest import shared_model
from test_region_step import SGD, _batches, _region_mesh
from test_region_step import _config as _region_step_config
from nerfpod import distributed
from nerfpod.errors import UserError
from nerfpod.nerf import regions, sampling
from nerfpod.run import components, step, train, train_state

BATCH = 128
# Of the first two batches' rays, at most 73 of 128 meet the fullest region (fill 0.57): 0.75 (C = 96) holds them
# all, and of 64 and 32 rays a device (2 x 4, 4 x 2) at most 42 and 22 do (C = 48, 24).
ROOMY = 0.75
TINY = 0.125  # C = 16 of 128: most rays overflow


def _config(**overrides):
  """tests/test_region_step.py's tiny 4-region config with BATCH rays a step."""
  return _region_step_config(**({"train.batch_size": BATCH} | overrides))


def _one():
  return Mesh(np.array(jax.devices()[:1]), (distributed.DATA_AXIS,))


def _run(mesh, capacity, steps=2, batches=None, optimizer=None, microbatches=1, compiler_options=None, **overrides):
  """(state, metrics of each step) of `steps` steps (plain SGD: the parameters move exactly as the gradients)."""
  config = _config(**overrides)
  per_frame = bool(config.model.appearance_dim or config.train.pose_refine)
  model = shared_model(config, num_frames=100 if per_frame else 0)
  scene, own = _batches(config, steps, per_frame)
  optimizer = optimizer or SGD
  state = train_state.initial_state(model, optimizer, config.train.seed, mesh)
  step_fn = step.make_train_step(model, optimizer, mesh, 2.0, 6.0, scene.background,
                                 step.Options(random_background=True, distortion_weight=0.01,
                                              region_capacity=capacity, microbatches=microbatches,
                                              compiler_options=compiler_options))
  metrics = []
  for batch in batches or own:
    state, m = step_fn(state, jax.device_put(batch, distributed.batch_sharding(mesh)), jax.random.key(7))
    metrics.append(jax.device_get(m))
  return jax.device_get(state), metrics


@pytest.fixture(scope="module")
def dense():
  """The dense step (capacity 0) on one device, two steps: the reference. Compiled with procs.OPTIMIZED_KERNELS,
  whatever the test session's flags: its values are pinned below, recorded at that level (XLA's default level 2
  computes the same bits; at level 0 a program's bits depend on its structure, not only its arithmetic)."""
  return _run(_one(), 0.0, compiler_options=procs.OPTIMIZED_KERNELS)


@pytest.fixture(scope="module")
def segments():
  """Each region's segment (K, R) of the first two batches' rays, as the model cuts them (box, then planes)."""
  config = _config()
  model = components.make_model(config)
  _, batches = _batches(config, 2)

  @jax.jit  # one program rather than one per operation
  def segments_of(o, d):
    near, far = sampling.clip_to_box(o, d, 2.0, 6.0, config.model.hashgrid.bound)
    return regions.segments(o, d, near, far, model.partition)
  return [segments_of(batch["origins"], batch["directions"]) for batch in batches]


def _present(t_in, t_out):
  return np.asarray(t_out) > np.asarray(t_in)  # (on the host: no program)


def _dropped(present_KxR, capacity):
  """Rays with a segment beyond the first `capacity` of its region's, in ray order (a brute-force count)."""
  rank = np.cumsum(present_KxR, axis=1) - 1
  return np.any(present_KxR & (rank >= capacity), axis=0)


def _same_step(got, want, rtol_params=1e-4):
  (state_got, metrics_got), (state_want, metrics_want) = got, want
  for m_got, m_want in zip(metrics_got, metrics_want):
    for key in ("loss", "mse", "interlevel", "distortion", "grad_norm", "regions/segments_per_ray"):
      np.testing.assert_allclose(m_got[key], m_want[key], rtol=2e-5, err_msg=key)
    assert m_got["regions/dropped"] == 0
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=rtol_params, atol=1e-6),
               state_got.params, state_want.params)


# Capacity 0 is the region step of commit 4d8cad3 (before model.region_capacity), which gave these values on
# this one-device configuration: the loss of steps 1 and 2 and the sum of the parameters after them (every
# parameter was checked bit for bit against that commit's code, on 2 x 4 devices with Adam too and on the smoke
# config's fields, at LLVM levels 1 and 2, on the 2-core machine of 2026-12-06; another CPU may round otherwise,
# hence rtol 1e-6, as tests/test_golden.py's 1e-5).
BEFORE_CAPACITY = {"losses": (0.07140574604272842, 0.068402960896492), "param_sum": -15.518214437191176}


def test_capacity_zero_is_the_dense_region_step_of_before(dense):
  state, metrics = dense
  losses = tuple(float(m["loss"]) for m in metrics)
  param_sum = float(sum(np.sum(np.asarray(p, np.float64)) for p in jax.tree.leaves(state.params)))
  got = {"losses": losses, "param_sum": param_sum}
  assert got["losses"] == pytest.approx(BEFORE_CAPACITY["losses"], rel=1e-6), got
  assert got["param_sum"] == pytest.approx(BEFORE_CAPACITY["param_sum"], rel=1e-6), got
  assert "regions/capacity" not in metrics[0]  # dense: no C


@pytest.mark.slow  # (another compile of the one-device step; the quick loop checks the one-device compaction in
# test_an_overflow_drops_whole_rays_counts_them_and_trains_on_the_rest[None-1], against the dense step on the rays
# kept, and a roomy capacity on 2 x 4 against the dense one-device step in the next test)
def test_roomy_capacity_steps_as_the_dense_one_on_one_device(dense, segments):
  """C = 96 of 128 rays (fewer rows than rays: a real compaction), nothing dropped: the loss, metrics and the
  parameters after two SGD steps are the dense step's, to float tolerance (not bit for bit: XLA rounds the
  same per-ray arithmetic differently on gathered rows, ~1e-7 relative in a segment's sums)."""
  compact = _run(_one(), ROOMY)
  assert regions.capacity_rows(ROOMY, BATCH) == 96
  assert max(int(_present(*s).sum(axis=1).max()) for s in segments) <= 96
  _same_step(compact, dense)
  assert compact[1][0]["regions/field_evals_per_chip"] == 4 * 96 * (8 + 6)
  assert dense[1][0]["regions/field_evals_per_chip"] == 4 * BATCH * (8 + 6)


@pytest.mark.parametrize("shape", [(2, 4), pytest.param((4, 2), marks=pytest.mark.slow)])
def test_roomy_capacity_steps_as_the_dense_one_on_a_region_mesh(dense, segments, shape):
  """(data, region) = `shape` on 8 devices, each with its L = 4 / regions share: the same against the dense
  step on one device (which tests/test_region_step.py holds equal to the dense step on these meshes). (4, 2):
  another compile of the 8-device step, the slow set; (2, 4) covers the same claim."""
  compact = _run(_region_mesh(shape), ROOMY)
  rays = BATCH // shape[0]
  capacity = regions.capacity_rows(ROOMY, rays)
  _same_step(compact, dense)
  for (t_in, t_out), metrics in zip(segments, compact[1]):
    assert metrics["regions/capacity"] == capacity
    present = _present(t_in, t_out)  # the fill: the mean over the data axis of each device's fullest region
    fills = [present[:, i:i + rays].sum(axis=1).max() / capacity for i in range(0, BATCH, rays)]
    assert metrics["regions/fill"] == pytest.approx(np.mean(fills), rel=1e-6)


def test_dispatch_compacts_the_present_segments_in_ray_order():
  # (L 2, R 5); 5.0: empty [far, far]
  t_in = np.array([[0.0, 5.0, 1.0, 0.5, 2.0], [5.0, 5.0, 5.0, 1.0, 5.0]], np.float32)
  t_out = np.array([[1.0, 5.0, 2.0, 0.7, 3.0], [5.0, 5.0, 5.0, 2.0, 5.0]], np.float32)

  @jax.jit  # one program rather than one per operation
  def run(t_in, t_out, x):
    d = regions.dispatch(t_in, t_out, 3)
    rows = regions.gather_rows(x, d)
    return d, rows, regions.scatter_rows(rows + 1, d, -1.0)

  d, rows, back = run(t_in, t_out, np.arange(5.0, dtype=np.float32) * 10)
  np.testing.assert_array_equal(d.present_LxR, [[1, 0, 1, 1, 1], [0, 0, 0, 1, 0]])
  np.testing.assert_array_equal(d.rows_LxC, [[0, 2, 3], [3, 5, 5]])  # 5 = R: a row left over
  np.testing.assert_array_equal(d.slots_LxR, [[0, 3, 1, 2, 3], [3, 3, 3, 0, 3]])  # 3 = C: no row
  np.testing.assert_array_equal(d.dropped_LxR, [[0, 0, 0, 0, 1], [0, 0, 0, 0, 0]])  # ray 4 over capacity
  np.testing.assert_array_equal(rows, [[0, 20, 30], [30, 40, 40]])
  np.testing.assert_array_equal(back, [[1, -1, 21, 31, -1], [-1, -1, -1, 31, -1]])
  assert [regions.capacity_rows(f, 128) for f in (0.01, 0.5, 0.51, 1.0)] == [8, 64, 72, 128]
  assert regions.capacity_rows(1.0, 20) == 20  # never more rows than rays


def test_an_absent_segment_takes_what_the_dense_path_gives_an_empty_one():
  """Rays that miss a region: the dense renderer's sums there are nerf_regions.empty_sums' (t_in the ray's far
  bound exactly, every sum 0), which the compacted path puts in the rays it does not render. The dense sums are
  0 up to round-off only: the empty segment's sample edges, all at `far`, may land an ulp apart after the map
  from s to t, and a tiny (even negative) interval length gives a weight of about 5e-7."""
  config = _config()
  model = components.make_model(config)
  _, (batch,) = _batches(config, 1)
  o, d = batch["origins"], batch["directions"]  # (NumPy: sliced without a program)
  params = jax.jit(model.init)(jax.random.key(0), o[:2], d[:2], 2.0, 6.0, np.zeros(3, np.float32))

  # One program rather than one per operation, its bits from optimised kernels (procs.OPTIMIZED_KERNELS), as in
  # every claim that two computations give the same bits (the segments' start and the ray's far bound).
  @functools.partial(jax.jit, compiler_options=procs.OPTIMIZED_KERNELS)
  def run(params, o, d):
    uniforms = tuple(jax.random.uniform(jax.random.key(i), (4, BATCH, n))
                     for i, n in enumerate(model.sample_counts()))
    partials, own = model.apply(params, o, d, 2.0, 6.0, jnp.arange(4), uniforms, method="render_partials")
    far = sampling.clip_to_box(o, d, 2.0, 6.0, config.model.hashgrid.bound)[1][:, 0]
    interlevel = jax.vmap(regions.interlevel_loss)(own["s_edges"], own["weights"], own["proposals"][0]["s_edges"],
                                                   own["proposals"][0]["weights"], jnp.ones(own["present"].shape))
    return partials, own["present"], far, interlevel

  partials, present, far, interlevel = run(params, o, d)
  absent = ~np.asarray(present)
  assert absent.sum() > 50 and (~absent).sum() > 50
  far = np.asarray(far)
  for key, value in partials.items():
    want = np.broadcast_to(np.asarray(regions.empty_sums(far, key), np.float32), absent.shape)
    got = np.asarray(value)[absent]
    if key == "t_in":
      np.testing.assert_array_equal(got, want[absent], err_msg=key)
    else:
      np.testing.assert_allclose(got, 0.0, atol=2e-5, err_msg=key)
  np.testing.assert_allclose(np.asarray(interlevel)[absent], 0.0, atol=1e-6)


@pytest.mark.parametrize("shape,microbatches", [(None, 1), ((2, 4), 2)])
def test_an_overflow_drops_whole_rays_counts_them_and_trains_on_the_rest(segments, shape, microbatches):
  """At capacity TINY (C = 16 of 128 rays on one device; on 2 x 4 in 2 micro-batches, 8 of each 32) the rays
  with a segment over capacity in any region (counted by brute force, per device's and micro-batch's share of
  the batch) are dropped whole, on every device of the region axis: regions/dropped counts them, and the step is
  the dense step on the batch of the rays kept (each ray's random numbers are its own, whatever batch holds
  it), its loss and gradients scaled by the share kept (a dropped ray adds 0 to the batch's means)."""
  mesh = _one() if shape is None else _region_mesh(shape)
  rays = BATCH // (shape or (1,))[0] // microbatches
  capacity = regions.capacity_rows(TINY, rays)
  state, (metrics,) = _run(mesh, TINY, steps=1, microbatches=microbatches)
  local = 4 // (shape or (1, 1))[1]
  assert metrics["regions/field_evals_per_chip"] == local * capacity * (8 + 6) * microbatches
  present = _present(*segments[0])
  dropped = np.concatenate([_dropped(present[:, i:i + rays], capacity) for i in range(0, BATCH, rays)])
  assert 0 < dropped.sum() < BATCH - 8
  assert metrics["regions/dropped"] == dropped.sum()
  assert metrics["regions/capacity"] == capacity
  if shape is None:  # (on a mesh, the mean of each device's fullest)
    np.testing.assert_allclose(metrics["regions/fill"], present.sum(axis=1).max() / capacity)
  _, (batch,) = _batches(_config(), 1)
  kept_state, (kept_metrics,) = _run(_one(), 0.0, steps=1, batches=[{k: v[~dropped] for k, v in batch.items()}])
  share = (~dropped).sum() / BATCH
  for key in ("loss", "mse", "interlevel", "distortion", "grad_norm"):
    np.testing.assert_allclose(metrics[key], share * kept_metrics[key], rtol=2e-5, err_msg=key)
  initial = jax.device_get(train_state.initial_state(shared_model(_config()), SGD, 0, _one()).params)
  jax.tree.map(lambda got, kept, start: np.testing.assert_allclose(got - start, share * (kept - start), rtol=1e-4,
                                                                   atol=1e-6),
               state.params, kept_state.params, initial)


def test_the_scalars_on_a_hand_checked_case():
  # 3 regions x 4 rays: ray 0 crosses regions 0 and 1, ray 1 region 1, ray 2 all three, ray 3 region 1.
  counts = np.array([2, 4, 1], np.float32)  # rays with a segment in each region
  # (Jitted, here and below: one program rather than one per operation.)
  dense = jax.jit(lambda c: step.region_metrics(c, 4, None, 0, local=3, field_samples=14, microbatches=1,
                                                shares=1))(counts)
  assert {k: float(v) for k, v in dense.items()} == {
      "regions/segments_per_ray": 7 / 4, "regions/fill": 4 / 4, "regions/dropped": 0.0,
      "regions/field_evals_per_chip": 3 * 4 * 14}
  dropped = np.array([[0, 0, 0, 0], [0, 0, 1, 1], [0, 0, 0, 0]], np.float32)  # C = 2: region 1's rays 2, 3
  compact = jax.jit(lambda c, d: step.region_metrics(c, 4, d, 2, local=1, field_samples=14, microbatches=2,
                                                     shares=4))(counts, dropped)
  assert {k: float(v) for k, v in compact.items()} == {
      "regions/segments_per_ray": 7 / 4, "regions/fill": 4 / 2, "regions/dropped": 2 * 4,
      "regions/field_evals_per_chip": 1 * 2 * 14 * 2, "regions/capacity": 2}


def test_the_step_scalars_are_the_rays_segments(dense, segments):
  """One device holding the 4 regions: the dense step's scalars against a count of the segments."""
  for (t_in, t_out), metrics in zip(segments, dense[1]):
    present = _present(t_in, t_out)
    assert metrics["regions/segments_per_ray"] == pytest.approx(present.sum(axis=0).mean(), rel=1e-7)
    assert metrics["regions/fill"] == pytest.approx(present.sum(axis=1).max() / BATCH, rel=1e-7)
    assert metrics["regions/dropped"] == 0


def _step_scalars(dropped: float, fill: float, capacity: int) -> dict:
  """The step's scalars that train.DropWatch reads, as a step's metrics come back from the device."""
  return {"regions/dropped": np.float32(dropped), "regions/fill": np.float32(fill),
          "regions/capacity": np.float32(capacity)}


def test_the_loop_refuses_a_window_that_drops_over_a_thousandth_of_its_rays():
  watch = train.DropWatch(0.25, 1024)
  for s, dropped in ((1, 1.0), (2, 0.0)):  # 1 of 2,048: under 0.1%
    watch.dispatched(s, _step_scalars(dropped, 0.9, 64))
  watch.check()
  for s in (3, 4):
    watch.dispatched(s, _step_scalars(2.0, 1.31 if s == 3 else 1.2, 64))
  with pytest.raises(UserError) as refused:
    watch.check()
  assert str(refused.value) == (
      "training dropped 4 of the 2,048 rays of steps 3 to 4 (0.20%, over the 0.1% a run may drop): "
      "model.region_capacity=0.25 gives each region C = 64 rows of each device's rays and the fullest region's "
      "rays with a segment in it filled 1.31 x C, so rays over capacity were dropped whole; resume with "
      "--config.model.region_capacity=0.4 (or 0: every ray through every region).")


def test_the_refusal_of_a_measured_capacity_says_it_was_auto():
  watch = train.DropWatch(0.713, 128, auto=True)
  watch.dispatched(5, _step_scalars(3.0, 1.05, 96))
  with pytest.raises(UserError, match=r"model.region_capacity=auto \(F = 0.713\) gives each region C = 96 rows .*"
                                      r"resume with --config.model.region_capacity=0.85 "):
    watch.check()


@pytest.mark.slow  # (a region run through the loop, ~14 s; the quick loop checks the refusal on the watch's
# counts, test_the_loop_refuses_a_window_that_drops_over_a_thousandth_of_its_rays, and the step's drops above)
def test_a_run_that_overflows_stops_with_the_sentence(tmp_path):
  from nerfpod.run import modes
  config = _config(**{"model.region_capacity": TINY, "train.num_steps": 3, "train.log_every": 1,
                      "train.image_every": 0, "orbit.render_after_training": False})
  with pytest.raises(UserError, match=r"^training dropped (\d+) of the 128 rays of steps 1 to 1 .*"
                                      r"model.region_capacity=0.125 gives each region C = 8 rows") as refused:
    modes.train_and_evaluate(config, str(tmp_path))
  # Step 1's scalars reached TensorBoard before the refusal, the regions' with the others.
  from tensorboard.backend.event_processing import event_accumulator
  events = event_accumulator.EventAccumulator(str(tmp_path), size_guidance={"scalars": 0})
  events.Reload()
  scalars = {tag: events.Scalars(tag)[-1] for tag in events.Tags()["scalars"] if tag.startswith("train/regions/")}
  assert sorted(scalars) == ["train/regions/capacity", "train/regions/dropped", "train/regions/field_evals_per_chip",
                             "train/regions/fill", "train/regions/segments_per_ray"]
  assert scalars["train/regions/dropped"].step == 1
  assert scalars["train/regions/dropped"].value == int(str(refused.value).split()[2])
  assert scalars["train/regions/capacity"].value == 8 and scalars["train/regions/fill"].value > 1


# model.region_capacity=auto: the fraction measured on the training rays before the first step, recorded in the
# workdir's config.json, kept by a resume.

def _brute_force_counts(origins, directions, near, far, partition):
  """(K,) how many rays have a piece of positive length in each region: each ray's [near, far] cut at every
  plane of every region (float64), each piece between two cuts lying in one region, found by its midpoint
  (the half-spaces tested directly: no slab method)."""
  o, d = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
  near, far = np.asarray(near, np.float64)[:, 0], np.asarray(far, np.float64)[:, 0]
  normals = np.asarray(partition.normals_KxPx3, np.float64).reshape(-1, 3)
  offsets = np.asarray(partition.offsets_KxP, np.float64).reshape(-1)
  counts = np.zeros(partition.size, np.int64)
  for i in range(len(o)):
    nd = normals @ d[i]
    crossings = (offsets - normals @ o[i])[nd != 0] / nd[nd != 0]
    cuts = np.unique(np.concatenate([[near[i], far[i]], np.clip(crossings, near[i], far[i])]))
    met = set()
    for a, b in zip(cuts[:-1], cuts[1:]):
      point = o[i] + 0.5 * (a + b) * d[i]
      values = np.einsum("kpc,c->kp", np.asarray(partition.normals_KxPx3, np.float64), point)
      inside = np.all((values < partition.offsets_KxP) | (partition.closed_KxP & (values == partition.offsets_KxP)),
                      axis=1)
      met.add(int(np.argmax(inside)))
    counts[sorted(met)] += 1
  return counts


@pytest.mark.parametrize("cut", ["grid", "cameras"])
def test_auto_counts_the_rays_that_meet_each_region_as_a_brute_force_count(cut):
  """regions.segment_counts (in chunks, the last one padded) of 3,000 rays of the procedural scene's training
  pixels, clipped to the hash grid's box: the rays that cross each region, counted piece by piece."""
  config = _config(**{"model.region_cut": cut})
  scene, _ = _batches(config, 0)
  split = scene.split("train")
  model = components.make_model(config, camera_positions=np.asarray(split.poses)[:, :3, 3])
  origins, directions = regions.pixel_rays(np.asarray(split.poses), split.cameras, 3000, seed=1)
  counts = regions.segment_counts(origins, directions, 2.0, 6.0, model.partition, bound=1.5, chunk=1024)
  near, far = jax.jit(sampling.clip_to_box, static_argnums=(2, 3, 4))(origins, directions, 2.0, 6.0, 1.5)  # one program
  want = _brute_force_counts(origins, directions, near, far, model.partition)
  np.testing.assert_array_equal(counts, want)
  assert 0 < want.min() and want.max() < 3000 and want.sum() > 3000  # rays that miss some regions, cross several


def test_auto_draws_its_rays_as_the_training_batches_are_drawn():
  """regions.pixel_rays with the pipeline's seed of a step is that step's batch: uniform over every pixel."""
  config = _config()
  scene, (batch,) = _batches(config, 1)
  split = scene.split("train")
  origins, directions = regions.pixel_rays(np.asarray(split.poses), split.cameras, BATCH, seed=[0, 0])
  np.testing.assert_array_equal(origins, batch["origins"])
  np.testing.assert_array_equal(directions, batch["directions"])


def test_the_auto_fraction_is_the_fullest_share_and_its_margin():
  # 0.5 + 4 sqrt(0.25 / 128) + 0.01 = 0.68678: rounded up to a thousandth
  assert regions.auto_fraction(0.5, 128) == 0.687
  assert regions.auto_fraction(0.0, 128) == 0.01 and regions.auto_fraction(1.0, 128) == 1.0
  assert regions.auto_fraction(0.9, 16) == 1.0  # capped
  assert regions.auto_fraction(0.25, 1024) == pytest.approx(0.25 + 4 * np.sqrt(0.25 * 0.75 / 1024) + 0.01, abs=1e-3)


def test_auto_measures_the_fullest_share_of_the_scenes_training_rays():
  """step.measure_capacity: step.AUTO_RAYS training rays, their counts per region, F for a chip's rows."""
  config = _config()
  scene, _ = _batches(config, 0)
  model = components.make_model(config)
  measured = step.measure_capacity(config, scene, _one(), model.partition, 2.0, 6.0)
  split = scene.split("train")
  origins, directions = regions.pixel_rays(np.asarray(split.poses), split.cameras, step.AUTO_RAYS, step.AUTO_SEED)
  want = regions.segment_counts(origins, directions, 2.0, 6.0, model.partition, bound=1.5)
  assert measured.counts == tuple(want) and measured.rays == step.AUTO_RAYS and measured.rows == BATCH
  assert measured.fraction == regions.auto_fraction(max(want) / step.AUTO_RAYS, BATCH)
  # About half the rays meet each quarter of the 2 x 2 grid; the batches above fill 0.57 at most: F holds them.
  assert 0.45 < max(want) / step.AUTO_RAYS < 0.6 and 0.66 < measured.fraction < 0.8
  assert measured.capacity == regions.capacity_rows(measured.fraction, BATCH) == 96
  assert measured.line().startswith(f"model.region_capacity=auto: of 65,536 training rays, the shares that meet "
                                    f"regions 0 to 3 are {', '.join(f'{c / 65536:.3f}' for c in want)}; ")
  assert measured.line().endswith(f"gives F = {measured.fraction:g}: C = 96 of 128 rows per region")


def test_resolve_keeps_a_number_and_a_resumed_workdirs_record(tmp_path, monkeypatch):
  """train.resolve_capacity: a number (and model.regions=1) as it is; auto measured on a fresh run, and on a
  resume the fraction the workdir's config.json records (not measured again); a record of 0 (a dense run) or
  none: measured."""
  import dataclasses
  import json
  config = _config(**{"model.region_capacity": "auto"})
  scene, _ = _batches(config, 0)
  comps = components.build_program(config, _one(), scene=scene)
  for number in (0.0, 0.5):
    same = dataclasses.replace(comps, config=_config(**{"model.region_capacity": number}))
    assert train.resolve_capacity(same, str(tmp_path), resuming=True) is same
  measured = step.measure_capacity(config, scene, _one(), comps.model.partition, 2.0, 6.0).fraction
  fresh = train.resolve_capacity(comps, str(tmp_path), resuming=False)
  assert fresh.config.model.region_capacity == measured and config.model.region_capacity == "auto"
  # The step's options of a config still at auto (nerfpod bench's): measured alike; without a scene, refused.
  assert step.Options.of(comps, 1).region_capacity == measured
  with pytest.raises(UserError, match="^model.region_capacity=auto is measured on the scene's training rays"):
    step.Options.of(dataclasses.replace(comps, scene=None), 1)
  (tmp_path / "config.json").write_text(json.dumps({"model": {"region_capacity": 0.3}}))
  monkeypatch.setattr(step, "measure_capacity", lambda *args: pytest.fail("measured again on a resume"))
  assert train.resolve_capacity(comps, str(tmp_path), resuming=True).config.model.region_capacity == 0.3
  monkeypatch.undo()
  (tmp_path / "config.json").write_text(json.dumps({"model": {"region_capacity": 0.0}}))
  assert train.resolve_capacity(comps, str(tmp_path), resuming=True).config.model.region_capacity == measured


@pytest.mark.slow  # (two region runs through the loop, ~15 s; the quick loop checks the resume's rule,
# test_resolve_keeps_a_number_and_a_resumed_workdirs_record, and the measurement, on the same config)
def test_a_run_with_auto_records_its_fraction_and_its_resume_compiles_the_same_capacity(tmp_path, monkeypatch,
                                                                                        capsys):
  """A fresh run with model.region_capacity=auto measures F before its first step, says so in one line, trains
  with C = capacity_rows(F, R) and records F in config.json; the same command resumed (two more steps) reads F
  back from config.json, measures nothing, and compiles the same C."""
  import json
  from nerfpod import monitor
  from tensorboard.backend.event_processing import event_accumulator

  def run(steps):
    config = _config(**{"model.region_capacity": "auto", "train.num_steps": steps, "train.log_every": 1,
                        "train.image_every": 0, "orbit.render_after_training": False,
                        "checkpoint.every_steps": 2})
    comps = components.build(config, _one())
    watch = monitor.Monitor(str(tmp_path), steps, BATCH, config)
    try:
      train.train(comps, str(tmp_path), watch)
    finally:
      watch.close(0)
    return comps

  comps = run(2)
  measured = step.measure_capacity(comps.config, comps.scene, _one(), comps.model.partition, 2.0, 6.0)
  printed = [l for l in capsys.readouterr().out.splitlines() if "model.region_capacity=auto" in l]
  assert printed == [f"nerfpod: {measured.line()}"]
  recorded = json.loads((tmp_path / "config.json").read_text())["model"]["region_capacity"]
  assert recorded == measured.fraction
  monkeypatch.setattr(step, "measure_capacity", lambda *args: pytest.fail("measured again on a resume"))
  run(4)
  printed = [l for l in capsys.readouterr().out.splitlines() if "model.region_capacity=auto" in l]
  assert printed == [f"nerfpod: model.region_capacity=auto: F = {recorded:g}, as the workdir's config.json records "
                     f"(the fraction its run trained with): C = {measured.capacity} of {BATCH} rows per region"]
  assert json.loads((tmp_path / "config.json").read_text())["model"]["region_capacity"] == recorded
  events = event_accumulator.EventAccumulator(str(tmp_path), size_guidance={"scalars": 0})
  events.Reload()
  capacity = {e.step: e.value for e in events.Scalars("train/regions/capacity")}
  assert capacity == {1: measured.capacity, 2: measured.capacity, 3: measured.capacity, 4: measured.capacity}


@pytest.mark.slow  # (a region run through the loop, ~8 s; the quick loop checks the fit's counts and fractions,
# test_a_fitted_micro_batch_gets_the_margin_of_its_own_rays, with the compiler standing in)
def test_a_run_fitted_to_two_micro_batches_trains_with_and_records_their_margin(tmp_path, monkeypatch, capsys):
  """train.microbatches=0 with auto, a budget only two micro-batches fit (XLA's analysis of each compiled step
  stands in: the one-micro-batch step over it): the run says and records F for 64 rays a micro-batch, and its
  step renders C = capacity_rows(F, 64) rows (the step's own regions/capacity scalar)."""
  import json
  from nerfpod import monitor
  from nerfpod.run import compilation
  from tensorboard.backend.event_processing import event_accumulator
  monkeypatch.setattr(compilation, "memory_budget_bytes", lambda config: 150)
  monkeypatch.setattr(compilation, "step_memory_bytes", lambda compiled: 200 if "1 micro" in seen[-1] else 100)
  seen = []
  fitted = step.fitted_capacity
  monkeypatch.setattr(step, "fitted_capacity", lambda comps, count: seen.append(f"{count} micro") or fitted(comps, count))
  config = _config(**{"model.region_capacity": "auto", "train.microbatches": 0, "train.num_steps": 2,
                      "train.log_every": 1, "train.image_every": 0, "orbit.render_after_training": False})
  comps = components.build(config, _one())
  watch = monitor.Monitor(str(tmp_path), 2, BATCH, config)
  try:
    train.train(comps, str(tmp_path), watch)
  finally:
    watch.close(0)
  measured = step.measure_capacity(comps.config, comps.scene, _one(), comps.model.partition, 2.0, 6.0)
  wide = measured.at_rows(BATCH // 2)
  assert wide.fraction > measured.fraction
  lines = [l for l in capsys.readouterr().out.splitlines() if "model.region_capacity=auto" in l]
  assert lines == [f"nerfpod: {measured.line()}",
                   f"nerfpod: {wide.line()} (its margin for one of the 2 micro-batches)"]
  assert json.loads((tmp_path / "config.json").read_text())["model"]["region_capacity"] == wide.fraction
  events = event_accumulator.EventAccumulator(str(tmp_path), size_guidance={"scalars": 0})
  events.Reload()
  assert {e.value for e in events.Scalars("train/regions/capacity")} == {regions.capacity_rows(wide.fraction, 64)}


@pytest.mark.parametrize("cut", ["grid", "cameras", "balanced"])
def test_the_tools_region_cut_is_the_run_models(cut):
  """components.region_cut (what nerfpod aot's auto measures on) is the partition of the model that
  build_program makes for a run of the same scene: the training cameras' k-means cells, the balanced cut of the
  training rays' samples, or the grid."""
  config = _config(**{"model.region_cut": cut})
  scene, _ = _batches(config, 0)
  want = components.build_program(config, _one(), scene=scene).model.partition
  got = components.region_cut(config, scene)
  jax.tree.map(np.testing.assert_array_equal, tuple(got), tuple(want))
  if cut != "grid":  # (cut from the scene: not the placeholders' cut without one)
    assert not np.array_equal(got.offsets_KxP, components.region_partition(config).offsets_KxP)


def test_a_tool_without_a_run_measures_auto_on_a_built_in_scene_and_asks_for_a_number_otherwise(capsys):
  """step.measure_for_tool (nerfpod aot's): the built-in scene made and measured, its line on stderr; a scene
  it would have to read (data.kind=blender) refused in one sentence asking for a fraction; a number kept (none
  measured)."""
  config = _config(**{"model.region_capacity": "auto"})
  resolved = step.measure_for_tool(config, _one())
  scene, _ = _batches(config, 0)
  model = components.make_model(config)
  measured = step.measure_capacity(config, scene, _one(), model.partition, 2.0, 6.0)
  assert resolved == measured and config.model.region_capacity == "auto"
  assert capsys.readouterr().err.splitlines()[-1] == f"nerfpod: {measured.line()} (on data.kind=procedural)"
  numbered = _config(**{"model.region_capacity": 0.5})
  assert step.measure_for_tool(numbered, _one()) is None
  with pytest.raises(UserError) as refused:
    step.measure_for_tool(_config(**{"model.region_capacity": "auto", "data.kind": "blender", "data.path": "/x"}),
                          _one())
  assert str(refused.value) == (
      "model.region_capacity=auto is measured on the scene's training rays, and this tool loads only the built-in "
      "scenes (data.kind procedural or street), not data.kind=blender; give a fraction instead, e.g. the one a "
      "training run with auto measured (its first lines print it, its workdir's config.json records it), or "
      "--config.model.region_capacity=0.75.")


def test_a_fitted_micro_batch_gets_the_margin_of_its_own_rays(tmp_path, monkeypatch, capsys):
  """train.microbatches=0 with a measured auto capacity: each count the fit tries compiles with F for that
  count's micro-batch of R / M rays (a smaller draw spreads wider: MeasuredCapacity.at_rows), and the run goes on
  with, records and says the fitted count's F; a fixed count, or a resumed record, compiles as resolved. (The
  compiler stands in: the fit's choice of count is compilation.fewest_microbatches', tested with the step.)"""
  import dataclasses
  from nerfpod.run import compilation
  config = _config(**{"model.region_capacity": "auto", "train.microbatches": 0})
  scene, _ = _batches(config, 0)
  comps = train.resolve_capacity(components.build_program(config, _one(), scene=scene), str(tmp_path), False)
  measured = comps.capacity_measured
  assert measured.rows == BATCH and comps.config.model.region_capacity == measured.fraction
  share = max(measured.counts) / measured.rays
  tried = []

  class Program:  # the step's lowering and compiling, as the fit calls them
    def __init__(self, fitted, count):
      self.seen = (count, fitted.config.model.region_capacity)

    def lower(self, *args):
      return self

    def compile(self):
      tried.append(self.seen)
      return self

  monkeypatch.setattr(step, "for_program", lambda fitted, count, backend=None: Program(fitted, count))
  monkeypatch.setattr(compilation, "step_memory_bytes", lambda compiled: 200 // compiled.seen[0])  # halves per count
  monkeypatch.setattr(compilation, "memory_budget_bytes", lambda config: 150)
  monkeypatch.setattr(compilation, "device_memory_bytes", lambda: 2**40)
  capsys.readouterr()
  fitted = step.compile_for_run(comps)
  wide = regions.auto_fraction(share, BATCH // 2)
  assert tried == [(1, measured.fraction), (2, wide)] and wide > measured.fraction
  assert fitted.step.seen == (2, wide) and fitted.comps.config.model.region_capacity == wide
  assert fitted.comps.capacity_measured == measured.at_rows(BATCH // 2)
  assert capsys.readouterr().out.splitlines()[-1] == (
      f"nerfpod: {measured.at_rows(BATCH // 2).line()} (its margin for one of the 2 micro-batches)")
  assert f"over a chip's {BATCH // 2} rays gives F = {wide:g}: C = {regions.capacity_rows(wide, 64)} of 64" in (
      measured.at_rows(64).line())
  # A fixed count was measured for its own micro-batch (region_rows); a resume's record has no measurement.
  for fixed in (dataclasses.replace(comps, config=_config(**{"model.region_capacity": 0.7, "train.microbatches": 2}),
                                    capacity_measured=measured.at_rows(BATCH // 2)),
                dataclasses.replace(comps, capacity_measured=None)):
    tried.clear()
    got = step.compile_for_run(fixed)
    assert got.comps is fixed and [c for _, c in tried] == [fixed.config.model.region_capacity] * len(tried)
  # Split classes: each F_j anew from its own fullest share, F their largest.
  split = step.MeasuredCapacity((700, 600), 1000, 128, 0.0, ((500, 150, 50), (100, 400, 100)), (0.0, 0.0, 0.0))
  wider = split.at_rows(32)
  assert wider.split_fractions == tuple(regions.auto_fraction(p, 32) for p in (0.5, 0.4, 0.1))
  assert wider.fraction == max(wider.split_fractions) and wider.rows == 32 and wider.counts == split.counts
