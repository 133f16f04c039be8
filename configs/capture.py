"""An unbounded 360-degree capture, any of the three formats: `--config=configs/capture.py:path=DIR`.

DIR holds a COLMAP model (sparse/0/ + images/), a nerfstudio / instant-ngp transforms.json, or an LLFF
poses_bounds.npy (data.kind=auto tells which, and says so). The capture is oriented with +z up, centred on
what its cameras look at and scaled so the farthest camera is at distance 1; space beyond the unit ball is
contracted into the ball of radius 2 (mip-NeRF 360), which the hash grid covers, and the samples run from
0.2 to 1e6 evenly in inverse distance, so the background is modelled rather than painted on a wall; a small
proposal field places the field's 32 samples where it found matter (mip-NeRF 360's proposal sampling). The
video follows mip-NeRF 360's ellipse through the capture's cameras. Arguments: `path=DIR`, `downscale=N`
(images_N/ where it exists, else shrunk on loading; default 4), `smoke` for tests.
"""
from nerfpod import config_util


def get_config(arg: str | None = None):
  args = config_util.parse_arg(arg, path="data/capture", downscale="4", smoke=False)
  default = config_util.sibling_module(__file__, "default")
  c = default.get_config()
  default.for_real_capture(c)     # opaque, view directions, the hash grid in the ball of radius 2, ...
  c.data.kind = "auto"
  c.data.path = args["path"]      # a capture folder (or a transforms.json)
  c.data.downscale = int(args["downscale"])
  c.data.space = "unbounded"      # near 0.2, far 1e6 in the normalised frame
  c.render.space = "contract"
  c.render.spacing = "inverse"
  c.render.proposal_samples = (64,)  # one proposal round of 64 intervals in inverse distance, then
  c.render.num_samples = 32       # 32 samples for the field: cheaper steps than 48 coarse + 32 fine
  c.model.proposal.num_levels, c.model.proposal.log2_table_size = 4, 12  # as tiny_fast: more rays/s
  c.model.hashgrid.log2_table_size = 17  # 2^19 rows made each step's dense Adam update over the table dear
  c.train.num_steps = 10_000      # of 512 rays, with Adam's b2 = 0.99 (Instant-NGP's) and nerfacto's distortion
  c.train.batch_size = 512        # loss: 27.32 dB on the cup in 8 min 26 s, against 26.45 dB in 14 min 41 s
  c.train.adam_b2 = 0.99          # for 4,000 steps of 1,024 rays (docs/results.md)
  c.train.distortion_weight = 0.002
  c.orbit.path = "ellipse"        # mip-NeRF 360's, through the capture's cameras
  # Per-frame appearance codes and pose refinement stay off: on the cup and the fox both lowered held-out PSNR
  # (docs/results.md, "Appearance codes and pose refinement"); turn them on for captures that need them.
  c.model.appearance_dim = 0
  c.train.pose_refine = False
  if args["smoke"]:
    default.shrink_for_smoke(c)
  return c
