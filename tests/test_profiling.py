"""train.profile_steps: a jax.profiler trace of the chosen steps in the workdir, where TensorBoard's profile
tab (and xprof) read it."""
import pytest

from conftest import SMOKE_RUN_OVERRIDES, smoke_config
from nerfpod import schema
from nerfpod.run import modes
from nerfpod.errors import UserError


@pytest.mark.slow
def test_the_chosen_steps_are_traced_into_the_workdir_for_tensorboards_profile_tab(tmp_path, capsys):
  config = smoke_config(**dict(SMOKE_RUN_OVERRIDES, **{"train.num_steps": 6, "train.profile_steps": (3, 4),
                                                       "eval.max_views": 1}))
  modes.train_and_evaluate(config, str(tmp_path))
  traces = list((tmp_path / "plugins" / "profile").glob("*/*.xplane.pb"))
  assert len(traces) == 1, list(tmp_path.rglob("*"))  # one process: one host's file, in one run's folder
  data = traces[0].read_bytes()
  # The trace holds the train step's program (jax.jit of the shard_map of step.make_train_step's
  # `local_step`), with its XLA ops (fusions, dots).
  assert b"jit_local_step" in data and b"fusion" in data and b"dot" in data
  assert "profile of steps 3..4 written under" in capsys.readouterr().err


def test_profile_steps_is_a_range_of_steps_or_nothing():
  assert schema.FIELDS["train.profile_steps"].accepts(())
  assert schema.FIELDS["train.profile_steps"].accepts((100, 110))
  for bad in ((0, 3), (5, 2), (1, 2, 3), (1,)):
    with pytest.raises(UserError, match=r"train.profile_steps=.* must be \(\) or \(first, last\)"):
      schema.validate(smoke_config(**{"train.profile_steps": bad}))
