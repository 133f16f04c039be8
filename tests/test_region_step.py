"""A model of K regions (model.regions, NeRF-XL) in the model, on the mesh and in the train step: each device
renders its regions, partial sums are gathered over the region axis; the same loss, gradients and parameters as
the whole model on one device."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.sharding import Mesh

from conftest import shared_model, smoke_config
from nerfpod import data, distributed, scenes
from nerfpod.errors import UserError
from nerfpod.nerf import model as nerf_model
from nerfpod.nerf import regions
from nerfpod.run import components, step, train_state


def _config(**overrides):
  tiny = {"model.regions": 4, "model.hashgrid.num_levels": 2, "model.hashgrid.log2_table_size": 6,
          "model.hashgrid.max_resolution": 32, "model.hashgrid.hidden_width": 8,
          "model.proposal.num_levels": 2, "model.proposal.log2_table_size": 6, "model.proposal.max_resolution": 32,
          "model.proposal.hidden_width": 8, "render.proposal_samples": (8,), "render.num_samples": 6,
          "train.batch_size": 64, "train.distortion_weight": 0.01, "model.hashgrid.bound": 1.5}
  return smoke_config(**(tiny | overrides))


# One optimiser object for the region files' SGD runs, with conftest.shared_model's one model per config: the
# tests that start from the same config share its init program (train_state.initial_state's, per pair).
SGD = optax.sgd(1.0)


def _rays(count=64, seed=0):
  rng = np.random.default_rng(seed)
  origins = rng.normal(size=(count, 3)) * 0.3 + np.array([0.0, 0.0, 4.0])
  directions = np.array([0.0, 0.0, -1.0]) + 0.3 * rng.normal(size=(count, 3))
  return jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32)


def test_regions_one_is_the_one_field_model():
  """model.regions=1, whatever the region settings say (a cut around the cameras, each region's own box), is the
  one-field model: its parameters have no region axis and its renders are the plain config's, bit for bit."""
  one = components.make_model(_config(**{"model.regions": 1, "model.region_cut": "cameras",
                                          "model.region_box": "own"}))
  plain = components.make_model(_config(**{"model.regions": 1}))
  assert one.regions == 1 and one.region_planes == ()  # NeRF's defaults: the model it always was
  origins, directions = _rays()
  init = lambda model: jax.jit(model.init)(jax.random.key(0), origins, directions, 2.0, 6.0, jnp.zeros(3))  # noqa: E731
  params = init(one)
  assert nerf_model.REGIONS not in params["params"] and "coarse" in params["params"]
  jax.tree.map(np.testing.assert_array_equal, params, init(plain))
  render = lambda model: jax.jit(model.apply)(params, origins, directions, 2.0, 6.0, jnp.ones(3))[-1]  # noqa: E731
  out, expected = render(one), render(plain)
  for key in ("rgb", "depth", "acc"):
    np.testing.assert_array_equal(out[key], expected[key])


@pytest.mark.slow  # (~15 s) the sharded step's equality below composites the device shares as well
def test_each_device_share_of_the_regions_composites_to_the_whole_model():
  """The model's own rendering of all K regions equals rendering the regions in two halves, each with its half
  of the stacked parameters only (a device's share), composited after."""
  model = components.make_model(_config())
  origins, directions = _rays()
  params = model.init(jax.random.key(0), origins[:2], directions[:2], 2.0, 6.0, jnp.zeros(3))
  stacked = params["params"]["regions"]
  assert all(leaf.shape[0] == 4 for leaf in jax.tree.leaves(stacked))
  whole = jax.jit(model.apply)(params, origins, directions, 2.0, 6.0, jnp.ones(3))[-1]
  partials_of = jax.jit(lambda share, ids: model.apply(share, origins, directions, 2.0, 6.0, ids,
                                                       method="render_partials")[0])
  halves = []
  for ids in (jnp.arange(2), jnp.arange(2, 4)):
    halves.append(partials_of({"params": {"regions": jax.tree.map(lambda p: p[ids], stacked)}}, ids))
  partials = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), *halves)
  out = regions.composite_regions(partials, jnp.ones(3))
  for key in ("rgb", "depth", "acc"):
    np.testing.assert_allclose(out[key], whole[key], rtol=1e-4, atol=1e-5)  # (jit moves a sample by round-off)
  assert float(jnp.std(whole["rgb"])) > 0  # rays saw the fields


def _batches(config, steps, with_frames=False):
  scene = scenes.load(config.data)
  dataset = data.ray_batches(scene.split("train"), 0, config.train.batch_size,
                             slice(0, config.train.batch_size), 0.5, steps, with_frames=with_frames)
  out = []
  for i in range(steps):
    batch = dict(dataset[i])
    batch.pop("step")
    out.append(batch)
  return scene, out


def _run(mesh, config, steps, optimizer, grad_clip=0.0, capacity=0.0):
  per_frame = bool(config.model.appearance_dim or config.train.pose_refine)
  model = shared_model(config, num_frames=100 if per_frame else 0)
  scene, batches = _batches(config, steps, per_frame)
  state = train_state.initial_state(model, optimizer, config.train.seed, mesh)
  step_fn = step.make_train_step(model, optimizer, mesh, 2.0, 6.0, scene.background,
                                 step.Options(random_background=True, distortion_weight=0.01, grad_clip=grad_clip,
                                              region_capacity=capacity))
  metrics_all = []
  for batch in batches:
    state, metrics = step_fn(state, jax.device_put(batch, distributed.batch_sharding(mesh)), jax.random.key(7))
    metrics_all.append(jax.device_get(metrics))
  return state, metrics_all


def test_the_mesh_gains_a_region_axis_and_refuses_what_does_not_split():
  mesh = distributed.make_mesh(regions=4)
  assert mesh.axis_names == ("data", "region") and mesh.devices.shape == (2, 4)
  assert distributed.batch_axes(mesh) == "data" and distributed.batch_devices(mesh) == 2
  assert distributed.make_mesh(num_slices=2, regions=2).devices.shape == (2, 2, 2)
  assert distributed.make_mesh(regions=1).axis_names == ("data",)
  with pytest.raises(UserError, match="model.regions=3 does not split over the 8 devices"):
    distributed.make_mesh(regions=3)
  with pytest.raises(UserError, match="model.regions=8 does not split over the 4 devices of a slice"):
    distributed.make_mesh(num_slices=2, regions=8)
  assert distributed.local_slice(64, mesh) == slice(0, 64)


# (4, 2) and (2, 1, 4) compile the 8-device step again for another layout: the slow set (about 15 s each).
@pytest.mark.parametrize("shape", [(2, 4), pytest.param((4, 2), marks=pytest.mark.slow),
                                   pytest.param((2, 1, 4), marks=pytest.mark.slow)])
def test_sharded_regions_step_matches_the_whole_model_on_one_device(shape):
  """Loss, metrics and parameters after two steps (plain SGD: parameters move exactly as the gradients) on
  8 devices, (data, region) = `shape`, equal the whole model's on one device, which holds every region and
  needs no gather: its gradients are plain autodiff of the stitched model's loss. A gradient K times too large
  (the gather's transpose summing every region device's cotangent) would show at once. (2, 1, 4): two
  simulated slices, (slice, data, region)."""
  config = _config(**{"model.regions": 4})
  one = Mesh(np.array(jax.devices()[:1]), (distributed.DATA_AXIS,))
  if len(shape) == 3:
    mesh = distributed.make_mesh(num_slices=shape[0], regions=shape[2])
    assert mesh.axis_names == (distributed.SLICE_AXIS, distributed.DATA_AXIS, distributed.REGION_AXIS)
  else:
    mesh = _region_mesh(shape)
  state_1, metrics_1 = _whole_model_two_sgd_steps()
  state_8, metrics_8 = _run(mesh, config, 2, SGD)
  for m1, m8 in zip(metrics_1, metrics_8):
    for key in ("loss", "mse", "interlevel", "distortion", "grad_norm"):
      np.testing.assert_allclose(m8[key], m1[key], rtol=2e-5, err_msg=key)
  assert metrics_1[0]["interlevel"] > 0 and metrics_1[0]["distortion"] > 0
  params_1, params_8 = jax.device_get(state_1.params), jax.device_get(state_8.params)
  initial = jax.device_get(train_state.initial_state(shared_model(config), SGD, 0, one).params)
  moved = jax.tree.map(lambda a, b: float(np.max(np.abs(a - b))), params_1, initial)
  assert max(jax.tree.leaves(moved)) > 1e-4  # the parameters did move
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), params_8, params_1)
  # Each device holds its regions' fields only: 1/K (4 regions on the axis) or 2/K of them.
  leaf = state_8.params["params"]["regions"]["coarse"]["rgb"]["kernel"]
  assert tuple(leaf.sharding.spec)[:1] == (distributed.REGION_AXIS,) and not any(tuple(leaf.sharding.spec)[1:])
  assert leaf.addressable_shards[0].data.shape[0] == 4 // shape[-1]


@functools.cache
def _whole_model_two_sgd_steps():
  """The reference of the sharded steps above: the whole 4-region model's two SGD steps on one device (one
  program, whichever mesh it is compared with, so computed once a session)."""
  one = Mesh(np.array(jax.devices()[:1]), (distributed.DATA_AXIS,))
  state, metrics = _run(one, _config(**{"model.regions": 4}), 2, SGD)
  return jax.device_get(state), metrics


def _region_mesh(shape):
  return Mesh(np.array(jax.devices()).reshape(shape), (distributed.DATA_AXIS, distributed.REGION_AXIS))


def test_each_device_holds_one_kth_of_the_region_fields():
  """Per-device parameter (and Adam moment) bytes, read off the state's shardings: the region fields' 1/K on
  each device of a (2 data x 4 regions) mesh, against the whole model replicated on every device."""
  config = _config(**{"model.regions": 4})
  model, adam = components.make_model(config), optax.adam(1e-2)

  def per_device_bytes(shapes, where):
    total = 0
    for path, leaf in jax.tree_util.tree_leaves_with_path(shapes):
      if where(path):
        shard = leaf.sharding.shard_shape(leaf.shape)
        total += int(np.prod(shard)) * leaf.dtype.itemsize
    return total

  sharded = train_state.state_shapes(model, adam, _region_mesh((2, 4)))
  whole = train_state.state_shapes(model, adam, Mesh(np.array(jax.devices()), (distributed.DATA_AXIS,)))
  region_bytes = per_device_bytes(sharded, nerf_model.in_region)
  assert region_bytes > 0 and region_bytes * 4 == per_device_bytes(whole, nerf_model.in_region)
  # Parameters, and Adam's two moments of them, all split the same way; nothing else is in the state here.
  assert per_device_bytes(sharded, lambda path: True) == region_bytes + 4 * 2  # + step and Adam's count
  leaf = sharded.params["params"]["regions"]["coarse"]["rgb"]["kernel"]
  assert leaf.sharding.spec == jax.sharding.PartitionSpec(distributed.REGION_AXIS)


def test_the_region_renderer_renders_each_devices_regions_as_the_whole_model():
  config = _config(**{"model.regions": 4})
  model = shared_model(config)
  origins, directions = _rays(count=64, seed=2)
  from nerfpod.render import renderer
  one = Mesh(np.array(jax.devices()[:1]), (distributed.DATA_AXIS,))
  params_1 = train_state.initial_state(model, SGD, 0, one).params
  want = renderer.render_rays(renderer.make_renderer(model, one, 2.0, 6.0, (1.0, 1.0, 1.0)), params_1, one,
                              np.asarray(origins), np.asarray(directions), 64)
  mesh = _region_mesh((2, 4))
  params_8 = train_state.initial_state(model, SGD, 0, mesh).params
  got = renderer.render_rays(renderer.make_renderer(model, mesh, 2.0, 6.0, (1.0, 1.0, 1.0)), params_8, mesh,
                             np.asarray(origins), np.asarray(directions), 64)
  for key in got:
    np.testing.assert_allclose(got[key], want[key], rtol=1e-5, atol=1e-6, err_msg=key)


def test_checkpoints_restore_the_region_fields_split_over_any_region_mesh(tmp_path):
  from nerfpod.workdir import checkpoints
  config = _config(**{"model.regions": 4})
  model, adam = components.make_model(config), optax.adam(1e-2)
  state = train_state.initial_state(model, adam, 0, _region_mesh((2, 4)))
  with checkpoints.Checkpoints(str(tmp_path), 1, 2) as ckpt:
    assert ckpt.save(1, state, {"next_step": 1})
  for shape in ((2, 4), (1, 4)):
    mesh = Mesh(np.array(jax.devices()[:shape[0] * shape[1]]).reshape(shape),
                (distributed.DATA_AXIS, distributed.REGION_AXIS))
    with checkpoints.Checkpoints(str(tmp_path), 1, 2) as ckpt:
      restored, position = ckpt.restore(train_state.state_shapes(model, adam, mesh))
    assert position == {"next_step": 1}
    leaf = restored.opt_state[0].mu["params"]["regions"]["coarse"]["rgb"]["kernel"]
    assert leaf.sharding.mesh.shape == mesh.shape and leaf.sharding.spec == jax.sharding.PartitionSpec("region")
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), restored, state)


def test_per_frame_tables_and_stratified_regions_step_as_the_whole_model():
  """The MLP field with stratified samples per segment (no proposals), per-frame appearance codes and pose
  corrections, replicated over the region axis: their gradients, summed over the region devices (each holds
  the part through its own region), then averaged over the data axis, equal the whole model's on one device;
  dense, and at a capacity with nothing dropped (model.region_capacity 0.75: 24 rows of each device's 32 rays,
  each row taking its ray's code and moved ray; tests/test_region_capacity.py holds the capacity's other
  claims)."""
  config = _config(**{"model.regions": 4, "model.field": "mlp", "model.mlp.depth": 2, "model.mlp.width": 16,
                      "model.mlp.skips": (), "model.use_viewdirs": True, "model.appearance_dim": 4,
                      "train.pose_refine": True, "render.proposal_samples": (), "render.num_samples": 8})
  one = Mesh(np.array(jax.devices()[:1]), (distributed.DATA_AXIS,))
  state_1, metrics_1 = _run(one, config, 2, SGD)
  params_1 = jax.device_get(state_1.params)
  assert np.abs(params_1["params"]["appearance"]).max() > 0  # the per-frame tables did move
  assert np.abs(params_1["params"]["pose_correction"]).max() > 0
  for capacity in (0.0, 0.75):
    state_8, metrics_8 = _run(_region_mesh((2, 4)), config, 2, SGD, capacity=capacity)
    for m1, m8 in zip(metrics_1, metrics_8):
      for key in ("loss", "grad_norm", "regions/segments_per_ray"):
        np.testing.assert_allclose(m8[key], m1[key], rtol=2e-5, err_msg=(key, capacity))
      assert m8.get("regions/capacity", 0) == (24 if capacity else 0) and m8["regions/dropped"] == 0
    params_8 = jax.device_get(state_8.params)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), params_8, params_1)
    assert state_8.params["params"]["appearance"].sharding.spec == jax.sharding.PartitionSpec()


def test_regions_cut_around_the_cameras():
  config = _config(**{"model.regions": 3, "model.region_cut": "cameras"})
  angles = np.linspace(0, 2 * np.pi, 30, endpoint=False)
  cameras = np.stack([4 * np.cos(angles), 4 * np.sin(angles), np.ones_like(angles)], -1)
  model = components.make_model(config, camera_positions=cameras)
  part = model.partition
  assert part.size == 3
  # Each camera lies in the region of its nearest k-means centre, and the centres share out the ring.
  which = np.asarray(jax.jit(lambda c: regions.region_of(c, part))(cameras.astype(np.float32)))  # one program
  centres = regions.kmeans(cameras[:, :2], 3)
  np.testing.assert_array_equal(which, np.argmin(((cameras[:, None, :2] - centres[None])**2).sum(-1), axis=1))
  assert min(np.bincount(which, minlength=3)) >= 8
  assert components.make_model(config).partition.size == 3  # without cameras: a placeholder ring


def test_regions_that_do_not_split_over_the_devices_are_one_sentence_and_exit_2(tmp_path, capsys, monkeypatch,
                                                                               run_start_held):
  """`python -m nerfpod.main` refuses before any work; in this process (procs.in_process; conftest.run_start_held
  puts back what the run's start-up sets), on its 8 CPU devices."""
  import procs
  from conftest import REPO
  from nerfpod import main
  assert jax.device_count() == 8  # the devices the regions must split over
  main_here = procs.in_process(main.run, "nerfpod.main", capsys, monkeypatch, REPO)
  result = main_here("--config=configs/default.py:smoke", f"--workdir={tmp_path}", "--config.model.regions=3")
  assert result.returncode == 2, result.stderr
  lines = [line for line in result.stderr.splitlines() if line.startswith("nerfpod: error:")]
  assert lines == ["nerfpod: error: model.regions=3 does not split over the 8 devices of a slice (each region's "
                   "fields live on the devices of its place on the mesh's region axis); make it a divisor of 8 "
                   "(one of 2, 4, 8) or 1."]
  assert "Traceback" not in result.stderr


@pytest.mark.slow  # (~12 s) one more pair of step compiles
def test_the_step_clips_the_norm_of_every_regions_gradients():
  """train.grad_clip with regions: the step clips by the global norm (every region's gradients, which no
  device's optimiser sees alone), as optax.clip_by_global_norm clips the whole model's on one device."""
  config = _config(**{"model.regions": 4, "train.grad_clip": 0.005})
  assert train_state.make_optimizer(config.train, clip=False) is not None
  one = Mesh(np.array(jax.devices()[:1]), (distributed.DATA_AXIS,))
  whole_model = optax.chain(optax.clip_by_global_norm(0.005), SGD)  # no region axis: optax's own clip
  state_1, metrics_1 = _run(one, config, 1, whole_model)
  state_8, metrics_8 = _run(_region_mesh((2, 4)), config, 1, SGD, grad_clip=0.005)
  assert metrics_1[0]["grad_norm"] > 0.005  # the clip was at work
  np.testing.assert_allclose(metrics_8[0]["grad_norm"], metrics_1[0]["grad_norm"], rtol=2e-5)
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6),
               jax.device_get(state_8.params), jax.device_get(state_1.params))
  # SGD at a learning rate of 1 moves the parameters by the clipped gradient: its global norm is the limit.
  initial = jax.device_get(train_state.initial_state(shared_model(config), SGD, 0, one).params)
  moved = jax.tree.map(lambda a, b: np.sum((np.asarray(a, np.float64) - b) ** 2), jax.device_get(state_8.params),
                       initial)
  np.testing.assert_allclose(np.sqrt(sum(jax.tree.leaves(moved))), 0.005, rtol=1e-3)


def test_each_regions_resampling_is_padded_and_annealed_inside_its_segment():
  """render.proposal_padding and the annealing exponent reach every region's rounds: the NeRF's intervals move
  (wider windows with padding, or with the weights annealed to w^0) and stay inside each region's segment."""
  origins, directions = _rays()
  plain = components.make_model(_config())
  padded = components.make_model(_config(**{"render.proposal_padding": 0.05}))
  params = jax.jit(plain.init)(jax.random.key(0), np.asarray(origins)[:2], np.asarray(directions)[:2], 2.0, 6.0,
                               np.zeros(3, np.float32))  # (NumPy slices: no program each)
  ids = np.arange(4, dtype=np.int32)
  # (Jitted: one program per model and annealing, not hundreds of operations compiled one by one.)
  edges = lambda model, **kw: jax.jit(functools.partial(model.apply, method="render_partials"))(  # noqa: E731
      params, origins, directions, 2.0, 6.0, ids, **kw)[1]["s_edges"]
  base, wide, flat = edges(plain), edges(padded), edges(plain, anneal=jnp.float32(0.0))
  np.testing.assert_array_equal(edges(plain, anneal=jnp.float32(1.0)), base)  # w^1: the raw histogram
  # Each region's segment [s_in, s_out] of the ray, as the model cuts it (the box, then the region's planes).
  from nerfpod.nerf import coord, sampling

  @jax.jit  # one program rather than one per operation
  def inside_and_spans(origins, directions, edges):
    near, far = sampling.clip_to_box(origins, directions, 2.0, 6.0, plain.model_config.hashgrid.bound)
    t_in, t_out = regions.segments(origins, directions, near, far, plain.partition)  # (K, R)
    to_s = lambda t: jnp.clip(coord.t_to_s(t[..., None], near, far, "linear"), 0.0, 1.0)  # noqa: E731
    s_in, s_out = to_s(t_in), jnp.maximum(to_s(t_out), to_s(t_in))  # (K, R, 1)
    return ([jnp.all((moved >= s_in - 1e-6) & (moved <= s_out + 1e-6)) for moved in edges],
            [jnp.mean(e[..., -1] - e[..., 0]) for e in edges])

  inside, (span_base, span_wide, _) = inside_and_spans(origins, directions, (base, wide, flat))
  assert all(bool(i) for i in inside)
  for moved in (wide, flat):
    assert not np.array_equal(np.asarray(moved), np.asarray(base))
  assert float(span_wide) >= float(span_base)
