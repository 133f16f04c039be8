"""The default job: the built-in procedural scene, sized to train, evaluate and render in minutes on a CPU.

Every other config starts from this one; the real captures' configs (capture.py, llff.py) then apply
`for_real_capture`. Argument: `smoke` shrinks everything to seconds (tests, CI), as `shrink_for_smoke` does.
"""
import ml_collections

from nerfpod import config_util


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  args = config_util.parse_arg(arg, smoke=False)
  c = ml_collections.ConfigDict()

  c.data = ml_collections.ConfigDict()
  c.data.kind = "procedural"      # scene format: 'procedural' (built in), 'tiny' (npz), 'blender' (folder),
  #                                 captures 'llff', 'colmap', 'nerfstudio', or 'auto' (told by data.path's files)
  c.data.path = ""                # the npz file or scene folder; unused by the procedural scene
  c.data.downscale = 1            # integer factor the images are shrunk by (captures: images_N/ where it exists)
  c.data.image_size = 100         # procedural scene: width and height of its images, pixels
  c.data.pixel_center = 0.5       # where in its pixel a ray passes: 0.5 centre, 0.0 corner (original code)
  c.data.llffhold = 8             # captures: every Nth frame (from the first) is held out as test and val
  c.data.orient = "auto"          # captures' rotation: 'llff' avg camera, 'up' mean up -> +z, 'pca', 'none'
  c.data.center = "auto"          # captures' origin: 'focus' (what cameras look at), 'poses' (their mean), 'none'
  c.data.scale = 0.0              # captures' scale factor; 0: LLFF near bound at 1/0.75, else farthest camera at 1
  c.data.space = "auto"           # 'object', 'forward_facing' (LLFF's default), 'unbounded' (COLMAP/nerfstudio's)
  c.data.shards = 1               # training frames split into this many shards (frame i -> i mod shards); each
  #                                 host reads only its own: a multiple of every host count the run may use
  c.data.host_memory_gib = 0.0    # images a host may hold (its shards + held-out), GiB; 0: half its memory

  c.model = ml_collections.ConfigDict()
  c.model.field = "hashgrid"      # 'mlp' (NeRF's) or 'hashgrid' (Instant-NGP's encoding + small MLPs)
  c.model.use_viewdirs = False    # feed the view direction to the colour head (view-dependent effects)
  c.model.compute_dtype = "float32"    # matmul dtype: 'bfloat16' for mixed precision on TPU/GPU
  c.model.appearance_dim = 0      # width of a learned appearance code per training frame (GLO, NeRF-W), fed to
                                  # the colour head; held-out views get the codes' mean; 0: off
  c.model.mlp = ml_collections.ConfigDict()  # NeRF's MLP: the Tiny NeRF tutorial's by default
  c.model.mlp.num_frequencies = 6  # positional-encoding frequencies L of points; 0 switches it off
  c.model.mlp.depth = 8           # number of hidden layers
  c.model.mlp.width = 256         # units per hidden layer
  c.model.mlp.skips = (4,)        # after these (0-based) layers the encoded input is concatenated again
  c.model.mlp.viewdir_frequencies = 4  # positional-encoding frequencies of view directions
  c.model.mlp.density_activation = "relu"  # 'relu' (paper), 'softplus' or 'exp'
  c.model.hashgrid = ml_collections.ConfigDict()
  c.model.hashgrid.bound = 1.5            # the field lives in the box [-bound, bound]^3, world units
  c.model.hashgrid.num_levels = 8         # resolution levels of the grid
  c.model.hashgrid.features_per_level = 2  # features stored per grid vertex and level
  c.model.hashgrid.log2_table_size = 16   # rows per level's table, log2; finer levels share them by hashing
  c.model.hashgrid.base_resolution = 16   # cells per side of the coarsest level
  c.model.hashgrid.max_resolution = 256   # cells per side of the finest level
  c.model.hashgrid.hidden_width = 32      # units of the density and colour MLPs' hidden layers
  c.model.hashgrid.geo_features = 7       # features passed from the density MLP to the colour MLP
  c.model.proposal = ml_collections.ConfigDict()  # proposal fields (render.proposal_samples): density only,
                                          # in the hash grid's box, model.hashgrid.features_per_level wide
  c.model.proposal.num_levels = 5         # resolution levels of each proposal field's hash grid
  c.model.proposal.log2_table_size = 17   # rows per level's table, log2
  c.model.proposal.base_resolution = 16   # cells per side of the coarsest level
  c.model.proposal.max_resolution = 128   # cells per side of the finest level
  c.model.proposal.hidden_width = 16      # units of its one hidden layer

  c.render = ml_collections.ConfigDict()
  c.render.num_samples = 16       # samples per ray of the NeRF field (stratified ones where no proposals)
  c.render.num_importance = 0     # extra importance samples per ray for a fine network; 0: no fine network
  c.render.eval_samples = 0       # render.num_samples of every rendering that trains nothing (evaluation,
                                  # previews, orbits, the viewer, exports): more than in training gives a finer
                                  # quadrature of the same field (docs/training.md); 0: render.num_samples
  c.render.proposal_samples = (32,)  # intervals per ray of each proposal round, e.g. (64, 32): the NeRF field
                                  # then gets render.num_samples intervals drawn from the last; (): no proposals,
                                  # render.num_samples stratified samples (docs/training.md, Speed settings)
  c.render.last_delta = 0.0       # length of the last sample's interval, world units (the paper: 1e10,
                                  # opaque at the far end: use it only with a fixed background colour)
  c.render.near = -1.0            # ray start, world units; negative: the scene's own bound
  c.render.far = -1.0             # ray end, world units; negative: the scene's own bound
  c.render.space = "euclidean"    # where the field lives: 'euclidean' (the world), 'ndc' (forward-facing
                                  # scenes: NDC rays, near/far in [0, 1]), 'contract' (unbounded: mip-NeRF
                                  # 360's contraction into the ball of radius 2)
  c.render.spacing = "linear"     # samples even in distance ('linear') or in 1/distance ('inverse')

  c.train = ml_collections.ConfigDict()
  c.train.num_steps = 1500        # optimiser steps
  c.train.batch_size = 1024       # rays per step, over all devices of all hosts
  c.train.microbatches = 1        # slices each device's rays are processed in (gradient accumulation); 0: as
                                  # few as fit the memory (XLA's analysis of the compiled step)
  c.train.lr_init = 1e-2          # learning rate at the start (after warm-up)
  c.train.lr_final = 1e-3         # learning rate at the last step (log-linear decay in between)
  c.train.lr_warmup_steps = 50    # linear warm-up from 0, steps
  c.train.adam_eps = 1e-15        # Adam's epsilon (1e-15 for hash grids, 1e-8 for MLPs)
  c.train.adam_b1 = 0.9           # Adam's decay of the gradients' mean
  c.train.adam_b2 = 0.999         # ... and of their square (Instant-NGP: 0.99, which follows a hash grid's
                                  # sparse gradients faster)
  c.train.random_background = True  # data with alpha: composite training rays on random colours
  c.train.grad_clip = 0.0         # clip the global gradient norm to this; 0: no clipping
  c.train.interlevel_weight = 1.0  # proposal sampling: weight of the interlevel loss (mip-NeRF 360 eq. 13)
  c.train.distortion_weight = 0.0  # proposal sampling: weight of the distortion loss (eq. 15); 0: off
  c.train.near_gradient_distance = 0.0  # > 0: scale the field's gradients by min(1, (distance from the ray's
                                  # origin / this)^2), world units: fewer floaters in front of the cameras; 0: off
  c.train.pose_refine = False     # learn an SE(3) correction of each training frame's pose (nerfacto's camera
                                  # optimiser); held-out frames keep their given poses
  c.train.pose_lr_init = 1e-4     # the corrections' own learning rate at the start (after warm-up); 1e-3
                                  # let them drift by degrees (docs/results.md)
  c.train.pose_lr_final = 1e-5    # ... and at the last step (log-linear decay, as train.lr_*)
  c.train.pose_weight_decay = 0.0  # decoupled weight decay of the corrections (AdamW), pulls them to zero
  c.train.seed = 0                # seeds the parameters, the ray batches and the stratified jitter
  c.train.log_every = 100         # steps between TensorBoard scalars and console lines
  c.train.image_every = 500       # steps between rendered held-out views in TensorBoard; 0: never
  c.train.max_nonfinite_steps = 20  # stop (exit 2) after this many steps in a row with a non-finite loss or
                                    # gradient; each such step is skipped, its update never reaches the state
  c.train.profile_steps = ()      # (first, last): a jax.profiler trace of these steps into the workdir
                                  # (TensorBoard's profile tab, xprof); (): none

  c.compile = ml_collections.ConfigDict()
  c.compile.cpu_ynnpack = False   # CPU: let XLA hand dots to YNNPACK (its default); off, the steps ran
                                  # faster on a 2-core CPU (docs/results.md). Ignored on TPU/GPU.
  c.compile.cpu_memory_gib = 3.0  # CPU: memory the train step may use (all of a process's simulated devices
                                  # together) when train.microbatches=0; accelerators use their own size
  c.compile.cpu_reuse_host_memory = True  # CPU: glibc's malloc keeps freed memory for the next step instead
                                  # of unmapping it (faster steps on 2 cores for more peak memory; results.md)
  c.compile.gradient_mean = "auto"  # 'ordered' (the same bits on any topology: log2(N) exchanges), 'pmean'
                                  # (one all-reduce) or 'auto' (ordered on CPU, pmean on TPU/GPU; docs/scale.md)
  c.compile.hashgrid_lookup = "auto"  # hash-grid levels: 'gather', 'matmul' (dense levels, no gather or
                                  # scatter) or 'auto' (matmul on TPU, gather elsewhere; docs/pod-compile.md)
  c.compile.matmul_max_rows = 30000  # 'matmul' applies to dense levels of at most this many rows

  c.mesh = ml_collections.ConfigDict()
  c.mesh.slices = 0               # TPU slices joined by the data-centre network (DCN) the mesh spans; 0: as
                                  # many as the devices report (1 on CPU; a count > 1 there simulates slices,
                                  # docs/scale.md#multi-slice)

  c.checkpoint = ml_collections.ConfigDict()
  c.checkpoint.every_steps = 500  # steps between (asynchronous) checkpoints; one is always saved at the end
  c.checkpoint.max_to_keep = 3    # newest checkpoints kept on disk
  c.checkpoint.preempted_exit_code = 75  # exit status after a preemption/SIGTERM/Ctrl-C saved a step (75:
                                         # EX_TEMPFAIL of sysexits.h, "try again": schedulers requeue on it)

  c.eval = ml_collections.ConfigDict()
  c.eval.split = "test"           # held-out split the final metrics are computed on
  c.eval.max_views = 0            # evaluate at most this many views of the split; 0: all
  c.eval.chunk = 4096             # rays rendered per device call, over all devices (bounds memory)
  c.eval.lpips_net = "alex"       # LPIPS network: 'alex' (the papers'), 'vgg', or 'none'; needs nerfpod[lpips]

  c.orbit = ml_collections.ConfigDict()
  c.orbit.render_after_training = True  # render the orbit (archive + videos) when training ends
  c.orbit.path = "orbit"          # camera path: 'orbit' (the tutorial's circle), 'spiral' (LLFF's, from the
                                  # capture's cameras), 'ellipse' (mip-NeRF 360's), 'file' (orbit.path_file)
  c.orbit.path_file = ""          # orbit.path=file: a nerfstudio camera_path.json (its size, fov and fps rule)
  c.orbit.num_frames = 120        # frames of the path (orbit: over one full turn; spiral: over two turns)
  c.orbit.elevation = -30.0       # degrees, the tutorial's sign: -30 is 30 degrees above the z = 0 plane
  c.orbit.radius = 4.0            # distance of the cameras from the origin they look at, world units
  c.orbit.width = 0               # frame width, pixels; 0: the eval split's
  c.orbit.height = 0              # frame height, pixels; 0: from the width with the eval split's aspect
  c.orbit.focal = 0.0             # focal length, pixels; 0: the eval split's field of view at this width
  c.orbit.chunk = 4096            # rays each host feeds per call of the whole-slice renderer (bounds memory)
  c.orbit.fps = 30.0              # frames per second of the exported videos

  c.monitor = ml_collections.ConfigDict()  # TensorBoard always; Weights & Biases as well (the wandb extra)
  c.monitor.wandb = ml_collections.ConfigDict()
  c.monitor.wandb.mode = "disabled"  # 'online', 'offline' (a local run folder for `wandb sync`) or 'disabled'
  c.monitor.wandb.project = ""    # W&B project; '': $WANDB_PROJECT, else 'nerfpod'
  c.monitor.wandb.entity = ""     # W&B user or team; '': $WANDB_ENTITY, else your default entity
  c.monitor.wandb.name = ""       # the run's display name; '': $WANDB_NAME, else the workdir's folder name
  c.monitor.wandb.tags = ()       # the run's tags, e.g. ("lego", "hashgrid"); (): $WANDB_TAGS

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
  c.train.batch_size = 256
  c.train.microbatches = 1
  c.train.lr_warmup_steps = 2
  c.train.log_every = 5
  c.train.image_every = 10
  c.checkpoint.every_steps = 10
  c.eval.max_views = 2
  c.eval.chunk = 1024
  c.eval.lpips_net = "none"  # PSNR and SSIM only: LPIPS's network costs each short run more than its steps
  c.orbit.num_frames = 4
  c.orbit.width = 16
  c.orbit.height = 16
  c.orbit.chunk = 1024


def for_real_capture(c: ml_collections.ConfigDict) -> None:
  """What the configs of real captures share (configs/capture.py, configs/llff.py): an opaque far end, view
  directions, a finer hash grid in a box of 2, proposal sampling, 512-ray batches with Adam's b2 = 0.99, a
  lower final learning rate, and for their longer runs sparser logs, images and checkpoints and bigger render
  chunks. Each then says what its kind needs."""
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
  c.eval.chunk = 8192
  c.orbit.chunk = 8192


def for_accelerator(c: ml_collections.ConfigDict) -> None:
  """A real capture's config sized for a GPU or a TPU host (the `big` variants of capture.py and llff.py), as
  nerfacto's default sizes it: a 16-level hash grid of 2^19 rows up to 2048 cells a side with 64-unit MLPs,
  two proposal rounds (256 then 96 intervals) before 48 field samples, 4,096 rays a step for 30,000 steps,
  and rendering calls of 32,768 rays (an accelerator's size: the CPU's 8,192 leave it idle between calls)."""
  g = c.model.hashgrid
  g.num_levels, g.log2_table_size, g.max_resolution = 16, 19, 2048
  g.hidden_width, g.geo_features = 64, 15
  c.model.proposal.num_levels, c.model.proposal.log2_table_size = 5, 17
  c.model.proposal.max_resolution, c.model.proposal.hidden_width = 256, 16
  c.render.proposal_samples = (256, 96)
  c.render.num_samples = 48
  c.train.batch_size = 4096
  c.train.num_steps = 30_000
  c.train.log_every = 100
  c.train.image_every = 5000
  c.checkpoint.every_steps = 5000
  c.eval.chunk = c.orbit.chunk = 32768
