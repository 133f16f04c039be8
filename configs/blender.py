"""The original NeRF on a Blender synthetic scene: `--config=configs/blender.py:scene=lego`.

The paper's model: positional encoding with 10 frequencies for points and 4 for view directions, 8x256 MLP
with the input rejoining after layer 4, hierarchical sampling with 64 coarse + 128 fine samples (two
networks), 4096 rays a step, Adam 5e-4 decaying to 5e-5. Arguments: `scene=NAME` (folder under
data/nerf_synthetic, or set --config.data.path), `smoke` for tests.
"""
from nerfpod import config_util


def get_config(arg: str | None = None):
  args = config_util.parse_arg(arg, scene="lego", smoke=False)
  default = config_util.sibling_module(__file__, "default")
  c = default.get_config()
  c.data.kind = "blender"
  c.data.path = f"data/nerf_synthetic/{args['scene']}"  # a folder with transforms_{train,val,test}.json
  c.model.field = "mlp"           # the default MLP's 8x256 trunk, skip at layer 4, 4 view frequencies
  c.model.mlp.num_frequencies = 10
  c.model.use_viewdirs = True
  c.render.num_samples = 64
  c.render.num_importance = 128
  c.render.proposal_samples = ()  # the paper's hierarchical sampling instead
  c.render.last_delta = 1e10      # the paper's infinite last interval...
  c.train.random_background = False  # ...with its fixed white background
  c.train.num_steps = 200_000
  c.train.batch_size = 4096
  c.train.microbatches = 0        # as few micro-batches as fit compile.cpu_memory_gib (CPU) or the device
  c.train.lr_init = 5e-4
  c.train.lr_final = 5e-5
  c.train.lr_warmup_steps = 0
  c.train.adam_eps = 1e-8
  c.train.log_every = 100
  c.train.image_every = 5000
  c.checkpoint.every_steps = 5000
  if args["smoke"]:
    default.shrink_for_smoke(c)
  return c
