"""A fast field on the Tiny NeRF data: multiresolution hash grid + small MLPs, for CPUs and small budgets.

Target (see tools/benchmark.py and the README's table): a mean held-out PSNR of 28 dB on frames 100-105
within 10 minutes on a 2-core CPU, start to finish. Arguments: `path=FILE` (the npz), `smoke` for tests.
"""
from nerfpod import config_util


def get_config(arg: str | None = None):
  args = config_util.parse_arg(arg, path="data/tiny_nerf_data.npz", smoke=False)
  default = config_util.sibling_module(__file__, "default")
  c = default.get_config()
  c.data.kind = "tiny"
  c.data.path = args["path"]      # tiny_nerf_data.npz
  c.model.use_viewdirs = True
  c.train.num_steps = 4000
  c.train.batch_size = 1024
  c.train.log_every = 100
  c.train.image_every = 1000
  c.checkpoint.every_steps = 1000
  if args["smoke"]:
    default.shrink_for_smoke(c)
  return c
