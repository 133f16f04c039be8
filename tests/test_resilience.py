"""Nothing good lost, in one process: damaged checkpoints are set aside and restore falls back, non-finite
steps never reach a saved state, metrics.json stays strict JSON, workdir mistakes are one sentence, the first
Ctrl-C is a preemption, and the gradient mean gives the same bits on any spread of devices.
(Real processes killed at random moments: test_chaos.py.)"""
import json
import os
import pathlib
import re
import signal

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from conftest import smoke_config
from nerfpod import distributed, schema
from nerfpod.run import evaluate, modes, preemption, train
from nerfpod.workdir import checkpoints, files as workdir_files
from nerfpod.run.step import Options, make_train_step
from nerfpod.run.train_state import TrainState
from nerfpod.errors import UserError

# A restore that fails half way leaves orbax an asyncio callback that fires after its loop closed: noise.
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")


def _mesh(count: int = 8) -> Mesh:
  return Mesh(np.array(jax.devices()[:count]), (distributed.DATA_AXIS,))


def _state(value: float, mesh=None, w=None):
  """A small train state (a dataclass, as the real one: orbax needs its saved metadata to read it back)."""
  params = {"w": jnp.full((4, 3), float(value)) if w is None else w, "b": jnp.arange(5.0) * value}
  tree = TrainState(step=jnp.asarray(int(value), jnp.int32), params=params,
                    opt_state=optax.adam(0.1).init(params))
  return jax.device_put(tree, NamedSharding(mesh or _mesh(), P()))


def _abstract(tree):
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), tree)


def _saved_steps(workdir, *steps):
  with checkpoints.Checkpoints(str(workdir), every_steps=1, max_to_keep=5) as ckpt:
    for step in steps:
      assert ckpt.save(step, _state(step), {"next_step": step})


def _empty_a_data_file(step_dir):
  files = sorted(p for p in pathlib.Path(step_dir, "state").rglob("*") if p.is_file() and p.parent.name == "d")
  assert files, f"no data files under {step_dir}"
  for path in files:
    path.write_bytes(b"")


DAMAGES = {
    "emptied data files": _empty_a_data_file,
    "deleted _METADATA": lambda step_dir: os.remove(step_dir / "state" / "_METADATA"),
    "deleted data position": lambda step_dir: [os.remove(p) for p in (step_dir / "data").iterdir()],
}


@pytest.mark.parametrize("damage", list(DAMAGES), ids=list(DAMAGES))
def test_a_damaged_newest_checkpoint_is_set_aside_and_restore_falls_back(tmp_path, capsys, damage):
  _saved_steps(tmp_path, 10, 20)
  directory = checkpoints.checkpoint_dir(str(tmp_path))
  DAMAGES[damage](directory / "20")
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=3) as ckpt:
    state, position = ckpt.restore(_abstract(_state(0)))
    assert position == {"next_step": 10} and int(state.step) == 10
    np.testing.assert_array_equal(state.params["b"], np.arange(5.0) * 10)
    assert ckpt.save(20, _state(20), {"next_step": 20})  # the run goes on and writes step 20 again
  err = capsys.readouterr().err
  lines = [line for line in err.splitlines() if line.startswith("nerfpod: warning:")]
  assert len(lines) == 1 and "step 20" in lines[0] and "set aside as" in lines[0], err
  assert checkpoints.finished_steps(str(tmp_path)) == [10, 20]
  aside = tmp_path / "checkpoints_damaged" / "20"
  assert aside.is_dir() and (aside / "state").is_dir()  # kept, not deleted


def test_read_only_restore_skips_a_damaged_step_and_leaves_it_in_place(tmp_path, capsys):
  _saved_steps(tmp_path, 10, 20)
  directory = checkpoints.checkpoint_dir(str(tmp_path))
  os.remove(directory / "20" / "state" / "_METADATA")
  damaged = {}
  step, state = checkpoints.restore_newest(str(tmp_path), _abstract(_state(0)), damaged=damaged)
  assert step == 10 and int(state.step) == 10 and list(damaged) == [20]
  (line,) = capsys.readouterr().err.splitlines()
  assert line.startswith(f"nerfpod: warning: the checkpoint of step 20 in {directory} does not read back whole (")
  assert "left in place" in line and line.endswith("falling back to the step before it")
  # Known damaged steps are not read again; none after the newest, or none that reads back whole: None.
  assert checkpoints.restore_newest(str(tmp_path), _abstract(_state(0)), damaged=damaged)[0] == 10
  assert capsys.readouterr().err == ""
  assert checkpoints.restore_newest(str(tmp_path), _abstract(_state(0)), above=10, damaged=damaged) is None
  assert (directory / "20").is_dir() and not (tmp_path / "checkpoints_damaged").exists()
  _, position, step = checkpoints.read_numpy(str(tmp_path))  # tools read the same way
  assert step == 10 and position == {"next_step": 10}


def test_no_readable_checkpoint_is_one_sentence_and_nothing_is_deleted(tmp_path):
  _saved_steps(tmp_path, 10, 20)
  directory = checkpoints.checkpoint_dir(str(tmp_path))
  for step in (10, 20):
    _empty_a_data_file(directory / str(step))
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=3) as ckpt:
    with pytest.raises(UserError, match=r"no checkpoint in .* reads back whole \(step 20: .*; step 10: .*\); "
                                        r"they were set aside in .*checkpoints_damaged"):
      ckpt.restore(_abstract(_state(0)))
  assert sorted(p.name for p in (tmp_path / "checkpoints_damaged").iterdir()) == ["10", "20"]


def test_a_non_finite_state_is_never_saved_and_a_saved_one_counts_as_damaged(tmp_path, capsys):
  _saved_steps(tmp_path, 10)
  bad = _state(20, w=jnp.full((4, 3), 20.0).at[0, 0].set(jnp.nan))
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=1) as ckpt:
    assert not ckpt.save(20, bad, {"next_step": 20}, force=True)
  assert "holds non-finite values; not saving it" in capsys.readouterr().err
  assert checkpoints.finished_steps(str(tmp_path)) == [10]  # max_to_keep=1 did not rotate step 10 out
  # A NaN state written by an older version (straight through orbax) reads back as damaged.
  import orbax.checkpoint as ocp
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=3) as ckpt:
    ckpt.manager.save(30, args=ocp.args.Composite(state=ocp.args.StandardSave(bad),
                                                  data=ocp.args.JsonSave({"next_step": 30})), force=True)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=3) as ckpt:
    _, position = ckpt.restore(_abstract(_state(0)))
  assert position == {"next_step": 10} and "non-finite values" in capsys.readouterr().err


def test_a_non_finite_loss_skips_the_update_and_the_loop_stops_after_too_many_in_a_row():
  config = smoke_config(**{"model.field": "mlp", "model.mlp.depth": 2, "model.mlp.width": 16,
                           "model.mlp.skips": (), "train.batch_size": 64,
                           "render.proposal_samples": ()})
  from nerfpod.run import train_state
  from nerfpod.run import components
  mesh = _mesh(2)
  model, optimizer = components.make_model(config), optax.adam(1e-2)
  state = train_state.initial_state(model, optimizer, 0, mesh)
  rng = np.random.default_rng(0)
  batch = {"origins": np.tile([0.0, 0.0, 4.0], (64, 1)).astype(np.float32),
           "directions": rng.normal(size=(64, 3)).astype(np.float32),
           "rgb": rng.uniform(size=(64, 3)).astype(np.float32), "ray_ids": np.arange(64, dtype=np.int32)}
  put = lambda b: jax.tree.map(lambda x: jax.device_put(x, distributed.batch_sharding(mesh)), b)  # noqa: E731
  before = jax.device_get(state.params)
  poisoned = dict(batch, rgb=batch["rgb"].copy())
  poisoned["rgb"][5, 1] = np.nan  # one ray's target: the loss and every gradient become NaN
  initial, kept = state, {}
  # The update under a conditional (CPUs) or selected after it (accelerators): the same skip, the same bits.
  for under_cond in (True, False):
    step_fn = make_train_step(model, optimizer, mesh, 2.0, 6.0, jnp.ones(3), Options(update_under_cond=under_cond))
    state, metrics = step_fn(jax.tree.map(jnp.copy, initial), put(poisoned), jax.random.key(0))
    assert int(metrics["skipped"]) == 1 and not np.isfinite(float(metrics["loss"]))
    assert int(state.step) == 1  # the data moves on
    jax.tree.map(np.testing.assert_array_equal, jax.device_get(state.params), before)
    assert int(jax.device_get(state.opt_state[0].count)) == 0  # Adam's moments and count untouched
    state, metrics = step_fn(state, put(batch), jax.random.key(0))
    assert int(metrics["skipped"]) == 0 and int(jax.device_get(state.opt_state[0].count)) == 1
    after = jax.tree.leaves(jax.device_get(state.params))
    assert any(not np.array_equal(a, b) for a, b in zip(after, jax.tree.leaves(before)))
    kept[under_cond] = jax.device_get(state)
  jax.tree.map(np.testing.assert_array_equal, kept[True], kept[False])

  class Saved:  # the checkpoints a run has saved: steps 2 and 4
    pinned = set()
    def newest_before(self, step):
      return max([s for s in (2, 4) if s < step], default=None)
    def pin(self, step):
      self.pinned.add(step)
    def unpin(self):
      self.pinned.clear()

  saved = Saved()
  skips = train.SkipCount(3, saved)
  for step, flag in [(1, 1), (2, 1), (3, 0)]:
    skips.record(step, jnp.asarray(flag))
  assert saved.pinned == set() and skips.in_row == 0  # a streak that ended unpins
  for step, flag in [(4, 1), (5, 1)]:
    skips.record(step, jnp.asarray(flag))
  assert skips.total == 4 and skips.in_row == 2 and saved.pinned == {2}  # saved before step 4, the first skip
  assert skips.position(6) == {"next_step": 6, "skipped": 4, "skipped_in_row": 2, "streak_from": 4,
                               "checkpoint_before_streak": 2}
  resumed = train.SkipCount(3, Saved(), skips.position(6))  # a resumed run goes on with the streak
  assert (resumed.total, resumed.in_row, resumed.first, resumed.before) == (4, 2, 4, 2)
  with pytest.raises(UserError, match=r"training diverged: it ended at step 5 inside a run of 2 skipped steps "
                                      r"\(from step 4,.*the newest checkpoint before it is step 2.*lower "
                                      r"train.lr_init"):
    skips.check_ended(5)
  with pytest.raises(UserError, match=r"training diverged: the last 3 steps \(to step 6\).*newest checkpoint "
                                      r"before it is step 2.*lower train.lr_init"):
    skips.record(6, jnp.asarray(1))
  assert skips.with_total({"loss": 1.0, "skipped": 1}) == {"loss": 1.0, "skipped": 5}
  fresh = train.SkipCount(3, Saved())
  fresh.record(1, jnp.asarray(1))
  with pytest.raises(UserError, match="no checkpoint was saved before it"):
    fresh.check_ended(1)
  assert train.SkipCount(3, Saved()).position(7) == {"next_step": 7}  # no skips: the position as ever


@pytest.mark.slow
def test_a_short_run_that_diverges_exits_non_zero_naming_the_checkpoint_before_it(tmp_path):
  """train.lr_init=1e30 on the 20-step smoke job: the parameters grow huge, then every step is skipped; fewer
  than train.max_nonfinite_steps in a row, but the run ends inside the streak, so it is refused (exit 2), the
  checkpoint before the streak is named and kept past max_to_keep, and rerunning the command refuses again."""
  from procs import run_main
  workdir = tmp_path / "run"
  flags = ("--config=configs/default.py:smoke", f"--workdir={workdir}", "--config.train.lr_init=1e30",
           "--config.checkpoint.every_steps=1", "--config.checkpoint.max_to_keep=2",
           "--config.orbit.render_after_training=false")
  result = run_main(*flags)
  errors = [line for line in result.stderr.splitlines() if line.startswith("nerfpod: error:")]
  assert result.returncode == 2 and len(errors) == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
  match = re.search(r"it ended at step 20 inside a run of (\d+) skipped steps \(from step (\d+),.*the newest "
                    r"checkpoint before it is step (\d+);", errors[0])
  assert match, errors[0]
  in_row, first, before = map(int, match.groups())
  assert in_row == 20 - first + 1 and before == first - 1 and in_row < 20
  assert checkpoints.finished_steps(str(workdir)) == [before, 19, 20]  # kept beyond the newest 2
  state, position, _ = checkpoints.read_numpy(str(workdir), before)
  assert position == {"next_step": before}
  assert not (workdir / "eval").exists()  # nothing evaluated, no orbit
  again = run_main(*flags)
  assert again.returncode == 2 and f"inside a run of {in_row} skipped steps" in again.stderr, again.stderr[-2000:]


def test_metrics_json_holds_null_with_a_reason_never_a_bare_nan(tmp_path):
  entry = evaluate._finite_or_null({"index": 0, "psnr": float("nan"), "ssim": 0.5})
  assert entry["psnr"] is None and entry["ssim"] == 0.5 and "psnr not finite (psnr=nan)" in entry["reason"]
  assert evaluate._finite_or_null({"psnr": 20.0, "ssim": 0.5}) == {"psnr": 20.0, "ssim": 0.5}
  workdir_files.write_json(tmp_path / "m.json", {"mean": entry})
  assert json.loads((tmp_path / "m.json").read_text(), parse_constant=lambda c: pytest.fail(c))["mean"] == entry
  with pytest.raises(ValueError):
    workdir_files.write_json(tmp_path / "n.json", {"psnr": float("nan")})
  assert not (tmp_path / "n.json").exists()


def test_workdir_mistakes_are_one_sentence_before_any_work(tmp_path):
  a_file = tmp_path / "file"
  a_file.write_text("x")
  config = smoke_config()
  for mode in (modes.train_and_evaluate, modes.evaluate_workdir):
    with pytest.raises(UserError, match=r"--workdir=.*file is an existing file, not a folder"):
      mode(config, str(a_file))
  trained = tmp_path / "trained"
  _saved_steps(trained, 10)
  (trained / "config.json").write_text('{"train": ')
  with pytest.raises(UserError, match=r"config.json is not valid JSON .*restore it"):
    modes.train_and_evaluate(config, str(trained))
  with pytest.raises(UserError, match=r"--workdir=.*file/run cannot be written \(Not a directory\)"):
    modes.train_and_evaluate(config, str(a_file / "run"))  # a folder that cannot be made
  if os.geteuid() != 0:  # root writes anywhere
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    with pytest.raises(UserError, match="cannot be written"):
      modes.train_and_evaluate(config, str(locked / "run"))


def test_a_refused_resume_leaves_config_json_as_it_was(tmp_path):
  saved = json.loads(smoke_config().to_json_best_effort())
  workdir_files.write_config(str(tmp_path), saved)
  _saved_steps(tmp_path, 10)
  before = (tmp_path / "config.json").read_bytes()
  with pytest.raises(UserError, match=r"different config: model.hashgrid.hidden_width \(16 -> 8\)") as refused:
    modes.train_and_evaluate(smoke_config(**{"model.hashgrid.hidden_width": 8}), str(tmp_path))
  assert (tmp_path / "config.json").read_bytes() == before
  # The sentence names what may change (the schema's RESUMABLE fields, in its order), the proposal guards a
  # collapse warning asks for among them.
  names = schema.resumable_names()
  assert {"render.proposal_padding", "train.proposal_anneal_steps", "model.trunc_exp"} <= set(names)
  assert f"(only {', '.join(names)} may change on resuming)." in str(refused.value)


def test_checkpoints_without_their_config_json_are_refused_and_left_as_they_were(tmp_path):
  """A workdir whose config.json is gone (deleted while a run still saved into it) holds checkpoints of an unknown
  config: a resume is one sentence, and nothing is written."""
  _saved_steps(tmp_path, 10)
  before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
  with pytest.raises(UserError, match=r"holds checkpoints but no config.json, the config they were trained with"):
    modes.train_and_evaluate(smoke_config(), str(tmp_path))
  assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_the_loop_moves_data_between_host_and_devices_only_explicitly(tmp_path, monkeypatch):
  """The tests run the training loop under jax.transfer_guard("disallow") (tests/conftest.py sets
  NERFPOD_LOOP_TRANSFER_GUARD; every run the tests train passes it); one implicit transfer in it fails the
  run. (On a CPU, reading a device array is no transfer, so the guard sees host -> device and device -> device
  ones there: a host value sent to a device, a key on one device sent to the mesh.)"""
  assert train.TRANSFER_GUARD == "disallow"

  def flush_implicitly(self):
    if self.pending is not None:
      self.pending[1]["loss"] * 2.0  # a host value (2.0) sent to the device without jax.device_put

  monkeypatch.setattr(train.StepLog, "flush", flush_implicitly)
  # JAX's wording (jax 0.10.2); a JAX that words it otherwise fails the match, and the test with it.
  with pytest.raises(jax.errors.JaxRuntimeError, match="Disallowed host-to-device transfer"):
    modes.train_and_evaluate(smoke_config(**{"train.num_steps": 2}), str(tmp_path))


def test_a_first_ctrl_c_in_training_is_a_preemption_and_the_handler_is_given_back(tmp_path):
  before = signal.getsignal(signal.SIGINT)
  ckpt = checkpoints.Checkpoints(str(tmp_path), every_steps=100, max_to_keep=3)
  watch = preemption.Watch(0)
  try:
    assert not watch.reached(3)
    os.kill(os.getpid(), signal.SIGINT)  # no KeyboardInterrupt: the step in hand is saved, then the run stops
    assert watch.reached(3)
    assert ckpt.save(3, _state(3), {"next_step": 3}, force=watch.reached(3))
  finally:
    ckpt.close()
    watch.close()
  assert signal.getsignal(signal.SIGINT) is before
  assert checkpoints.latest_step(str(tmp_path)) == 3


@pytest.mark.parametrize("devices", [8, 6, 1])
def test_ordered_mean_is_the_mean_in_index_order_and_the_same_on_every_device(devices):
  mesh = _mesh(devices)
  rng = np.random.default_rng(devices)
  # Magnitudes spread over many decades: the order of the additions shows in the last bits.
  values = (rng.normal(size=(devices, 257)) * 10.0 ** rng.integers(-6, 6, size=(devices, 257))).astype(np.float32)

  def local(x):
    mean = distributed.ordered_mean(x[0], distributed.DATA_AXIS, devices)
    return mean[None], jax.lax.all_gather(mean, distributed.DATA_AXIS)[None]

  step = jax.jit(jax.shard_map(local, mesh=mesh, in_specs=P(distributed.DATA_AXIS),
                               out_specs=(P(), P(distributed.DATA_AXIS))))
  mean, everywhere = step(jax.device_put(values, NamedSharding(mesh, P(distributed.DATA_AXIS))))
  everywhere = np.asarray(everywhere)
  assert all(np.array_equal(row, everywhere[0][0]) for row in everywhere.reshape(-1, 257))
  if devices & (devices - 1) == 0:  # the butterfly: pairs, then pairs of pairs, ...
    partial = list(values)
    while len(partial) > 1:
      partial = [partial[i] + partial[i + 1] for i in range(0, len(partial), 2)]
    expected = partial[0] / np.float32(devices)
  else:  # in index order
    expected = values[0].copy()
    for row in values[1:]:
      expected = expected + row
    expected = expected / np.float32(devices)
  if devices & (devices - 1):  # XLA may divide by 6 as a multiplication by 1/6: one ulp apart at most
    np.testing.assert_array_max_ulp(np.asarray(mean)[0], expected, maxulp=1)
  else:
    np.testing.assert_array_equal(np.asarray(mean)[0], expected)


def test_a_non_finite_evaluation_is_refused_after_metrics_json_is_written(monkeypatch, tmp_path):
  """A model whose renderings hold NaN does not exit 0 (by --mode=train or --mode=eval): metrics.json keeps the
  nulls with their reasons, and the run stops before the orbit with one sentence."""
  views = [{"index": 0, "psnr": 20.0, "ssim": 0.5, "lpips": None},
           {"index": 3, "psnr": None, "ssim": None, "lpips": None, "reason": "psnr and ssim not finite (psnr=nan)"}]
  monkeypatch.setattr(evaluate, "evaluate", lambda *a, **k: {"split": "test", "views": views, "mean": {}})
  with pytest.raises(UserError, match=r"the evaluation of step 7 is not finite: 1 of 2 held-out views rendered "
                                      r"non-finite values \(psnr and ssim not finite \(psnr=nan\)\), so the model "
                                      r"diverged; .*eval/metrics.json holds nulls"):
    modes._evaluate(None, None, str(tmp_path), 7)
  views[1] = dict(views[0], index=3)
  assert modes._evaluate(None, None, str(tmp_path), 7)["views"] == views


def _tmpfs(path, size: str):
  """Mounts a RAM disk of `size` at `path` (root only, where the machine allows mounts), else skips."""
  import subprocess
  path.mkdir(exist_ok=True)
  done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True,
                        text=True)
  if done.returncode != 0:
    pytest.skip(f"cannot mount a small tmpfs to fill up here ({done.stderr.strip() or 'mount failed'}); the "
                f"full-disk test needs root in a machine that allows mounts")


@pytest.mark.parametrize("raised", [OSError(28, "No space left on device"),  # ENOSPC, as Python raises it
                                    RuntimeError("tensorstore write failed: No space left on device")])
def test_a_full_disk_is_one_sentence_and_what_it_cut_off_goes_without_root_or_a_mount(tmp_path, raised):
  """The full-disk path on its own (the whole run on a RAM disk, below, needs root): whichever write hit the
  disk's end, the run stops with one sentence naming the newest complete checkpoint; a cut-off save and an
  empty events file are removed, the good checkpoint and a written events file stay; any other error passes."""
  _saved_steps(tmp_path, 4)
  # orbax's temporary folders of saves under way, as this orbax names them and as its docs do (a timestamp)
  cut_off = [checkpoints.checkpoint_dir(str(tmp_path)) / name
             for name in ("8.orbax-checkpoint-tmp", "12.orbax-checkpoint-tmp-1010101")]
  for folder in cut_off:
    folder.mkdir()
  (tmp_path / "events.out.tfevents.1.empty").write_bytes(b"")
  (tmp_path / "events.out.tfevents.2.written").write_bytes(b"header")
  with pytest.raises(UserError) as error:
    with modes._disk_full_is_one_sentence(str(tmp_path), training=True):
      raise raised
  assert str(error.value) == (f"the disk holding workdir {tmp_path} is full (No space left on device); the newest "
                              f"complete checkpoint, step 4, is safe; free space there (or pass a --workdir on a "
                              f"larger disk) and rerun the same command, which resumes from it.")
  assert not any(folder.exists() for folder in cut_off) and checkpoints.latest_step(str(tmp_path)) == 4
  assert sorted(p.name for p in tmp_path.glob("events.out.tfevents.*")) == ["events.out.tfevents.2.written"]
  with pytest.raises(ValueError, match="not a disk"):  # anything else is not turned into that sentence
    with modes._disk_full_is_one_sentence(str(tmp_path), training=True):
      raise ValueError("not a disk")


@pytest.mark.slow
def test_a_full_disk_is_one_sentence_naming_the_safe_checkpoint_and_a_rerun_with_space_resumes(tmp_path):
  """The smoke job on a 900 KiB RAM disk (room for one checkpoint of ~540 KiB, not two): it stops at its second
  save with one sentence naming the step that is safe, leaves no cut-off save, no lock and no empty events
  file; once the disk is larger the same command resumes and ends with the parameters of the run that never
  hit the disk's end. A disk full from the start is the same sentence, without a checkpoint to name."""
  import subprocess
  from procs import run_main
  flags = ("--config=configs/default.py:smoke", "--config.checkpoint.every_steps=4",
           "--config.orbit.render_after_training=false")
  reference = run_main(*flags, f"--workdir={tmp_path / 'reference'}")
  assert reference.returncode == 0, reference.stderr[-3000:]
  disk = tmp_path / "disk"
  _tmpfs(disk, "900k")
  try:
    workdir = disk / "run"
    full = run_main(*flags, f"--workdir={workdir}")
    errors = [line for line in full.stderr.splitlines() if line.startswith("nerfpod: error:")]
    assert full.returncode == 2 and len(errors) == 1, full.stderr[-3000:]
    assert "Traceback" not in full.stderr and "RESOURCE_EXHAUSTED" not in full.stderr, full.stderr[-3000:]
    assert errors[0] == (f"nerfpod: error: the disk holding workdir {workdir} is full (No space left on device); "
                         f"the newest complete checkpoint, step 4, is safe; free space there (or pass a --workdir "
                         f"on a larger disk) and rerun the same command, which resumes from it.")
    assert sorted(p.name for p in (workdir / "checkpoints").iterdir()) == ["4"]  # no cut-off save left
    assert not (workdir / "lock.json").exists() and not (workdir / "config.json.tmp").exists()
    assert all(p.stat().st_size > 0 for p in workdir.glob("events.out.tfevents.*"))
    subprocess.run(["mount", "-o", "remount,size=64m", str(disk)], check=True)
    resumed = run_main(*flags, f"--workdir={workdir}")
    assert resumed.returncode == 0 and "steps 4..20" in resumed.stdout, resumed.stderr[-3000:]
    want, _, _ = checkpoints.read_numpy(str(tmp_path / "reference"))
    got, position, step = checkpoints.read_numpy(str(workdir))
    assert step == 20 and position == {"next_step": 20}
    jax.tree.map(np.testing.assert_array_equal, got["params"], want["params"])
    subprocess.run(["umount", str(disk)], check=True)
    _tmpfs(disk, "8k")  # full from the start: config.json fits, nothing more
    at_start = run_main(*flags, f"--workdir={disk / 'new'}")
    assert at_start.returncode == 2 and "Traceback" not in at_start.stderr, at_start.stderr[-3000:]
    assert "is full (No space left on device); no checkpoint had been saved yet; free space there (or pass a " \
           "--workdir on a larger disk) and run the same command again." in at_start.stderr
    assert not list((disk / "new").glob("*.tmp")) and not list((disk / "new").glob("events.out.tfevents.*"))
  finally:
    subprocess.run(["umount", str(disk)], capture_output=True)


def test_a_data_mistake_leaves_no_new_workdir_and_no_lock_behind(tmp_path):
  workdir = tmp_path / "new-run"
  config = smoke_config(**{"data.kind": "blender", "data.path": str(tmp_path / "no-such-scene")})
  with pytest.raises(UserError, match="no-such-scene"):
    modes.train_and_evaluate(config, str(workdir))
  assert not workdir.exists()  # made for the run, removed again as it stayed empty
  existing = tmp_path / "existing"
  existing.mkdir()
  with pytest.raises(UserError, match="no-such-scene"):
    modes.train_and_evaluate(config, str(existing))
  assert existing.is_dir() and list(existing.iterdir()) == []  # a folder the user made stays; no lock.json


# A second Ctrl-C while training stops the process at once (os._exit), so it runs in a process of its own.
_SECOND_CTRL_C = r"""
import os, signal, sys, time
from nerfpod.run import preemption
watch = preemption.Watch(0)
os.kill(os.getpid(), signal.SIGINT)   # the first: a preemption, the step in hand is saved
assert watch.reached(1)
os.kill(os.getpid(), signal.SIGINT)   # the second: stop now, without saving
time.sleep(30)
sys.exit(0)
"""


def test_a_second_ctrl_c_in_training_stops_at_once_with_status_130():
  import subprocess
  import sys
  from conftest import REPO
  env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  done = subprocess.run([sys.executable, "-c", _SECOND_CTRL_C], env=env, capture_output=True, text=True,
                        timeout=60)
  assert done.returncode == 130, done.stderr
  assert "saving the current step" in done.stderr
  assert done.stderr.strip().endswith("nerfpod: interrupted again: stopping now, without saving")


# Ctrl-C in start-up, the evaluation or the orbit (a KeyboardInterrupt there), through nerfpod.main in a process
# of its own (absl's flags are the process's): each mode's exit status and stderr, as JSON.
_CTRL_C_OUTSIDE_STEPS = r"""
import contextlib, io, json, sys
from nerfpod import distributed, main
from nerfpod.run import compilation, modes

def interrupted(config, workdir):
  raise KeyboardInterrupt

for name in ("train_and_evaluate", "evaluate_workdir", "render_workdir"):
  setattr(modes, name, interrupted)
distributed.initialize = lambda *a, **k: None
out = {}
for mode in ("eval", "render", "train"):
  err = io.StringIO()
  with contextlib.redirect_stderr(err):
    try:
      main.run(["--config=configs/default.py:smoke", "--workdir=" + sys.argv[1], "--mode=" + mode])
      code = 0
    except SystemExit as e:
      code = e.code
  out[mode] = [code, err.getvalue()]
print(json.dumps(out))
"""


def test_ctrl_c_outside_training_steps_exits_130_in_one_sentence(tmp_path):
  import subprocess
  import sys
  from conftest import REPO
  env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  done = subprocess.run([sys.executable, "-c", _CTRL_C_OUTSIDE_STEPS, str(tmp_path)], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=120)
  assert done.returncode == 0, done.stderr[-3000:]
  for mode, (code, err) in json.loads(done.stdout.strip().splitlines()[-1]).items():
    assert code == 130, (mode, code, err)
    assert err.strip().splitlines() == ["nerfpod: interrupted; the same command resumes from the newest checkpoint"]
