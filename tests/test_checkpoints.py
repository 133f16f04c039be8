"""Checkpoints in one process: complete steps only, max_to_keep, restore onto another mesh, SIGTERM, and the
config-compatibility check. (Real processes, kills and pods: test_multiprocess.py.)"""
import json
import os
import shutil
import signal

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from conftest import smoke_config
from nerfpod import distributed, schema
from nerfpod.run import preemption
from nerfpod.workdir import checkpoints, files as workdir_files
from nerfpod.errors import UserError


def _state(mesh, value: float):
  """A small replicated pytree, as the train state is."""
  tree = {"step": jnp.asarray(int(value), jnp.int32), "params": {"w": jnp.full((4, 3), float(value)),
                                                                 "b": jnp.arange(5.0) * value}}
  return jax.device_put(tree, NamedSharding(mesh, P()))


def _abstract(tree):
  """ShapeDtypeStructs with shardings: what a restore fills (train_state.state_shapes for a train state)."""
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), tree)


def _mesh(count: int) -> Mesh:
  return Mesh(np.array(jax.devices()[:count]), (distributed.DATA_AXIS,))


def test_saves_every_n_steps_keeps_the_newest_and_restores_state_and_position(tmp_path):
  mesh = _mesh(8)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=2, max_to_keep=2) as ckpt:
    saved = [step for step in range(1, 8)
             if ckpt.save(step, _state(mesh, step), {"next_step": step}, force=step == 5)]
    ckpt.manager.wait_until_finished()
  assert saved == [2, 4, 5, 6]  # every 2 steps and the forced one (a preemption's), no extra save of step 1
  assert checkpoints.finished_steps(str(tmp_path)) == [5, 6]
  with checkpoints.Checkpoints(str(tmp_path), every_steps=2, max_to_keep=2) as ckpt:
    state, position = ckpt.restore(_abstract(_state(mesh, 0)))
  assert position == {"next_step": 6}
  np.testing.assert_array_equal(state["params"]["b"], np.arange(5.0) * 6)


def test_rotated_out_steps_are_renamed_before_they_are_deleted_and_remains_are_cleared(tmp_path, capfd):
  """A step rotated out is renamed into checkpoints/.rotated/ in one move and deleted there: a process killed
  while deleting it leaves its remains in .rotated/ (cleared by the next run), never a step folder without
  its metadata among the good ones (orbax warned "Metadata file does not exist" on every later start)."""
  mesh = _mesh(8)
  directory = checkpoints.checkpoint_dir(str(tmp_path))
  renamed = []
  original = checkpoints.Checkpoints._delete_rotated

  def recording(self):  # what is in .rotated/ each time it is emptied
    rotated = directory / checkpoints.ROTATED
    renamed.append(sorted(p.name for p in rotated.iterdir()) if rotated.exists() else [])
    original(self)

  with pytest.MonkeyPatch.context() as patch:
    patch.setattr(checkpoints.Checkpoints, "_delete_rotated", recording)
    with checkpoints.Checkpoints(str(tmp_path), every_steps=1, max_to_keep=2) as ckpt:
      for step in range(1, 5):
        ckpt.save(step, _state(mesh, step), {"next_step": step})
  # Steps 1 and 2 went through .rotated/ (seen there before a later save, or when the run ended).
  assert sorted(sum(renamed, [])) == ["1", "2"], renamed
  assert sorted(p.name for p in directory.iterdir()) == [checkpoints.ROTATED, "3", "4"]
  assert not list((directory / checkpoints.ROTATED).iterdir())  # emptied when the run ended
  # What a process killed half way through deleting step 2 leaves: part of it, without its metadata.
  remains = directory / checkpoints.ROTATED / "2"
  shutil.copytree(directory / "3", remains)
  os.remove(remains / "_CHECKPOINT_METADATA")
  capfd.readouterr()
  with checkpoints.Checkpoints(str(tmp_path), every_steps=1, max_to_keep=2) as ckpt:
    assert ckpt.manager.all_steps() == [3, 4]
    state, position = ckpt.restore(_abstract(_state(mesh, 0)))
  assert position == {"next_step": 4} and int(state["step"]) == 4
  assert not remains.exists() and checkpoints.finished_steps(str(tmp_path)) == [3, 4]
  assert "Metadata file does not exist" not in "".join(capfd.readouterr())

def test_a_save_cut_off_half_way_is_never_the_latest(tmp_path):
  mesh = _mesh(8)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=3) as ckpt:
    ckpt.save(10, _state(mesh, 10), {"next_step": 10})
  directory = checkpoints.checkpoint_dir(str(tmp_path))
  # What a process killed while writing step 20 leaves behind: orbax's temporary folder, half full.
  shutil.copytree(directory / "10", directory / "20.orbax-checkpoint-tmp")
  os.remove(directory / "20.orbax-checkpoint-tmp" / "commit_success.txt")
  shutil.rmtree(directory / "20.orbax-checkpoint-tmp" / "state" / "d")
  assert checkpoints.latest_step(str(tmp_path)) == 10
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=3) as ckpt:
    assert ckpt.latest_step() == 10
    state, position = ckpt.restore(_abstract(_state(mesh, 0)))
    assert position == {"next_step": 10} and int(state["step"]) == 10
    # The run goes on and writes step 20 properly over the leftovers.
    assert ckpt.save(20, _state(mesh, 20), {"next_step": 20})
  assert checkpoints.finished_steps(str(tmp_path)) == [10, 20]
  assert not (directory / "20.orbax-checkpoint-tmp").exists()


def test_read_only_restore_leaves_a_save_under_way_and_sigterm_alone(tmp_path):
  """--mode=eval/render may run beside training: they must not clean up its in-progress save."""
  mesh = _mesh(8)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=3) as ckpt:
    ckpt.save(10, _state(mesh, 10), {"next_step": 10})
  directory = checkpoints.checkpoint_dir(str(tmp_path))
  shutil.copytree(directory / "10", directory / "20.orbax-checkpoint-tmp")  # training is writing step 20
  handler = signal.getsignal(signal.SIGTERM)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=10, max_to_keep=3, read_only=True):
    assert signal.getsignal(signal.SIGTERM) is handler
  step, state = checkpoints.restore_newest(str(tmp_path), _abstract(_state(mesh, 0)))
  assert step == 10 and int(state["step"]) == 10
  assert signal.getsignal(signal.SIGTERM) is handler
  assert (directory / "20.orbax-checkpoint-tmp").exists()


@pytest.mark.parametrize("devices", [1, 2])
def test_restores_onto_a_mesh_of_another_size(tmp_path, devices):
  with checkpoints.Checkpoints(str(tmp_path), every_steps=1, max_to_keep=1) as ckpt:
    ckpt.save(3, _state(_mesh(8), 3.5), {"next_step": 3})
  smaller = _mesh(devices)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=1, max_to_keep=1) as ckpt:
    state, _ = ckpt.restore(_abstract(_state(smaller, 0)))
  w = state["params"]["w"]
  assert w.sharding == NamedSharding(smaller, P()) and len(w.sharding.device_set) == devices
  np.testing.assert_array_equal(w, np.full((4, 3), 3.5))
  numpy_state, position, step = checkpoints.read_numpy(str(tmp_path))
  assert step == 3 and position == {"next_step": 3}
  np.testing.assert_array_equal(numpy_state["params"]["w"], np.full((4, 3), 3.5))


def test_sigterm_in_a_single_process_saves_the_current_step_then_gives_the_signal_back(tmp_path):
  mesh = _mesh(8)
  before = signal.getsignal(signal.SIGTERM)
  ckpt = checkpoints.Checkpoints(str(tmp_path), every_steps=100, max_to_keep=3)
  watch = preemption.Watch(0)
  try:
    assert not watch.reached(7)
    os.kill(os.getpid(), signal.SIGTERM)  # caught: the flag is set, nothing dies
    assert watch.reached(7)
    assert ckpt.save(7, _state(mesh, 7), {"next_step": 7}, force=watch.reached(7))  # off the 100-step interval
  finally:
    ckpt.close()
    watch.close()
  assert signal.getsignal(signal.SIGTERM) == before
  assert checkpoints.latest_step(str(tmp_path)) == 7


def test_read_numpy_of_an_empty_workdir_is_a_user_error(tmp_path):
  with pytest.raises(UserError, match="holds no complete checkpoint"):
    checkpoints.read_numpy(str(tmp_path))


def _config_json(**overrides):
  return json.loads(smoke_config(**overrides).to_json_best_effort())


def test_only_step_count_cadence_checkpoint_eval_orbit_and_eval_samples_may_change():
  saved = _config_json()
  allowed = _config_json(**{"train.num_steps": 999, "train.log_every": 1, "train.image_every": 0,
                            "checkpoint.every_steps": 7, "eval.max_views": 1, "render.eval_samples": 48})
  assert workdir_files.incompatible_fields(saved, allowed) == []
  changed = _config_json(**{"model.hashgrid.num_levels": 2, "data.image_size": 16, "train.seed": 3,
                            "train.num_steps": 999, "render.num_samples": 24})
  assert workdir_files.incompatible_fields(saved, changed) == ["data.image_size", "model.hashgrid.num_levels",
                                                             "render.num_samples", "train.seed"]


def test_resuming_a_workdir_of_another_shape_names_the_fields(tmp_path):
  saved = _config_json()
  workdir_files.write_config(str(tmp_path), saved)
  changed = _config_json(**{"model.hashgrid.hidden_width": 8})
  workdir_files.check_compatible(str(tmp_path), changed, has_checkpoint=False)  # no checkpoint yet: anything goes
  with checkpoints.Checkpoints(str(tmp_path), every_steps=1, max_to_keep=1) as ckpt:
    ckpt.save(1, _state(_mesh(8), 1), {"next_step": 1})
  with pytest.raises(UserError, match=r"model\.hashgrid\.hidden_width \(16 -> 8\)"):
    workdir_files.check_compatible(str(tmp_path), changed, has_checkpoint=True)
  workdir_files.check_compatible(str(tmp_path), _config_json(**{"train.num_steps": 5}), has_checkpoint=True)


def test_restoring_a_state_of_another_shape_is_one_sentence_and_keeps_the_checkpoint(tmp_path):
  """A workdir written by other model code (same config, other parameter tree) is refused with the
  differing leaves named, instead of orbax's stack trace; the checkpoint stays."""
  mesh = _mesh(2)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=1, max_to_keep=1) as ckpt:
    ckpt.save(1, _state(mesh, 1), {"next_step": 1})
  other = _state(mesh, 1)
  other["params"]["w"] = jax.device_put(jnp.zeros((4, 2)), NamedSharding(mesh, P()))
  other["params"]["extra"] = jax.device_put(jnp.zeros(3), NamedSharding(mesh, P()))
  with pytest.raises(UserError, match=r"step 1 .*another shape .*\(params/extra: new; "
                                      r"params/w: \(4, 3\) saved, \(4, 2\) now\).*new --workdir"):
    checkpoints.restore_newest(str(tmp_path), _abstract(other))
  _, state = checkpoints.restore_newest(str(tmp_path), _abstract(_state(mesh, 0)))  # the checkpoint is intact
  np.testing.assert_array_equal(state["params"]["w"], np.ones((4, 3)))
  assert checkpoints.state_differences(checkpoints.checkpoint_dir(str(tmp_path)) / "1" / "state",
                                       _abstract(_state(mesh, 0))) == ""


def test_a_config_json_this_version_does_not_know_is_one_sentence(tmp_path):
  """The viewer, the exports and --mode=eval read a run's config.json: one that lacks a field (written before
  the field was added) reads back with it at its default, what that run did (as a resume counts it); one
  holding a field this version does not know (another nerfpod version's) is refused in one sentence naming
  the field; a whole one reads as written."""
  config = _config_json()
  (tmp_path / "config.json").write_text(json.dumps(config))
  assert workdir_files.read_config(str(tmp_path)).train.seed == config["train"]["seed"]
  config["eval"]["lpips_net"] = "vgg"
  del config["eval"]["pose_fit"], config["train"]["coarse_to_fine"]
  (tmp_path / "config.json").write_text(json.dumps(config))
  read = workdir_files.read_config(str(tmp_path))
  assert read.eval.pose_fit == schema.FIELDS["eval.pose_fit"].default == "refined"
  assert tuple(read.train.coarse_to_fine) == schema.FIELDS["train.coarse_to_fine"].default
  assert read.eval.lpips_net == "vgg" and read.train.seed == config["train"]["seed"]  # what it holds wins
  config["eval"]["lpips_network"] = "alex"
  (tmp_path / "config.json").write_text(json.dumps(config))
  with pytest.raises(UserError, match=r"config.json holds a config this nerfpod version refuses \(.*eval.lpips_network"
                                      r".*\); use the nerfpod version that trained it."):
    workdir_files.read_config(str(tmp_path))


def test_a_workdir_whose_checkpoints_cannot_be_listed_is_one_sentence(tmp_path, monkeypatch):
  """An unreachable bucket (here: a listing that fails) is one sentence for every caller of latest_step:
  the run's start-up, the viewer and the exports alike."""
  import orbax.checkpoint as ocp
  checkpoints.checkpoint_dir(str(tmp_path)).mkdir(parents=True)
  def unreachable(_):
    raise OSError("503 Service Unavailable\nretry later")
  monkeypatch.setattr(ocp.path.step, "checkpoint_steps", unreachable)
  with pytest.raises(UserError, match=r"could not list the checkpoints of .* \(503 Service Unavailable retry "
                                      r"later\); check the --workdir path"):
    checkpoints.latest_step(str(tmp_path))


def test_abandoned_orbax_reads_are_quiet_and_other_reports_are_not(caplog):
  """What a failed restore leaves behind (orbax's other reads, failing in turn) is not reported; the same
  reports of anything else still are."""
  import logging
  import types
  seen = []
  from nerfpod.workdir import quiet
  hook = quiet.quiet_abandoned_reads(seen.append)
  def coroutine_of(filename):
    return types.SimpleNamespace(cr_code=types.SimpleNamespace(co_filename=filename))
  orbax_file = f"{os.sep}site-packages{os.sep}orbax{os.sep}checkpoint{os.sep}serialization.py"
  hook(types.SimpleNamespace(exc_value=None, exc_traceback=None, object=coroutine_of(orbax_file)))
  mine = types.SimpleNamespace(exc_value=None, exc_traceback=None, object=coroutine_of("/home/me/mine.py"))
  hook(mine)
  assert seen == [mine]
  # A task that failed, and one still pending at exit: each line names its coroutine's file.
  for report in ("Task exception was never retrieved\nfuture: <Task finished coro=<async_deserialize() done, "
                 "defined at {where}:394>>",
                 "Task was destroyed but it is pending!\ntask: <Task pending coro=<async_deserialize() running "
                 "at {where}:400>>"):
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="asyncio"):
      for where in (orbax_file, "/home/me/mine.py"):
        logging.getLogger("asyncio").error(report.format(where=where))
    assert [r.getMessage().count("mine.py") for r in caplog.records] == [1], report
  # A future gathering several reads names no file: its exception's traceback (orbax re-raises tensorstore's
  # error from its own code) tells whose it was.
  caplog.clear()
  def raised_in(filename):
    namespace = {}
    exec(compile("def read():\n  raise Exception('Encountered error while reading array index')", filename,
                 "exec"), namespace)
    try:
      try:
        raise ValueError("OUT_OF_RANGE: Requested byte range is not valid")
      except ValueError as cause:
        raise namespace["read"]() from cause
    except Exception as error:  # pylint: disable=broad-except
      return error
  with caplog.at_level(logging.ERROR, logger="asyncio"):
    for where in (orbax_file, "/home/me/mine.py"):
      error = raised_in(where)
      logging.getLogger("asyncio").error(
          f"_GatheringFuture exception was never retrieved\nfuture: <_GatheringFuture finished "
          f"exception={error!r}>", exc_info=(type(error), error, error.__traceback__))
  assert [r.exc_info[2].tb_next.tb_frame.f_code.co_filename for r in caplog.records] == ["/home/me/mine.py"]
  # A future tensorstore failed from its C++ code has no traceback: a status-code message is one of its reads.
  caplog.clear()
  with caplog.at_level(logging.ERROR, logger="asyncio"):
    for error in (ValueError('OUT_OF_RANGE: Error reading "params.w/0.0" in OCDBT database'),
                  ValueError("could not convert 'x'"), raised_in("/home/me/mine.py")):
      logging.getLogger("asyncio").error(f"Future exception was never retrieved\nfuture: <Future finished "
                                         f"exception={error!r}>", exc_info=(type(error), error, error.__traceback__))
  assert [str(r.exc_info[1]) for r in caplog.records] == [
      "could not convert 'x'", "Encountered error while reading array index"]


def test_a_read_only_manager_is_quiet_by_its_settings_and_other_warnings_pass(tmp_path, caplog, monkeypatch):
  """A read-only orbax manager with orbax's default options warns that it is read-only and that it overrides
  its interval (orbax 0.12.8, constraints.txt). nerfpod's readers (eval, render, the viewer, the exports) give
  it no setting to override and open it with orbax's logger passing errors only, so no such warning reaches
  the output with no filter installed, while any other warning of the same logger still passes. The quieting
  nerfpod still does by filters is installed once however often the entry points ask."""
  import logging

  import orbax.checkpoint as ocp
  from nerfpod.workdir import quiet
  absl_log = logging.getLogger("absl")
  monkeypatch.setattr(absl_log, "filters", [])  # the library as it is, before nerfpod configures it
  monkeypatch.setattr("sys.unraisablehook", __import__("sys").unraisablehook)
  mesh = _mesh(1)
  with checkpoints.Checkpoints(str(tmp_path), every_steps=1, max_to_keep=1) as ckpt:
    ckpt.save(1, _state(mesh, 1), {"next_step": 1})

  def warnings(action) -> list[str]:
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="absl"):
      action()
      absl_log.warning("a warning of another kind")
    return [r.getMessage() for r in caplog.records if r.name == "absl"]

  def orbax_defaults():
    options = ocp.CheckpointManagerOptions(read_only=True)
    ocp.CheckpointManager(checkpoints.checkpoint_dir(str(tmp_path)), options=options,
                          item_names=("state", "data")).close()
  level = absl_log.level
  said = warnings(orbax_defaults)
  assert any(m.startswith("Given directory is read only") for m in said), said
  assert any(m.startswith("CheckpointManagerOptions.read_only=True, setting") for m in said), said
  assert warnings(lambda: checkpoints.restore_newest(str(tmp_path), _abstract(_state(mesh, 0)))) == [
      "a warning of another kind"]
  assert absl_log.level == level  # (given back)
  quiet.quiet_library_reports()
  quiet.quiet_library_reports()  # a second call installs nothing twice
  assert [type(f).__name__ for f in absl_log.filters] == ["_DiskFullIsReported", "_StorageFailureIsReported"]


def test_the_orbax_words_and_names_other_tests_look_for_are_still_orbaxs(tmp_path, caplog, monkeypatch):
  """Some tests check that an orbax report is absent (tests/test_main.py: "Type handler registry"; the rotation
  test above and tests/test_chaos.py: "Metadata file does not exist"), and some find a save under way by the
  name of orbax's temporary folder (".orbax-checkpoint-tmp": the cut-off save tests above, test_chaos._saving,
  checkpoints.remove_cut_off_saves). Against an orbax that words or names them otherwise those would pass
  while seeing nothing; here orbax 0.12.8 (constraints.txt) is seen writing each, so such an orbax fails
  here instead."""
  import logging

  from etils import epath
  import orbax.checkpoint as ocp
  from orbax.checkpoint._src.metadata import checkpoint as metadata_lib
  from orbax.checkpoint._src.path import atomicity
  from orbax.checkpoint._src.serialization import type_handler_registry
  absl_log = logging.getLogger("absl")
  monkeypatch.setattr(absl_log, "filters", [])  # the library as it is, before nerfpod configures it

  def warnings(action) -> str:
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="absl"):
      action()
    return "\n".join(r.getMessage() for r in caplog.records if r.name == "absl")

  # What overriding jax.Array's handler (as checkpoints.py does, quieted there) says.
  registry = type_handler_registry.create_type_handler_registry(
      (jax.Array, ocp.type_handlers.ArrayHandler()))
  said = warnings(lambda: registry.add(jax.Array, ocp.type_handlers.ArrayHandler(use_replica_parallel=False),
                                       override=True))
  assert said.startswith("Type handler registry"), said
  # What reading a step folder without its metadata says.
  store = metadata_lib.metadata_store(enable_write=False)
  said = warnings(lambda: store.read(tmp_path / "_CHECKPOINT_METADATA"))
  assert said.startswith("Metadata file does not exist"), said
  # The temporary folder of a save of step 20 under way, as orbax names it: what nerfpod clears.
  (directory := checkpoints.checkpoint_dir(str(tmp_path))).mkdir(parents=True)
  temporary = atomicity.AtomicRenameTemporaryPath.from_final(epath.Path(directory / "20")).get()
  assert temporary.name.startswith("20.orbax-checkpoint-tmp"), temporary
  temporary.mkdir()
  assert checkpoints.remove_cut_off_saves(str(tmp_path)) == [temporary.name] and not temporary.exists()
