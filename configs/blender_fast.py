"""The hash-grid field on a Blender synthetic scene: `--config=configs/blender_fast.py:scene=lego`.

Instant-NGP-sized grid (16 levels, 2^19 rows, up to 2048 cells a side), view directions through spherical
harmonics, 4096 rays a step, proposal sampling (64 intervals, then 24 field samples a ray; 48 in every
rendering) with nerfacto's guards. Arguments: `scene=NAME` (folder under data/nerf_synthetic, or set
--config.data.path), `cpu` sizes the job for a 2-core CPU, `smoke` for tests.

`cpu`: 100x100 images (`data.downscale=4` of 400x400 renders; `--config.data.downscale=2` for 200x200), a
CPU-sized grid, proposal sampling, 512 rays a step, 16 field samples per ray in training and 48 in every
rendering (`render.eval_samples`), evaluated on the `val` split (the shared 400x400
lego has no test split): e.g. `--config=configs/blender_fast.py:scene=lego,cpu
--config.data.path=../shared/data/lego_400`. docs/results.md has what it reaches and in how long.
"""
from nerfpod import config_util


def get_config(arg: str | None = None):
  args = config_util.parse_arg(arg, scene="lego", cpu=False, smoke=False)
  default = config_util.sibling_module(__file__, "default")
  c = default.get_config()
  c.data.kind = "blender"
  c.data.path = f"data/nerf_synthetic/{args['scene']}"  # a folder with transforms_{train,val,test}.json
  c.model.use_viewdirs = True
  g = c.model.hashgrid
  g.num_levels, g.log2_table_size, g.max_resolution = 16, 19, 2048
  g.hidden_width, g.geo_features = 64, 15
  c.train.num_steps = 30_000
  c.train.batch_size = 4096
  c.train.microbatches = 0        # as few micro-batches as fit compile.cpu_memory_gib (CPU) or the device
  c.train.lr_init, c.train.lr_final = 1e-2, 3e-4
  c.train.log_every = 100
  c.train.image_every = 2500
  c.checkpoint.every_steps = 2500
  if args["cpu"]:
    c.data.downscale = 4
    g.num_levels, g.log2_table_size, g.max_resolution = 8, 16, 256
    g.hidden_width, g.geo_features = 32, 7
    c.render.proposal_samples = (32,)  # as configs/tiny_fast.py: 32 proposal intervals, 16 for the field
    c.render.num_samples = 16
    c.model.proposal.num_levels, c.model.proposal.log2_table_size = 4, 12  # as tiny_fast: more rays/s
    c.train.num_steps = 20_000      # of 512 rays (more updates per CPU-second), with Adam's b2 = 0.99 as
    c.train.batch_size = 512        # tiny_fast: 33.03 dB on lego's val in 9 min 40 s (docs/results.md)
    c.train.adam_b2 = 0.99
    c.train.lr_init, c.train.lr_final = 1e-2, 1e-3
    c.train.image_every = 3000
    c.checkpoint.every_steps = 3000
    c.render.eval_samples = 48      # 16 field samples in training, 48 in every rendering: +0.5 dB on lego
    c.eval.chunk = c.orbit.chunk = 1024  # rays per call: smaller calls render faster on a CPU (caches)
    c.eval.split = "val"
  else:
    # Proposal sampling: one round of 64 intervals from a small proposal grid, then 24 field samples a ray in
    # training (48 in every rendering). The proposal grid's three levels (8 to 24 cells a side) are dense and
    # under compile.matmul_max_rows rows, so on a TPU (compile.hashgrid_lookup=auto) matmuls read them, not
    # gathers: the step's indexed lookups are the field's 24 samples', against 128 stratified samples before
    # (`--config.render.proposal_samples='()' --config.render.num_samples=128` and the four overrides of
    # docs/results.md "Fewer lookups" give that config back). Estimated 4.4 times the rays/s on a v5e-8 with
    # held-out quality at equal steps no lower on a CPU (docs/pod-compile.md, docs/results.md).
    c.render.proposal_samples = (64,)
    c.render.num_samples = 24
    c.render.eval_samples = 48
    p = c.model.proposal
    p.num_levels, p.base_resolution, p.max_resolution, p.log2_table_size = 3, 8, 24, 15
    # The proposal sampler's guards (configs/default.py:for_accelerator, docs/training.md): padded and annealed
    # resampling, the density's gradient kept above its clamp.
    c.render.proposal_padding = 0.01
    c.train.proposal_anneal_steps = 1000
    c.model.trunc_exp = True
  if args["smoke"]:
    default.shrink_for_smoke(c)
  return c
