"""A forward-facing LLFF capture in NDC space: `--config=configs/llff.py:scene=horns`.

The original NeRF's set-up for real forward-facing scenes (nerf_llff_data): poses_bounds.npy + images_8/
(data.downscale = 8), the capture recentred and rescaled as load_llff.py does, every 8th image held out as
test, rays mapped to NDC (near plane at 1, t' in [0, 1] runs to infinity), and the spiral camera path
through the capture's cameras for the video. The field is the hash grid, sized to the NDC cube at the
images' resolution, with view directions (real scenes shine). Sized so that the whole job, training to the
spiral's videos, runs within 30 minutes on a 2-core CPU (README, Real captures). Arguments: `scene=NAME`
(folder under data/nerf_llff_data, or set --config.data.path), `smoke` for tests.
"""
from nerfpod import config_util


def get_config(arg: str | None = None):
  args = config_util.parse_arg(arg, scene="fern", smoke=False)
  default = config_util.sibling_module(__file__, "default")
  c = default.get_config()
  c.data.kind = "llff"
  c.data.path = f"data/nerf_llff_data/{args['scene']}"  # a folder with poses_bounds.npy and images_N/
  c.data.downscale = 8            # images_8/, the original's default factor
  c.data.space = "forward_facing"
  c.render.space = "ndc"          # near/far default to the NDC cube's 0 and 1
  c.render.num_samples = 48
  c.render.proposal_samples = ()  # 48 stratified samples in NDC, as measured (README)
  c.render.last_delta = 1e10      # the original's: the last sample absorbs what is left, so a capture is opaque
                                  # (with 0, dark pixels could be fitted as see-through onto black)
  c.model.use_viewdirs = True
  g = c.model.hashgrid
  # Offset cameras see up to |x|, |y| ~ 1.7 in NDC near the near plane (horns): a box of 2 keeps all of it,
  # and 1024 cells over 4 units match the ~500-pixel images over the cube's 2. Eight levels and 32-unit MLPs
  # keep a step near the default job's cost, so 8,000 steps fit the 30-minute budget.
  g.bound, g.log2_table_size, g.max_resolution = 2.0, 19, 1024
  c.train.num_steps = 8000
  c.train.batch_size = 1024
  c.train.lr_init, c.train.lr_final = 1e-2, 3e-4
  c.train.log_every = 200
  c.train.image_every = 2000
  c.checkpoint.every_steps = 2000
  c.eval.chunk = 8192
  c.orbit.path = "spiral"         # the original's: two turns, 120 frames, looking at the focus depth
  c.orbit.width = 252             # half the images' width (504): 120 frames stay within minutes on a CPU
  c.orbit.chunk = 8192
  if args["smoke"]:
    default.shrink_for_smoke(c)
  return c
