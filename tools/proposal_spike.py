"""A loss spike's effect on proposal sampling, reproduced from a trained checkpoint (docs/results.md, E1).

  python -m tools.proposal_spike --workdir=runs/cup --step=4000 --bias=5 --steps=500 --out=runs/cup_spike \
      [--set render.proposal_padding=0.01 --set model.trunc_exp=true ...]

Restores step `--step` of a run's workdir (its own config.json, with `--set` overrides: fields that do not
change the train state's shapes), raises every proposal field's density bias by `--bias` (each proposal's
density times e^bias everywhere: the weight piles up in the first intervals a ray meets, as after a spike),
trains `--steps` more steps on the run's own schedule and batches, and evaluates the held-out views into
`--out`/eval/metrics.json. Prints one JSON object: the proposal diagnostics (step.proposal_diagnostics) and the
loss terms of the first step, after the spike and every `--every` steps, and the held-out PSNR. `--bias=0`
measures the same continuation without a spike. The run's workdir is only read.
"""
import json
import sys

from absl import app, flags

flags.DEFINE_string("workdir", None, "a training run's workdir (read only)", required=True)
flags.DEFINE_integer("step", None, "the checkpoint step to start from (default: the newest)")
flags.DEFINE_float("bias", 5.0, "added to every proposal field's density bias")
flags.DEFINE_integer("steps", 500, "steps to train after the spike")
flags.DEFINE_integer("every", 50, "steps between the diagnostics printed")
flags.DEFINE_string("out", None, "where eval/metrics.json goes", required=True)
flags.DEFINE_multi_string("set", [], "FIELD=VALUE overrides of the run's config (JSON values: 0.01, true)")
FLAGS = flags.FLAGS


def spiked(params, bias: float):
  """`params` with every proposal field's density bias raised by `bias`."""
  import jax
  def raise_bias(path, leaf):
    names = [getattr(k, "key", None) for k in path]
    is_density_bias = any(str(n).startswith("proposal_") for n in names) and names[-2:] == ["density", "bias"]
    return leaf + bias if is_density_bias else leaf
  return jax.tree_util.tree_map_with_path(raise_bias, params)


def main(argv):
  del argv
  import jax
  from nerfpod import config_util, distributed, schema
  from nerfpod.run import components, evaluate, step as train_step, train_state
  from nerfpod.workdir import checkpoints, files

  config = files.read_config(FLAGS.workdir)
  config_util.override(config, **{k: json.loads(v) for k, v in (s.split("=", 1) for s in FLAGS.set)})
  schema.validate(config, jax.device_count())
  comps = components.build(config)
  reader = checkpoints.Checkpoints(FLAGS.workdir, config.checkpoint.every_steps, config.checkpoint.max_to_keep,
                                   read_only=True)
  start = FLAGS.step if FLAGS.step is not None else reader.latest_step()
  state, _ = reader.restore(comps.state_shapes, start)
  reader.close()
  state = state.replace(params=spiked(state.params, FLAGS.bias))
  step_fn = train_step.compile_for_run(comps).step
  key = train_state.rays_key(config.train.seed, comps.mesh)
  batches = comps.batches(start)
  log = []
  for step in range(start, start + FLAGS.steps):
    local = next(batches)
    assert int(local.pop("step")) == step
    state, metrics = step_fn(state, distributed.to_global(comps.mesh, local), key)
    done = step + 1 - start
    if done == 1 or done % FLAGS.every == 0:
      row = {k: float(v) for k, v in jax.device_get(metrics).items()}
      log.append(dict(step=step + 1, **row))
      print(json.dumps(log[-1]), file=sys.stderr, flush=True)
  metrics = evaluate.evaluate(comps, state.params, FLAGS.out, int(jax.device_get(state.step)))
  print(json.dumps({"workdir": FLAGS.workdir, "from_step": start, "bias": FLAGS.bias, "set": FLAGS.set,
                    "log": log, "held_out": metrics["mean"],
                    "views": [round(v["psnr"], 2) for v in metrics["views"]]}))


if __name__ == "__main__":
  app.run(main)
