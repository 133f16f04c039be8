"""The default job: the built-in procedural scene, sized to train, evaluate and render in minutes on a CPU.

100x100 images of the procedural scene; the hash-grid field (8 levels of 2^16 rows up to 256 cells a side,
32-unit MLPs) with one proposal round of 32 intervals, then 16 samples per ray for the field; 1,500 steps of
1,024 rays, Adam from 1e-2 to 1e-3; held-out PSNR, SSIM and LPIPS on the test split, then a 120-frame orbit.

Every field, its default (these are the default job's values), the values it may hold and what it means are
declared once, in nerfpod/schema.py's FIELDS; `python -m nerfpod.schema` prints them all as their
--config.section.name=value overrides. A new field is declared there, not here.

Every other config starts from this one; the real captures' configs (capture.py, llff.py) then apply
`for_real_capture`. Argument: `smoke` shrinks everything to seconds (tests, CI), as `shrink_for_smoke` does.
"""
import ml_collections

from nerfpod import config_util, schema


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  args = config_util.parse_arg(arg, smoke=False)
  c = schema.defaults()  # every field at its default: the default job as it is
  if args["smoke"]:
    shrink_for_smoke(c)
  return c


def shrink_for_smoke(c: ml_collections.ConfigDict) -> None:
  """Shrinks any config to seconds (tests, CI): tiny images, models, batches, runs, evals and orbits."""
  c.data.image_size = 32
  c.data.downscale = max(c.data.downscale, 8) if c.data.kind == "blender" else c.data.downscale
  c.model.mlp.depth, c.model.mlp.width, c.model.mlp.skips = 3, 32, (1,)
  c.model.hashgrid.num_levels = 4
  c.model.hashgrid.log2_table_size = 12
  c.model.hashgrid.max_resolution = 64
  c.model.hashgrid.hidden_width = 16
  c.model.hashgrid.geo_features = 7
  c.model.proposal.num_levels = 2
  c.model.proposal.log2_table_size = 10
  c.model.proposal.max_resolution = 32
  c.model.proposal.hidden_width = 8
  c.render.num_samples = 16
  c.render.proposal_samples = tuple(min(n, 16) for n in c.render.proposal_samples)
  c.render.num_importance = min(c.render.num_importance, 16)
  c.train.num_steps = 20
  c.train.proposal_anneal_steps = min(c.train.proposal_anneal_steps, 10)
  c.train.batch_size = 256
  c.train.microbatches = 1
  c.train.lr_warmup_steps = 2
  c.train.log_every = 5
  c.train.image_every = 10
  c.checkpoint.every_steps = 10
  c.eval.max_views = 2
  c.eval.chunk = 1024
  c.eval.lpips_net = "none"  # PSNR and SSIM only: LPIPS's network costs each short run more than its steps
  c.eval.pose_steps = 5      # (runs with pose refinement fit each held-out camera: a few steps of few rays)
  c.eval.pose_rays = 64
  c.orbit.num_frames = 4
  c.orbit.width = 16
  c.orbit.height = 16
  c.orbit.chunk = 1024


def for_real_capture(c: ml_collections.ConfigDict) -> None:
  """What the configs of real captures share (configs/capture.py, configs/llff.py): an opaque far end, view
  directions, a finer hash grid in a box of 2, proposal sampling, 512-ray batches with Adam's b2 = 0.99, a
  lower final learning rate, and for their longer runs sparser logs, images and checkpoints. Each then says what
  its kind needs."""
  c.render.last_delta = 1e10      # the original's: the last sample absorbs what is left, so a capture is opaque
                                  # (with 0, dark pixels could be fitted as see-through onto black)
  c.model.use_viewdirs = True     # real scenes shine
  g = c.model.hashgrid
  # A box of 2 covers capture.py's contracted ball of radius 2 and, in llff.py's NDC cube, the |x|, |y| up to
  # ~1.7 that offset cameras see near the near plane (horns); 1024 cells over its 4 units match ~500-pixel
  # images over the NDC cube's 2. 2^17 rows: 2^19 made each step's dense Adam update over the table dear.
  g.bound, g.log2_table_size, g.max_resolution = 2.0, 17, 1024
  c.render.proposal_samples = (64,)  # one proposal round of 64 intervals, then 32 samples for the field: on
  c.render.num_samples = 32       # horns 27.26 dB against 24.17 dB with 48 stratified samples (docs/results.md)
  c.model.proposal.num_levels, c.model.proposal.log2_table_size = 4, 12  # as tiny_fast: more rays/s
  c.train.batch_size = 512        # more updates per CPU-second than 1,024 rays, with Adam's b2 = 0.99
  c.train.adam_b2 = 0.99          # (Instant-NGP's), as tiny_fast
  c.train.lr_final = 3e-4
  c.train.log_every = 200
  c.train.image_every = 2000
  c.checkpoint.every_steps = 2000
  c.eval.chunk = c.orbit.chunk = 1024  # rays per rendering call, as blender_fast.py:cpu: on a CPU the horns'
  # spiral renders 1.0 s a frame against 1.6 s with the schema's 4,096 (caches), the same values (docs/results.md)


def for_accelerator(c: ml_collections.ConfigDict) -> None:
  """A real capture's config sized for a GPU or a TPU host (the `big` variants of capture.py and llff.py), as
  nerfacto's default sizes it: a 16-level hash grid of 2^19 rows up to 2048 cells a side with 64-unit MLPs,
  two proposal rounds (256 then 96 intervals) before 48 field samples, resampled with nerfacto's padding and
  annealing, 4,096 rays a step for 30,000 steps,
  and rendering calls of 32,768 rays (an accelerator's size: the CPU's 8,192 leave it idle between calls)."""
  g = c.model.hashgrid
  g.num_levels, g.log2_table_size, g.max_resolution = 16, 19, 2048
  g.hidden_width, g.geo_features = 64, 15
  c.model.proposal.num_levels, c.model.proposal.log2_table_size = 5, 17
  c.model.proposal.max_resolution, c.model.proposal.hidden_width = 256, 16
  c.render.proposal_samples = (256, 96)
  c.render.num_samples = 48
  # The proposal sampler's guards, nerfacto's (docs/training.md): padded and annealed resampling, and the
  # density's gradient kept above its clamp. Without them the cup collapsed on an H200 (18.5 dB held out).
  c.render.proposal_padding = 0.01
  c.train.proposal_anneal_steps = 1000
  c.model.trunc_exp = True
  c.train.batch_size = 4096
  c.train.num_steps = 30_000
  c.train.log_every = 100
  c.train.image_every = 5000
  c.checkpoint.every_steps = 5000
  c.eval.chunk = c.orbit.chunk = 32768
