"""A fast field on the Tiny NeRF data: multiresolution hash grid + small MLPs, for CPUs and small budgets.

Proposal sampling: one round of 32 intervals weighed by a small proposal field, then 16 for the NeRF field
(in place of 48 stratified samples: cheaper steps on a CPU that place the field's samples on the surface);
32 for every rendering after training.
Target (docs/results.md has what it reaches): 31.5 dB mean held-out PSNR on frames 100-105 at the end of a job
of at most 2 minutes (training, evaluation, the 120-frame orbit and its videos) on a 2-core CPU. For that:
batches of 512 rays (more updates per second of a CPU than 1,024), Adam's b2 = 0.99 as Instant-NGP's (+0.3 dB
at equal steps), and a proposal field of 4 levels of 2^12 rows (26% more rays/s; the proposal field only
places samples).
Arguments: `path=FILE` (the npz), `smoke` for tests.
"""
from nerfpod import config_util


def get_config(arg: str | None = None):
  args = config_util.parse_arg(arg, path="data/tiny_nerf_data.npz", smoke=False)
  default = config_util.sibling_module(__file__, "default")
  c = default.get_config()
  c.data.kind = "tiny"
  c.data.path = args["path"]      # tiny_nerf_data.npz
  c.model.use_viewdirs = True
  c.render.proposal_samples = (32,)
  c.render.num_samples = 16
  c.render.eval_samples = 32      # 32 field samples in every rendering (evaluation, orbit), 16 in training:
                                  # +0.19 dB (31.40 -> 31.59) for 7 s more of orbit
  c.model.proposal.num_levels = 4
  c.model.proposal.log2_table_size = 12
  c.train.num_steps = 4000        # the whole job (training, evaluation, orbit) within 2 minutes on 2 cores:
                                  # 3,000 until the CPU step got a fifth faster (31.04 -> 31.40 dB); 5,000
                                  # steps reach what 32 samples at evaluation give, 14 s later
  c.train.batch_size = 512
  c.train.adam_b2 = 0.99
  c.train.log_every = 100
  c.train.image_every = 1000
  c.checkpoint.every_steps = 1000
  if args["smoke"]:
    default.shrink_for_smoke(c)
  return c
