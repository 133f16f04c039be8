"""The Tiny NeRF tutorial ("Implementing NeRF in JAX") on its own data: tiny_nerf_data.npz, 100x100 lego.

Its model and sampling: positional encoding with 6 frequencies, an 8x256 ReLU MLP whose input rejoins after
layer 4, no view directions, 256 stratified samples between 2 and 6, Adam at a constant 5e-4, 10,000 rays a
step (one 100x100 image's worth, here drawn from all training images). Argument: `smoke` for tests.
`--config.model.num_frequencies=0` reproduces the tutorial's comparison without positional encoding.
"""
from nerfpod import config_util


def get_config(arg: str | None = None):
  args = config_util.parse_arg(arg, smoke=False)
  default = config_util.sibling_module(__file__, "default")
  c = default.get_config()
  c.data.kind = "tiny"
  c.data.path = "data/tiny_nerf_data.npz"  # the tutorial's npz (download: see docs/data.md)
  c.data.pixel_center = 0.0       # the tutorial's rays pass through pixel corners
  c.model.field = "mlp"           # the default MLP is the tutorial's: PE L=6, 8x256, skip at layer 4
  c.render.num_samples = 256
  c.render.proposal_samples = ()  # the tutorial's stratified sampling
  c.render.last_delta = 1e10      # the tutorial's infinite last interval
  c.train.num_steps = 1000
  c.train.batch_size = 10_000
  c.train.microbatches = 50       # 200 rays x 256 samples at a time: faster on a CPU than bigger slices
                                  # (their activations fit the caches better)
  c.train.lr_init = 5e-4
  c.train.lr_final = 5e-4         # the tutorial's constant learning rate
  c.train.lr_warmup_steps = 0
  c.train.adam_eps = 1e-8
  c.train.log_every = 25
  c.train.image_every = 250
  c.checkpoint.every_steps = 250
  if args["smoke"]:
    default.shrink_for_smoke(c)
  return c
