"""model.region_split: a ray's samples split across its segments, a flat cost per ray (docs/scale.md, "A flat
cost per ray"): each segment of the compacted region step renders 2^-j of every sampling round's count, j the
class of its share of the ray, each class within rows of its own. Against independent references: a segment's
class from its share, computed on the host; the split rendering against the dense rendering of every region at
each class's counts, picked per segment; the split step on a region mesh against one device; drops and the
per-class counts of model.region_capacity=auto against brute-force counts; the resume's record; the refusals."""
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import shared_model
from test_region_capacity import _one, _step_scalars
from test_region_step import SGD, _batches, _region_mesh
from test_region_step import _config as _region_step_config
from nerfpod import distributed, schema
from nerfpod.errors import UserError
from nerfpod.nerf import regions, sampling
from nerfpod.pod import aot
from nerfpod.run import components, step, train, train_state

BATCH = 128
CLASSES = 3  # sample fractions 1, 1/2, 1/4: (8, 6), (4, 3) and (2, 2) samples of the tiny config's (8,) then 6
CLASS_COUNTS = [(8, 6), (4, 3), (2, 2)]


def _config(**overrides):
  """tests/test_region_step.py's tiny 4-region config (a 2 x 2 grid, 8 proposal intervals then 6 samples) with
  BATCH rays a step and CLASSES sample classes, split by the segments' lengths (the tests of the weights' split
  say so)."""
  return _region_step_config(**({"train.batch_size": BATCH, "model.region_split": CLASSES,
                                 "model.region_capacity": 1.0, "model.region_split_by": "length"} | overrides))


def _host_classes(t_in, t_out, near, far):
  """Each segment's class on the host, in float64: its share of the ray's [near, far] (linear spacing: the tiny
  config's), and the largest j < CLASSES with 2^-j at least that share, within regions.CLASS_EDGE (this
  symmetric scene's shares fall on 1/2 exactly, often: float rounding must not pick the class there)."""
  near, far = (np.asarray(x, np.float64)[:, 0] for x in (near, far))
  share = (np.asarray(t_out, np.float64) - np.asarray(t_in, np.float64)) / (far - near)
  klass = np.zeros(share.shape, int)
  for j in range(1, CLASSES):
    klass += share <= 2.0**-j * regions.CLASS_EDGE
  return share, klass


def test_a_segment_takes_the_class_of_its_share():
  share = jnp.array([1.0, 0.75, 0.5, 0.4, 0.25, 0.2, 0.125, 0.01, 0.0])  # (and 0.5 x (1 + 1e-4): still 1/2's)
  assert int(jax.jit(regions.sample_classes, static_argnums=1)(jnp.float32(0.5 * (1 + 1e-4)), 3)) == 1
  np.testing.assert_array_equal(jax.jit(regions.sample_classes, static_argnums=1)(share, 3),
                                [0, 0, 1, 1, 2, 2, 2, 2, 2])
  np.testing.assert_array_equal(jax.jit(regions.sample_classes, static_argnums=1)(share, 4),
                                [0, 0, 1, 1, 2, 2, 3, 3, 3])
  assert regions.class_fractions(3) == (1.0, 0.5, 0.25) and regions.class_fractions(0) == (1.0,)
  assert regions.class_counts((64, 32), 0.25) == (16, 8) and regions.class_counts((8, 6), 0.25) == (2, 2)
  assert regions.class_counts((3, 1), 0.125) == (1, 1)  # never fewer than one sample
  # Every class gets at least its share of the samples: fraction >= share for every share above the last class's.
  for s, j in zip(np.asarray(share), [0, 0, 1, 1, 2, 2, 2, 2, 2]):
    assert regions.class_fractions(3)[j] >= s or j == 2


@pytest.fixture(scope="module")
def batch_and_params():
  config = _config()
  model = components.make_model(config)
  _, (batch,) = _batches(config, 1)
  o, d = batch["origins"], batch["directions"]  # (NumPy: sliced without a program)
  params = jax.jit(model.init)(jax.random.key(0), o[:2], d[:2], 2.0, 6.0, np.zeros(3, np.float32))
  return batch, params


def test_the_split_rendering_is_each_segment_rendered_dense_at_its_class_counts(batch_and_params):
  """Compacted with a class's rows for every ray (C_j = R: nothing dropped), each segment's partial sums are the
  dense rendering's of a model sampling every round at the segment's class's counts (the same parameters, the
  first n_j of the segment's random numbers), picked per segment by its class computed on the host; absent
  segments empty."""
  batch, params = batch_and_params
  o, d = batch["origins"], batch["directions"]
  split = components.make_model(_config())
  counts = split.sample_counts()
  assert counts == CLASS_COUNTS[0]
  dense = [components.make_model(_config(**{"model.region_split": 0, "model.region_capacity": 0.0,
                                            "render.proposal_samples": c[:-1], "render.num_samples": c[-1]}))
           for c in CLASS_COUNTS]

  @jax.jit  # one program
  def run(params, o, d):
    uniforms = tuple(jax.random.uniform(jax.random.key(i), (4, BATCH, n)) for i, n in enumerate(counts))
    got, own = split.apply(params, o, d, 2.0, 6.0, jnp.arange(4), uniforms, capacity=(BATCH,) * CLASSES,
                           method="render_partials")
    want = []
    for model, class_counts in zip(dense, CLASS_COUNTS):
      class_uniforms = tuple(u[..., :n] for u, n in zip(uniforms, class_counts))
      want.append(model.apply(params, o, d, 2.0, 6.0, jnp.arange(4), class_uniforms, method="render_partials")[0])
    near, far = sampling.clip_to_box(o, d, 2.0, 6.0, 1.5)
    t_in, t_out = regions.segments(o, d, near, far, split.partition)
    return got, own["present"], own["dropped"], want, (t_in, t_out, near, far)

  got, present, dropped, want, (t_in, t_out, near, far) = jax.device_get(run(params, o, d))
  share, klass = _host_classes(t_in, t_out, near, far)
  present = np.asarray(present)
  np.testing.assert_array_equal(present, np.asarray(t_out) > np.asarray(t_in))
  assert not np.asarray(dropped).any()
  # The batch holds segments of every class (and absent ones), so each class's path is checked.
  assert all((present & (klass == j)).sum() >= 5 for j in range(CLASSES)) and (~present).sum() >= 5, (
      [(present & (klass == j)).sum() for j in range(CLASSES)])
  for key, value in got.items():
    expected = np.where(present.reshape(present.shape + (1,) * (value.ndim - 2)) if value.ndim > 2 else present,
                        np.choose(klass[..., None] if value.ndim > 2 else klass, [w[key] for w in want]),
                        np.broadcast_to(np.asarray(regions.empty_sums(np.asarray(far)[:, 0], key), np.float32),
                                        value.shape))
    np.testing.assert_allclose(value, expected, rtol=2e-5, atol=2e-6, err_msg=key)


def _run(mesh, steps=2, **overrides):
  """(state, metrics of each step) of `steps` SGD steps of the split step."""
  config = _config(**overrides)
  model = shared_model(config)
  scene, batches = _batches(config, steps)
  optimizer = SGD
  state = train_state.initial_state(model, optimizer, config.train.seed, mesh)
  options = step.Options(random_background=True, distortion_weight=0.01, region_capacity=1.0,
                         region_split=CLASSES, region_split_capacity=tuple(config.model.region_split_capacity))
  step_fn = step.make_train_step(model, optimizer, mesh, 2.0, 6.0, scene.background, options)
  metrics = []
  for batch in batches:
    state, m = step_fn(state, jax.device_put(batch, distributed.batch_sharding(mesh)), jax.random.key(7))
    metrics.append(jax.device_get(m))
  return jax.device_get(state), metrics, batches


@pytest.fixture(scope="module")
def on_one_device():
  return _run(_one())


@pytest.fixture(scope="module")
def segments(on_one_device):
  """Each region's segment (K, R) of the two batches' rays and their classes, as the model cuts them."""
  model = components.make_model(_config())

  @jax.jit  # one program
  def cut(o, d):
    near, far = sampling.clip_to_box(o, d, 2.0, 6.0, 1.5)
    return regions.segments(o, d, near, far, model.partition) + (near, far)
  out = []
  for batch in on_one_device[2]:
    t_in, t_out, near, far = jax.device_get(cut(batch["origins"], batch["directions"]))
    out.append((np.asarray(t_out) > np.asarray(t_in), _host_classes(t_in, t_out, near, far)[1]))
  return out


def test_the_split_step_on_a_region_mesh_is_the_one_devices(on_one_device, segments):
  """(2 data x 4 regions), each device its region's rows per class, the class counts summed over the region
  axis: the loss, metrics and the parameters after two SGD steps are the one-device split step's; the scalars
  are the classes' (field evaluations: L x sum of C_j x the class's samples; fill: the fullest (region, class)'s
  rays over its C_j, the mean over the data axis)."""
  state, metrics, _ = _run(_region_mesh((2, 4)))
  state_one, metrics_one, _ = on_one_device
  samples = [sum(regions.class_counts((8, 6), f)) for f in regions.class_fractions(CLASSES)]  # 14, 7, 4
  assert samples == [14, 7, 4]
  for m, m_one, (present, klass) in zip(metrics, metrics_one, segments):
    for key in ("loss", "mse", "interlevel", "distortion", "grad_norm", "regions/segments_per_ray"):
      np.testing.assert_allclose(m[key], m_one[key], rtol=2e-5, err_msg=key)
    assert m["regions/dropped"] == m_one["regions/dropped"] == 0
    assert m_one["regions/field_evals_per_chip"] == 4 * BATCH * sum(samples)
    assert m["regions/field_evals_per_chip"] == 1 * 64 * sum(samples)
    assert m_one["regions/capacity"] == 3 * BATCH and m["regions/capacity"] == 3 * 64
    fills = [max((present[:, i:i + 64] & (klass[:, i:i + 64] == j)).sum(axis=1).max() for j in range(CLASSES)) / 64
             for i in (0, 64)]
    assert m["regions/fill"] == pytest.approx(np.mean(fills), rel=1e-6)
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), state.params, state_one.params)


def test_an_overflowing_class_drops_whole_rays_and_counts_them(segments):
  """Class 2's C = 8 rows of 128 rays (the others roomy): a ray is dropped where any of its segments is of a
  class over its capacity in its region (counted per class, in ray order, by brute force)."""
  capacities = (1.0, 1.0, 0.0625)
  _, (metrics,), _ = _run(_one(), steps=1, **{"model.region_split_capacity": capacities})
  present, klass = segments[0]
  dropped = np.zeros(BATCH, bool)
  for j, f in enumerate(capacities):
    mine = present & (klass == j)
    dropped |= np.any(mine & (np.cumsum(mine, axis=1) - 1 >= regions.capacity_rows(f, BATCH)), axis=0)
  assert 0 < dropped.sum() < BATCH // 2
  assert metrics["regions/dropped"] == dropped.sum()
  assert metrics["regions/capacity"] == 128 + 128 + 8
  assert metrics["regions/fill"] == pytest.approx((present & (klass == 2)).sum(axis=1).max() / 8, rel=1e-6)


def test_auto_measures_each_class_as_a_host_count_and_a_resume_keeps_the_record(tmp_path, monkeypatch):
  """step.measure_capacity with model.region_split: the rays per region and class counted on the host (each
  ray's segments and their shares), F_j per class, F their largest; train.resolve_capacity records both in the
  config (config.json), and a resume with auto takes the record and measures nothing."""
  config = _config(**{"model.region_capacity": "auto"})
  scene, _ = _batches(config, 0)
  comps = components.build_program(config, _one(), scene=scene)
  measured = step.measure_capacity(config, scene, _one(), comps.model.partition, 2.0, 6.0)
  split = scene.split("train")
  origins, directions = regions.pixel_rays(np.asarray(split.poses), split.cameras, step.AUTO_RAYS, step.AUTO_SEED)

  @jax.jit  # one program
  def cut(o, d):
    near, far = sampling.clip_to_box(o, d, 2.0, 6.0, 1.5)
    return regions.segments(o, d, near, far, comps.model.partition) + (near, far)
  t_in, t_out, near, far = jax.device_get(cut(origins, directions))
  present = np.asarray(t_out) > np.asarray(t_in)
  klass = _host_classes(t_in, t_out, near, far)[1]
  want = np.stack([(present & (klass == j)).sum(axis=1) for j in range(CLASSES)], axis=1)
  np.testing.assert_array_equal(np.asarray(measured.class_counts), want)
  assert measured.counts == tuple(int(c) for c in present.sum(axis=1))
  assert measured.split_fractions == tuple(regions.auto_fraction(max(c[j] for c in measured.class_counts) / 65536,
                                                                 BATCH) for j in range(CLASSES))
  assert measured.fraction == max(measured.split_fractions)
  assert measured.line().startswith("model.region_capacity=auto: of 65,536 training rays, the shares that meet "
                                    "regions 0 to 3 are ")
  assert "; class 2 (1/4 of the samples): fullest share " in measured.line()
  fresh = train.resolve_capacity(comps, str(tmp_path), resuming=False)
  assert fresh.config.model.region_split_capacity == measured.split_fractions
  assert fresh.config.model.region_capacity == measured.fraction
  options = step.Options.of(fresh, 1)
  assert options.capacity_rows(BATCH) == tuple(regions.capacity_rows(f, BATCH) for f in measured.split_fractions)
  (tmp_path / "config.json").write_text(json.dumps({"model": {"region_capacity": 0.5,
                                                              "region_split_capacity": [0.3, 0.4, 0.5]}}))
  monkeypatch.setattr(step, "measure_capacity", lambda *args: pytest.fail("measured again on a resume"))
  resumed = train.resolve_capacity(comps, str(tmp_path), resuming=True)
  assert resumed.config.model.region_split_capacity == (0.3, 0.4, 0.5)
  assert resumed.config.model.region_capacity == 0.5
  monkeypatch.undo()
  # A record without the classes (a run of before, or of another split) is measured again.
  (tmp_path / "config.json").write_text(json.dumps({"model": {"region_capacity": 0.5}}))
  again = train.resolve_capacity(comps, str(tmp_path), resuming=True)
  assert again.config.model.region_split_capacity == measured.split_fractions


def test_the_refusal_of_a_split_names_its_classes_capacities():
  watch = train.DropWatch(0.5, 1024, split_fractions=(0.2, 0.25, 0.3))
  watch.dispatched(7, _step_scalars(5.0, 1.2, 768))
  with pytest.raises(UserError) as refused:
    watch.check()
  assert str(refused.value) == (
      "training dropped 5 of the 1,024 rays of steps 7 to 7 (0.49%, over the 0.1% a run may drop): "
      "model.region_split_capacity=(0.2, 0.25, 0.3) gives the regions' sample classes 768 rows in all of each "
      "device's rays and the fullest class of a region filled 1.20 x its rows, so rays over capacity were dropped "
      "whole; resume with --config.model.region_split_capacity='(0.3,0.35,0.4)' (or --config.model."
      "region_capacity=0: every ray through every region).")
  # The classes' fractions the loop's watch is given: model.region_capacity for every class where none are set.
  assert regions.class_capacities(1.0, 3) == (1.0, 1.0, 1.0)
  assert regions.class_capacities(0.5, 3, (0.2, 0.25, 0.3)) == (0.2, 0.25, 0.3)
  assert regions.class_capacities(1.0, 0) == () and regions.class_capacities(0.0, 3) == ()


def test_the_config_refuses_a_split_without_a_capacity_or_with_another_count_of_classes():
  with pytest.raises(schema.ConfigError) as refused:
    schema.validate(_config(**{"model.region_capacity": 0.0}))
  assert [m.split("=")[0] for m in refused.value.messages] == ["model.region_split"]
  assert "needs model.regions > 1 and a capacity" in refused.value.messages[0]
  with pytest.raises(schema.ConfigError) as refused:
    schema.validate(_config(**{"model.region_split_capacity": (0.5, 0.5)}))
  assert refused.value.messages == [
      "model.region_split_capacity='(0.5,0.5)' gives 2 capacities for model.region_split=3's 3 sample class(es); "
      "give one fraction per class (or --config.model.region_split_capacity='()': model.region_capacity for "
      "every class)."]
  schema.validate(_config(**{"model.region_capacity": "auto"}))  # (measured: no capacities needed)
  with pytest.raises(schema.ConfigError) as refused:
    schema.validate(_config(**{"model.region_split_by": "weights", "render.proposal_samples": ()}))
  assert refused.value.messages == [
      "model.region_split=3 splits the NeRF field's samples by the proposal rounds' weights "
      "(model.region_split_by=weights), and render.proposal_samples=() has no proposal rounds; use "
      "--config.model.region_split_by=length (or give proposal rounds, e.g. --config.render.proposal_samples='(32,)')."]
  schema.validate(_config(**{"model.region_split_by": "length", "render.proposal_samples": ()}))
  schema.validate(_config(**{"model.region_split_by": "weights", "model.region_split": 0}))  # (no split: no effect)


def test_the_pod_tools_figures_count_each_class_at_its_samples():
  """aot.region_figures with the classes: rows C_j of each class's fraction, evaluations sum C_j x its samples
  (the model's counts (32, 16) at the classes' 1, 1/2 and 1/4: 48, 24 and 12 samples a row)."""
  figures = aot.region_figures(1024, 1, 8, 8, 48, 1, 0.5, split_capacity=(0.2, 0.25, 0.3), sample_counts=(32, 16))
  rows = [regions.capacity_rows(f, 1024) for f in (0.2, 0.25, 0.3)]
  assert figures["class_rows"] == rows == [208, 256, 312]
  assert figures["class_samples"] == [48, 24, 12]
  assert figures["capacity_rows"] == sum(rows)
  assert figures["field_evals_per_chip"] == 208 * 48 + 256 * 24 + 312 * 12
  assert figures["field_evals_per_chip_dense"] == 1024 * 48
  config = _config()
  assert aot._split_figures(config, components.make_model(config)) == dict(
      split_capacity=(1.0, 1.0, 1.0), split_by="length", sample_counts=(8, 6))
  assert aot._split_figures(_config(**{"model.region_split": 0}), None) == {}
  # By weights: the proposal rounds over the length classes' rows, the NeRF round over final_capacities'.
  weighted = aot.region_figures(1024, 1, 8, 8, 48, 1, 0.5, split_capacity=(0.2, 0.25, 0.3), split_by="weights",
                                sample_counts=(32, 16))
  assert weighted["final_rows"] == [208, 256, 208 + 256 + 312]
  assert weighted["field_evals_per_chip"] == (208 * 32 + 256 * 16 + 312 * 8) + (208 * 16 + 256 * 8 + 776 * 4)
  # What `nerfpod aot` prints of each.
  report = {"pod": "v5e-8", "topology": "2x4", "chips": 8, "hosts": 1, "chip": {"kind": "TPU v5e", "hbm_bytes": 2**34,
            "source": "test"}, "batch": 1024, "rays_per_chip": 1024, "microbatches": 1, "compute_dtype": "float32",
            "hashgrid_matmul_max_rows": 0, "host_rows_contiguous": True}
  assert ("1 region(s) x (208 rows x 48 samples + 256 rows x 24 samples + 312 rows x 12 samples) x 1 "
          "micro-batch(es) = 19,872 with model.region_split's 3 sample classes") in aot.format_report(
              report | {"regions": figures})
  assert ("the proposal rounds on 208 + 256 + 312 rows of the length classes and the NeRF round on 208 + 256 + 776 "
          "rows of the weight classes x 1 micro-batch(es) = 21,728") in aot.format_report(
              report | {"regions": weighted})


def test_a_segments_weight_share_and_the_nerf_rounds_rows_with_classes_handed_down():
  """regions.weight_shares against a host product in ray order (unsorted regions, an empty segment, an opaque
  one hiding what lies behind it), and regions.downgrade_dispatch against a host walk: class j takes its own
  segments and those class j - 1 had no row for, the first C_j in ray order; the last class holds the rest."""
  opacity = np.array([[0.5, 0.0, 0.2, 0.9], [0.25, 0.3, 0.0, 1.0], [0.0, 0.6, 0.7, 0.5]], np.float32)  # (K, R)
  t_in = np.array([[3.0, 6.0, 2.0, 4.0], [2.0, 3.0, 6.0, 2.0], [6.0, 2.5, 3.0, 5.0]], np.float32)
  want = np.zeros((3, 4))
  for r in range(4):
    light = 1.0
    for k in np.argsort(t_in[:, r], kind="stable"):
      want[k, r], light = light * opacity[k, r], light * (1.0 - opacity[k, r])
  np.testing.assert_allclose(jax.jit(regions.weight_shares)(opacity, t_in), want, rtol=1e-6)
  assert want[0, 3] == 0.0 and want[2, 3] == 0.0  # behind region 1's opaque segment: nothing reaches them
  rng = np.random.default_rng(3)
  klass = rng.integers(0, 3, (2, 40))
  kept = rng.random((2, 40)) < 0.8
  capacities = regions.final_capacities((6, 9, 30))
  assert capacities == (6, 9, 45)
  got = jax.jit(lambda k, p: regions.downgrade_dispatch(k, p, capacities))(klass, kept)
  for region in range(2):
    handed, seen = [], set()
    for j, capacity in enumerate(capacities):
      wants = [r for r in range(40) if kept[region, r] and (klass[region, r] == j or r in handed)]
      rows, handed = wants[:capacity], wants[capacity:]
      np.testing.assert_array_equal(np.asarray(got[j].rows_LxC[region]), rows + [40] * (capacity - len(rows)))
      assert not seen & set(rows)
      seen |= set(rows)
    assert seen == {r for r in range(40) if kept[region, r]} and not handed  # every kept segment, once
  assert np.asarray(got[0].dropped_LxR).sum() > 0  # (class 0 overflowed: its segments went on to class 1)


def test_the_weighted_split_renders_each_segment_as_a_dense_model_of_its_two_classes(batch_and_params):
  """model.region_split_by=weights with roomy rows: each segment's partial sums and histograms are those of a
  dense model whose proposal rounds sample at the counts of the segment's length class and whose NeRF round
  samples at the class of its share of the ray's proposal weight (the same parameters and random numbers), that
  share computed on the host from those proposal weights (every region's, in ray order). Two classes: (8, 6)
  and (4, 3). (The same step on a 2 x 4 mesh against one device: the extended set.)"""
  batch, params = batch_and_params
  o, d = batch["origins"], batch["directions"]
  split = components.make_model(_config(**{"model.region_split": 2, "model.region_split_by": "weights"}))
  counts = split.sample_counts()
  pairs = [(a, b) for a in range(2) for b in range(2)]  # (length class, weight class)
  dense = [components.make_model(_config(**{"model.region_split": 0, "model.region_capacity": 0.0,
                                            "render.proposal_samples": CLASS_COUNTS[a][:-1],
                                            "render.num_samples": CLASS_COUNTS[b][-1]})) for a, b in pairs]

  @jax.jit  # one program
  def run(params, o, d):
    uniforms = tuple(jax.random.uniform(jax.random.key(i), (4, BATCH, n)) for i, n in enumerate(counts))
    got, own = split.apply(params, o, d, 2.0, 6.0, jnp.arange(4), uniforms, capacity=(BATCH,) * 2,
                           method="render_partials")
    want = []
    for model, (a, b) in zip(dense, pairs):
      class_uniforms = (uniforms[0][..., :CLASS_COUNTS[a][0]], uniforms[1][..., :CLASS_COUNTS[b][1]])
      want.append(model.apply(params, o, d, 2.0, 6.0, jnp.arange(4), class_uniforms, method="render_partials"))
    near, far = sampling.clip_to_box(o, d, 2.0, 6.0, 1.5)
    t_in, t_out = regions.segments(o, d, near, far, split.partition)
    return got, own, want, (t_in, t_out, near, far)

  got, own, want, (t_in, t_out, near, far) = jax.device_get(run(params, o, d))
  present = np.asarray(own["present"])
  assert not np.asarray(own["dropped"]).any() and not np.asarray(own["downgraded"]).any()
  length = _host_classes(t_in, t_out, near, far)[1].clip(0, 1)  # (two classes: share above 1/2 or not)
  opacity = np.where(length == 0, want[0][1]["proposals"][-1]["weights"].sum(-1),
                     want[2][1]["proposals"][-1]["weights"].sum(-1)).astype(np.float64) * present
  share = np.zeros(opacity.shape)
  for r in range(BATCH):  # the host's product in ray order
    light = 1.0
    for k in np.argsort(np.where(present[:, r], t_in[:, r], np.inf), kind="stable"):
      share[k, r], light = light * opacity[k, r], light * (1.0 - opacity[k, r])
  weight = (share <= 0.5).astype(int)
  clear = present & (np.abs(share - 0.5) > 1e-4)  # (a share within float rounding of 1/2: either class)
  assert [(clear & (length == a) & (weight == b)).sum() >= 3 for a, b in pairs] == [True] * 4
  pick = np.asarray([[pairs.index((a, b)) for a, b in zip(la, wa)] for la, wa in zip(length, weight)])
  for key, value in got.items():
    expected = np.choose(pick[..., None] if value.ndim > 2 else pick, [w[0][key] for w in want])
    mask = clear.reshape(clear.shape + (1,) * (value.ndim - 2))
    np.testing.assert_allclose(np.where(mask, value, 0.0), np.where(mask, expected, 0.0), rtol=2e-5, atol=2e-6,
                               err_msg=key)
  # The rows' NeRF histograms are the reference's, their proposal histograms the length class's (padded).
  for j, klass in enumerate(own["classes"]):
    rows = np.asarray(klass["dispatch"].rows_LxC)
    for region in range(4):
      for c, ray in enumerate(rows[region]):
        if ray == BATCH or not clear[region, ray]:
          continue
        ref = want[pick[region, ray]][1]
        assert weight[region, ray] == j
        np.testing.assert_allclose(klass["weights"][region, c], ref["weights"][region, ray], rtol=2e-5, atol=2e-6)
        bins = ref["proposals"][0]["weights"].shape[-1]
        np.testing.assert_allclose(klass["proposals"][0]["weights"][region, c, :bins],
                                   ref["proposals"][0]["weights"][region, ray], rtol=2e-5, atol=2e-6)
        assert not klass["proposals"][0]["weights"][region, c, bins:].any()


@pytest.mark.slow  # (two split steps, ~12 s; the quick loop checks the weighted rendering against dense models
# and the length split's step on this mesh)
def test_the_weighted_split_step_on_a_region_mesh_is_the_one_devices():
  """model.region_split_by=weights on 2 data x 4 regions, the opacities gathered over the region axis: the loss,
  metrics and the parameters after two SGD steps are the one-device step's; field evaluations count the proposal
  rounds at the length classes' rows and the NeRF round at the weight classes' (regions.split_evals); with a
  class 0 of 8 rows the NeRF round hands segments down (regions/downgraded)."""
  weights = {"model.region_split_by": "weights"}
  state, metrics, _ = _run(_region_mesh((2, 4)), **weights)
  state_one, metrics_one, _ = _run(_one(), **weights)
  for m, m_one in zip(metrics, metrics_one):
    for key in ("loss", "mse", "interlevel", "distortion", "grad_norm", "regions/segments_per_ray",
                "regions/downgraded"):
      np.testing.assert_allclose(m[key], m_one[key], rtol=2e-5, err_msg=key)
    assert m_one["regions/downgraded"] == 0 and m_one["regions/dropped"] == 0
    assert m_one["regions/field_evals_per_chip"] == 4 * regions.split_evals((8, 6), (BATCH,) * 3, "weights")
    assert m["regions/field_evals_per_chip"] == 1 * regions.split_evals((8, 6), (64,) * 3, "weights")
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), state.params, state_one.params)
  assert regions.split_evals((8, 6), (10, 20, 30), "weights") == 10 * 8 + 20 * 4 + 30 * 2 + 10 * 6 + 20 * 3 + 60 * 2
  assert regions.split_evals((8, 6), (10, 20, 30)) == 10 * 14 + 20 * 7 + 30 * 4
  _, (tight,), _ = _run(_one(), steps=1, **weights, **{"model.region_split_capacity": (0.0625, 1.0, 1.0)})
  assert tight["regions/downgraded"] > 0
