"""The shared set-up: the learning-rate schedule and gradient clipping against hand-computed values, the
state's shapes without an initialisation, and the renderer's chunking."""
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.sharding import Mesh

from conftest import smoke_config
from nerfpod import distributed
from nerfpod.render import renderer
from nerfpod.run import components, train_state
from nerfpod.nerf import cameras, compositing


def test_learning_rate_warms_up_linearly_then_decays_log_linearly_to_its_final_value():
  tc = smoke_config(**{"train.num_steps": 110, "train.lr_warmup_steps": 10, "train.lr_init": 1e-2,
                       "train.lr_final": 1e-4}).train
  schedule = jax.jit(train_state.learning_rate_schedule(tc))  # one program rather than one per operation
  for step, want in [(0, 0.0), (5, 5e-3), (10, 1e-2), (60, math.sqrt(1e-2 * 1e-4)), (110, 1e-4)]:
    assert float(schedule(step)) == pytest.approx(want, rel=1e-5, abs=1e-12), step
  # 35 of the 100 decay steps: lr_init * (lr_final / lr_init) ** (35 / 100).
  assert float(schedule(45)) == pytest.approx(1e-2 * (1e-2) ** 0.35, rel=1e-5)
  no_warmup = jax.jit(train_state.learning_rate_schedule(smoke_config(**{"train.num_steps": 100,
                                                                        "train.lr_warmup_steps": 0}).train))
  assert float(no_warmup(0)) == pytest.approx(tc.lr_init)


def test_adams_decays_are_the_configs():
  """train.adam_b1 and train.adam_b2 reach Adam: after one step from zero, its moments are (1 - b1) g and
  (1 - b2) g^2."""
  config = smoke_config(**{"train.adam_b1": 0.8, "train.adam_b2": 0.99})
  optimizer = train_state.make_optimizer(config.train)
  params = {"w": np.zeros(3, np.float32)}
  grads = {"w": np.array([1.0, -2.0, 0.5], np.float32)}
  # One program rather than one per operation.
  _, state = jax.jit(lambda g, p: optimizer.update(g, optimizer.init(p), p))(grads, params)
  adam = next(s for s in jax.tree.leaves(state, is_leaf=lambda x: hasattr(x, "nu")) if hasattr(s, "nu"))
  np.testing.assert_allclose(adam.mu["w"], 0.2 * grads["w"], rtol=1e-6)
  np.testing.assert_allclose(adam.nu["w"], 0.01 * grads["w"] ** 2, rtol=1e-6)


def test_gradient_clipping_scales_the_global_norm_to_the_limit_before_adam():
  grads = {"a": np.array([3.0, 0.0], np.float32), "b": np.array([[4.0]], np.float32)}  # global norm 5
  # A huge epsilon makes Adam's first step linear in the gradient, -lr * g / (|g| + eps) per entry (its
  # moments are then g and g^2), so the clipping to norm 2.5 (every entry halved) shows in the step.
  lr, eps = 0.1, 1e3
  def first_step(grad_clip):
    tc = smoke_config(**{"train.grad_clip": grad_clip, "train.lr_warmup_steps": 0, "train.lr_init": lr,
                         "train.lr_final": lr, "train.adam_eps": eps}).train
    optimizer = train_state.make_optimizer(tc)

    @jax.jit  # one program rather than one per operation
    def update(grads):
      params = jax.tree.map(jnp.zeros_like, grads)
      return optimizer.update(grads, optimizer.init(params), params)[0]
    return update(grads)
  for grad_clip, scale in ((2.5, 0.5), (10.0, 1.0), (0.0, 1.0)):  # 10: above the norm; 0: no clipping
    updates = first_step(grad_clip)
    for name, g in grads.items():
      g = np.asarray(g) * scale
      np.testing.assert_allclose(updates[name], -lr * g / (np.abs(g) + eps), rtol=1e-5, err_msg=name)


def _lazy_adam_reference(grads_TxN, b1, b2, eps, lr):
  """Adam entry by entry in float64, skipping an entry whose gradient is zero (its moments and value left),
  with the bias correction of the global step t (TensorFlow's LazyAdam)."""
  steps, n = grads_TxN.shape
  w, m, v = np.zeros(n), np.zeros(n), np.zeros(n)
  for t in range(1, steps + 1):
    for i in range(n):
      g = grads_TxN[t - 1, i]
      if g == 0:
        continue
      m[i] = b1 * m[i] + (1 - b1) * g
      v[i] = b2 * v[i] + (1 - b2) * g * g
      w[i] -= lr * (m[i] / (1 - b1**t)) / (np.sqrt(v[i] / (1 - b2**t)) + eps)
  return w


def test_sparse_adam_skips_entries_without_gradient():
  """scale_by_sparse_adam against the per-entry reference above, on gradients that are zero at random steps
  (an entry seen at step 1 only, one never seen, one seen at every step); where every step has a gradient it is
  optax's Adam, and dense Adam moves an entry on after its gradients stop, which this does not."""
  rng = np.random.default_rng(0)
  b1, b2, eps, lr = 0.9, 0.99, 1e-6, 0.1
  grads = rng.normal(size=(12, 6)) * (rng.random((12, 6)) < 0.5)
  grads[:, 0] = 0.0                                   # never seen
  grads[:, 1] = 0.0
  grads[0, 1] = 0.7                                   # seen at the first step only
  grads[:, 2] = rng.normal(size=12) + 0.1             # seen at every step
  optimizer = optax.chain(train_state.scale_by_sparse_adam(b1, b2, eps), optax.scale_by_learning_rate(lr))
  dense = optax.adam(lr, b1=b1, b2=b2, eps=eps)

  @jax.jit  # one program for both optimisers' 12 steps rather than one per operation
  def run(grads):
    params = jnp.zeros(6, jnp.float32)
    state = optimizer.init(params)
    for g in grads:
      updates, state = optimizer.update(g, state, params)
      params = optax.apply_updates(params, updates)
    dense_params, dense_state = jnp.zeros(6, jnp.float32), dense.init(jnp.zeros(6))
    for g in grads:
      updates, dense_state = dense.update(g, dense_state, dense_params)
      dense_params = optax.apply_updates(dense_params, updates)
    return params, dense_params

  params, dense_params = (np.asarray(p) for p in run(grads.astype(np.float32)))
  np.testing.assert_allclose(params, _lazy_adam_reference(grads, b1, b2, eps, lr), rtol=1e-5, atol=1e-7)
  assert params[0] == 0.0 and params[1] == pytest.approx(-lr, rel=1e-5)   # one step of lr, then left alone
  assert float(dense_params[2]) == pytest.approx(float(params[2]), rel=1e-5)  # a gradient every step: Adam's
  assert float(dense_params[1]) < 3 * -lr                              # dense: on along its momentum


def test_sparse_table_updates_reach_the_hash_tables_only(smoke):
  """With train.sparse_table_updates, make_optimizer gives the hash grids' level tables (the field's and the
  proposal's) the Adam that skips entries without a gradient and every other parameter optax's Adam; off, its
  state is optax's Adam alone."""
  config = smoke_config(**{"train.sparse_table_updates": True})
  params = jax.tree.map(np.asarray, smoke.init_state().params)  # the smoke model's, on the host
  labels = train_state._labels(tables=True)(params)
  named = {jax.tree_util.keystr(path): label for path, label in jax.tree_util.tree_leaves_with_path(labels)}
  tables = {name for name, label in named.items() if label == "table"}
  assert tables and all("['grid']['level_" in name for name in tables)
  assert {name for name in named if "['grid']['level_" in name} == tables
  assert any("proposal" in name for name in tables) == bool(config.render.proposal_samples)
  # A step whose gradient is zero on a table's first row leaves it; a dense Adam after a first step would not.
  grads = jax.tree.map(np.ones_like, params)  # (NumPy, as the edit below: no program per leaf)
  optimizer = train_state.make_optimizer(config.train)
  update = jax.jit(optimizer.update)  # (one program, not each leaf's operations compiled one by one)
  state = jax.jit(optimizer.init)(params)
  _, state = update(grads, state, params)
  first_table = sorted(tables)[0]
  def zero_first_row(path, g):
    if jax.tree_util.keystr(path) == first_table:
      g = g.copy()
      g[0] = 0.0
    return g
  updates, _ = update(jax.tree_util.tree_map_with_path(zero_first_row, grads), state, params)
  flat = {jax.tree_util.keystr(p): u for p, u in jax.tree_util.tree_leaves_with_path(updates)}
  first = np.asarray(flat[first_table])  # (rows read on the host: no program each)
  assert np.all(first[0] == 0.0) and np.all(first[1] != 0.0)
  tc = smoke_config().train
  adam = optax.adam(train_state.learning_rate_schedule(tc))
  # (Their states' shapes only: no program per leaf's initial moments.)
  assert (jax.tree.structure(jax.eval_shape(train_state.make_optimizer(tc).init, params))
          == jax.tree.structure(jax.eval_shape(adam.init, params)))


@pytest.fixture(scope="module")
def smoke():
  """The smoke config's components on all 8 devices (built once for the tests that only read them)."""
  return components.build(smoke_config())


@pytest.fixture(scope="module")
def smoke_on_4():
  """The smoke config's components on 4 devices and their initial parameters."""
  comps = components.build(smoke_config(), Mesh(np.array(jax.devices()[:4]), (distributed.DATA_AXIS,)))
  return comps, comps.init_state().params


def test_state_shapes_are_those_of_the_initial_state_without_computing_it(smoke):
  comps = smoke
  state = comps.init_state()
  got = jax.tree.map(lambda s: (s.shape, s.dtype, s.sharding), comps.state_shapes)
  want = jax.tree.map(lambda x: (x.shape, x.dtype, x.sharding), state)
  assert got == want
  assert all(isinstance(s, jax.ShapeDtypeStruct) for s in jax.tree.leaves(comps.state_shapes))


@pytest.mark.parametrize("num_rays,chunk", [(100, 24), (37, 8), (5, 64), (64, 64)])
def test_chunked_rendering_equals_one_call_when_the_chunk_does_not_divide_the_rays(smoke_on_4, num_rays, chunk):
  comps, params = smoke_on_4
  mesh = comps.mesh
  rng = np.random.default_rng(0)
  origins = rng.normal(size=(num_rays, 3)).astype(np.float32)
  origins = 4.0 * origins / np.linalg.norm(origins, axis=-1, keepdims=True)
  directions = (-origins + rng.normal(scale=0.3, size=origins.shape)).astype(np.float32)
  chunked = renderer.render_rays(comps.renderer, params, mesh, origins, directions, chunk)
  padded = -(-num_rays // 4) * 4  # one call: every ray at once (padded to split over the 4 devices)
  pad = lambda x: np.concatenate([x, np.repeat(x[-1:], padded - num_rays, 0)])
  whole = jax.device_get(comps.renderer(params, *distributed.to_global(mesh, (pad(origins), pad(directions)))))
  for name in compositing.OUTPUTS:
    assert chunked[name].shape[0] == num_rays
    np.testing.assert_allclose(chunked[name], whole[name][:num_rays], rtol=1e-5, atol=1e-6, err_msg=name)


@pytest.mark.parametrize("chunk,num_rays,devices,want", [
    (4096, 10000, 1, 3334),  # 3 calls of 3,334 (2 rays padded), not 4,096 + 4,096 + 1,808 padded to 4,096
    (4096, 10000, 8, 3336),  # multiples of the devices
    (4096, 4096, 1, 4096), (4096, 4097, 1, 2049), (4096, 100, 8, 104),  # one call of what the rays need
    (56, 192, 8, 48), (40, 192, 8, 40), (5, 192, 8, 8),  # a chunk below the devices: one ray each
])
def test_rays_are_split_into_as_few_calls_as_the_chunk_allows_of_equal_size(chunk, num_rays, devices, want):
  got = renderer.balanced_chunk(chunk, num_rays, devices)
  assert got == want and got % devices == 0 and got <= max(devices, chunk)
  assert -(-num_rays // got) == -(-num_rays // max(devices, chunk - chunk % devices))  # no more calls


def test_render_image_is_its_rays_in_row_major_order(smoke):
  comps = smoke
  params = comps.init_state().params
  intr = cameras.Intrinsics.from_focal(6, 5, 8.0)
  pose = cameras.look_at(np.array([0.0, -4.0, 1.0]))
  image = renderer.render_image(comps.renderer, params, comps.mesh, pose, intr, 0.5, 16)
  origins, directions = cameras.image_rays(pose, intr, 0.5)
  rays = renderer.render_rays(comps.renderer, params, comps.mesh, origins.reshape(-1, 3),
                            directions.reshape(-1, 3), 16)
  assert image["rgb"].shape == (5, 6, 3) and image["depth"].shape == (5, 6)
  np.testing.assert_array_equal(image["rgb"].reshape(-1, 3), rays["rgb"])


def test_the_program_without_a_scene_has_a_runs_state_and_batch_shapes(smoke):
  """What the pod compile tool compiles from: the same state as components.build's and the batch the data
  pipeline yields, laid over the mesh's data axis, without loading the scene."""
  from nerfpod import data
  built = smoke
  config, mesh = built.config, built.mesh
  program = components.build_program(config, mesh, backend="cpu")
  same = lambda a, b: jax.tree.map(lambda x, y: (x.shape, x.dtype, x.sharding) == (y.shape, y.dtype, y.sharding),
                                   a, b)
  assert all(jax.tree.leaves(same(program.state_shapes, built.state_shapes)))
  batch = next(iter(data.ray_batches(built.scene.split("train"), 0, config.train.batch_size,
                                     slice(0, config.train.batch_size), config.data.pixel_center, 1)))
  batch.pop("step")
  assert sorted(program.batch_shapes) == sorted(batch)  # alpha too: the procedural scene has it
  for name, value in batch.items():
    shape = program.batch_shapes[name]
    assert (shape.shape, shape.dtype) == (value.shape, value.dtype), name
    assert shape.sharding == distributed.batch_sharding(mesh)
  assert program.model == built.model  # on CPU: the gather lookup, as training uses
  tpu = components.build_program(config, mesh, backend="tpu").model
  assert tpu.grid_matmul_max_rows == config.compile.matmul_max_rows and built.model.grid_matmul_max_rows == 0
  # The points kept in memory for the grid's levels on a CPU only (the programs for accelerators unchanged).
  assert built.model.grid_materialize and not tpu.grid_materialize
  assert not components.build_program(config, mesh, backend="gpu").model.grid_materialize


def test_eval_samples_render_the_trained_field_with_a_finer_quadrature(smoke_on_4):
  """render.eval_samples: every rendering that trains nothing (the renderer: evaluation, previews, orbits,
  the viewer) queries the field at that many samples per ray, the train step at render.num_samples; the
  parameters are the same, and 0 leaves the renderer the training model's."""
  comps, params = smoke_on_4
  config = comps.config
  assert config.render.eval_samples == 0 and comps.render_model is comps.model
  finer = components.build_program(smoke_config(**{"render.eval_samples": 3 * config.render.num_samples}),
                                   comps.mesh, scene=comps.scene)
  assert finer.model == comps.model  # training unchanged
  assert finer.render_model.num_samples == 3 * config.render.num_samples
  assert finer.render_model.clone(num_samples=config.render.num_samples) == comps.model
  origins, directions = cameras.image_rays(comps.scene.split("test").poses[0], comps.scene.split("test").intrinsics,
                                           0.5)
  origins, directions = origins.reshape(-1, 3)[:64], directions.reshape(-1, 3)[:64]
  got = renderer.render_rays(finer.make_renderer(), params, comps.mesh, origins, directions, 64)
  want = jax.jit(finer.render_model.apply, static_argnums=(3, 4))(  # one program, not op by op
      params, origins, directions, finer.near, finer.far, jnp.asarray(finer.background))[-1]
  np.testing.assert_allclose(got["rgb"], want["rgb"], rtol=1e-5, atol=1e-6)
  assert want["weights"].shape == (64, 3 * config.render.num_samples)
  coarse = renderer.render_rays(comps.renderer, params, comps.mesh, origins, directions, 64)
  assert np.abs(got["depth"] - coarse["depth"]).max() > 1e-4  # another quadrature of the same field


def test_batches_the_host_cannot_hold_are_refused_before_any_work(tmp_path, monkeypatch):
  """Each host holds its share of a global batch in several copies at once (in use, on its devices, and on
  accelerators prepared ahead): a train.batch_size whose copies exceed components.BATCH_MEMORY_SHARE of the
  host's memory is one sentence naming the field and a size that fits, before the scene loads; no workdir is
  left behind."""
  from nerfpod.run import modes
  from nerfpod.errors import UserError
  from nerfpod.run import compilation
  monkeypatch.setattr(compilation, "physical_memory_bytes", lambda: 64 * 2**20)  # a 64 MiB host
  # 2 copies x 48 bytes x 2**20 rays = 96 MiB > 16 MiB; 16 MiB / 96 bytes = 174,762 rays -> 174,760 (x 8).
  with pytest.raises(UserError, match=r"^train.batch_size=1048576 rays would make this host hold 0.1 GiB of "
                                      r"training batches at once \(2 copies of its share\), more than the 0.0 GiB "
                                      r"\(25% of its memory\) they may take; set --config.train.batch_size to at "
                                      r"most 174760 \(a multiple of the 8 devices\)\.$"):
    modes.train_and_evaluate(smoke_config(**{"train.batch_size": 2**20}), str(tmp_path / "run"))
  assert not (tmp_path / "run").exists()
  components.check_batches_fit_host(smoke_config(**{"train.batch_size": 174760}))  # the size it names fits


def test_a_step_no_device_could_hold_is_refused_before_the_workdir_holds_anything(tmp_path, monkeypatch, smoke):
  """A fixed train.microbatches whose step needs more than a device has (XLA's memory analysis of the very
  step compiled) is one sentence naming the fields and what to set, before config.json or any checkpoint."""
  from nerfpod.run import compilation, modes
  from nerfpod.errors import UserError
  from nerfpod.run import step as train_step
  # The compiled step's own need (XLA's analysis), and a device one byte short of it, then one just enough.
  analysed, memory = [], compilation.step_memory_bytes
  monkeypatch.setattr(compilation, "step_memory_bytes", lambda compiled: analysed.append(memory(compiled)) or analysed[-1])
  monkeypatch.setattr(compilation, "device_memory_bytes", lambda: 2**40)
  train_step.compile_for_run(smoke)
  need = analysed[-1]
  assert 2**20 < need < 2**30  # (the smoke step: a few MiB, shown in MiB)
  monkeypatch.setattr(compilation, "device_memory_bytes", lambda: need)
  train_step.compile_for_run(smoke)  # exactly enough: no refusal
  monkeypatch.setattr(compilation, "device_memory_bytes", lambda: need - 1)
  figure = re.escape(f"needs {need / 2**20:,.1f} MiB per device by XLA's analysis, more than the "
                     f"{(need - 1) / 2**20:,.1f} MiB a device has")
  with pytest.raises(UserError, match=r"^the train step of train.batch_size=256 \(32 rays per device\) in 1 "
                                      r"micro-batch\(es\) " + figure + r"; set --config.train.microbatches=0 "
                                      r"\(the fewest that fit, found at start-up\) or more than 1, or a smaller "
                                      r"--config.train.batch_size\.$"):
    modes.train_and_evaluate(smoke_config(), str(tmp_path))
  written = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
  # TensorBoard's event file is opened before training; no config.json, scene.json, checkpoint or lock.
  assert [w for w in written if not w.startswith("events.out.tfevents.")] == [], written
