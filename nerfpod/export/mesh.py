"""`nerfpod export mesh`: a coloured triangle mesh (PLY, or OBJ) of the trained density, by marching cubes.

The density of the trained NeRF field is sampled on a grid of --resolution points per side over the box
[-b, b]^3 of the normalised scene (b: the hash grid's bound; --bound sets it), slab after slab over the
whole mesh's devices, and scikit-image's marching cubes (the `mesh` extra) extracts the surface where it
crosses --level (density per unit of the normalised scene). Each vertex's normal is the field's outward
normal (minus the density gradient), its colour the field's colour seen along the normal, from outside.
Vertices and normals are written in the capture's own coordinates (the inverse of the run's capture ->
scene similarity in scene.json), or in the normalised scene's with --normalized. A contracted (unbounded)
scene's mesh covers its bounded part only: the unit ball (b = 1), inside the contraction; a forward-facing
(NDC) scene is refused (its field lives in NDC space; export a point cloud). A region model (model.regions > 1)
is meshed as one field: each grid point's density is that of the region it lies in (trained.FieldQuery), so
the surface runs on across the regions' boundaries.

Before any work, --resolution is weighed against this host's available memory (memory_bytes: the n^3 grid and
marching cubes' working memory): one that cannot fit is refused in one sentence naming the largest that
would. A long export measures its field queries a second first and says its time and memory up front; the
density pass prints its progress.
"""
import os
import time

import jax
import numpy as np
from absl import flags

from nerfpod.errors import UserError
from nerfpod.export import ply, shared
from nerfpod.text import byte_size, duration

ABOUT = "a coloured triangle mesh (PLY or OBJ) by marching cubes on the density"
DEFAULT_OUT = "mesh.ply"
MISSING = "mesh export needs scikit-image (marching cubes): pip install 'nerfpod[mesh]'"

# Marching cubes' working memory, in units of the float32 density grid it reads: skimage.measure.marching_cubes
# (Lewiner) keeps a few slices of cell data and grows its vertex and face arrays with the surface it finds.
# Measured (peak rise of the process's resident memory, and tracemalloc's peak) at N = 64, 128, 192: a smooth
# surface (a sphere) 0.5x, 0.06x, 0.02x the grid; a sphere with 1% of the grid points as isolated specks (the
# floaters of a partly trained field) 2.6x, 1.2x, 0.8x; pure noise (a surface in every cell) 42x, 43x, 45x.
# 2x covers every trained field measured and leaves room for the vertices' colours and normals queried after
# it; a field of pure noise is no scene and may still run out.
MARCHING_CUBES_FACTOR = 2.0
SLAB_POINTS = 2_000_000      # grid points per density query (one slab of x-planes)
SLAB_BYTES_PER_POINT = 64    # a slab's points (float64, then float32 for the devices) and their densities
MEMORY_SHARE = 0.75          # of this host's available memory, the most an export may plan to take
# Marching cubes on one core: 18-25 million grid points a second (measured at N = 128, 256 on a 2-core test machine).
MARCHING_CUBES_POINTS_PER_SECOND = 20e6
SAY_ESTIMATE_SECONDS = 30.0  # an export expected to take longer says its time up front


def define_flags(flag_values) -> None:
  flags.DEFINE_integer("resolution", 256, "Grid points per side of the box.", flag_values=flag_values)
  flags.DEFINE_float("level", 25.0, "Density of the surface, per unit of the normalised scene.",
                     flag_values=flag_values)
  flags.DEFINE_float("bound", 0.0, "The box [-b, b]^3 of the normalised scene (0: the field's box; 1 if "
                     "contracted).", flag_values=flag_values)


def check(args) -> None:
  if not 8 <= args.resolution <= 2048:
    raise UserError(f"--resolution={args.resolution} must be between 8 and 2048 grid points per side.")
  if not args.level > 0:
    raise UserError(f"--level={args.level} must be a positive density.")
  if not str(args.out or DEFAULT_OUT).lower().endswith((".ply", ".obj")):
    raise UserError(f"--out={args.out} must end in .ply or .obj (the mesh's format).")
  try:
    import skimage.measure  # noqa: F401
  except ImportError:
    raise UserError(f"{MISSING}.") from None
  check_memory(args.resolution)


def memory_bytes(n: int) -> int:
  """What a mesh export at --resolution=n takes at its peak: the n^3 float32 density grid, marching cubes'
  working memory (MARCHING_CUBES_FACTOR grids) and one slab of query points."""
  return int(4 * n ** 3 * (1 + MARCHING_CUBES_FACTOR) + SLAB_BYTES_PER_POINT * min(n ** 3, max(n * n, SLAB_POINTS)))


def available_memory_bytes() -> int:
  """This host's memory available to a new allocation (MemAvailable: free plus reclaimable caches), or the
  free pages where /proc/meminfo is not."""
  try:
    with open("/proc/meminfo") as meminfo:
      for line in meminfo:
        if line.startswith("MemAvailable:"):
          return int(line.split()[1]) * 1024
  except OSError:
    pass
  return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def largest_resolution(budget: float) -> int:
  """The largest n whose export fits in `budget` bytes (0 if not even the smallest does)."""
  n = int(round((max(budget, 0) / (4 * (1 + MARCHING_CUBES_FACTOR))) ** (1 / 3))) + 1
  while n > 0 and memory_bytes(n) > budget:
    n -= 1
  return n


def check_memory(n: int) -> None:
  """Refuses, before any work, a --resolution whose grid and marching cubes would not fit in this host's
  available memory (MEMORY_SHARE of it), naming the largest one that would."""
  need, available = memory_bytes(n), available_memory_bytes()
  if need <= MEMORY_SHARE * available:
    return
  fits = largest_resolution(MEMORY_SHARE * available)
  way_out = (f"pass --resolution={fits} or less" if fits >= 8
             else "free some memory (not even --resolution=8 fits)")
  raise UserError(f"--resolution={n} would take about {byte_size(need)} of memory (its {n}^3 density grid and "
                  f"marching cubes' working memory) but this host has {byte_size(available)} available; {way_out}.")


def _queries_per_second(query, points_Nx3) -> float:
  """Field queries a second on this host's devices, timed on one query of `points_Nx3` after a first that
  compiles the program (the density pass uses that same program and chunk size)."""
  query.density(points_Nx3)
  started = time.perf_counter()
  query.density(points_Nx3)
  return len(points_Nx3) / max(time.perf_counter() - started, 1e-9)


def export(args, trained: shared.Trained, out: str) -> dict:
  from skimage import measure  # the mesh extra
  config = trained.config
  if config.render.space == "ndc":
    raise UserError("a forward-facing scene's field lives in NDC space (render.space=ndc), where no mesh of the "
                    "world can be cut; export a point cloud instead (nerfpod export pointcloud).")
  bound = shared.box_bound(trained, args.bound)
  n = args.resolution
  axis = np.linspace(-bound, bound, n)
  query = shared.FieldQuery(trained, max(config.eval.chunk, 65536))
  density = np.empty((n, n, n), np.float32)
  plane = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
  slabs = max(1, min(n, SLAB_POINTS // (n * n)))  # x-planes per query: ~2M points
  slab_of = lambda xs: np.concatenate([np.concatenate([np.full((len(plane), 1), x), plane], 1) for x in xs])
  if n ** 3 >= 8 * query.chunk:  # worth a measurement: one chunk of the first slab, timed once compiled
    rate = _queries_per_second(query, slab_of(axis[:slabs])[:query.chunk])
    seconds = n ** 3 / rate + n ** 3 / MARCHING_CUBES_POINTS_PER_SECOND
    if seconds >= SAY_ESTIMATE_SECONDS:
      shared.say(f"mesh: a {n}^3 grid ({n ** 3:.3g} field queries at {rate:.3g} a second measured, then marching "
                 f"cubes) takes about {duration(seconds)} and {byte_size(memory_bytes(n))} of memory")
  progress = shared.Progress("mesh: density", n, "planes")
  started = time.perf_counter()
  for start in range(0, n, slabs):
    xs = axis[start:start + slabs]
    density[start:start + len(xs)] = query.density(slab_of(xs)).reshape(len(xs), n, n)
    done, spent = start + len(xs), time.perf_counter() - started
    progress.update(done, f", about {duration(spent * (n - done) / done)} left" if done < n else "")
  if n ** 3 / MARCHING_CUBES_POINTS_PER_SECOND >= SAY_ESTIMATE_SECONDS / 3:
    shared.say(f"mesh: marching cubes on the {n}^3 grid (about "
               f"{duration(n ** 3 / MARCHING_CUBES_POINTS_PER_SECOND)}, one core)")
  if not np.isfinite(density).all():
    raise UserError(f"the field's density is not finite at some grid points; the checkpoint of step {trained.step} "
                    f"is damaged or diverged.")
  if not density.min() < args.level < density.max():
    raise UserError(f"the density never crosses --level={args.level:g} in the box [-{bound:g}, {bound:g}]^3 (it "
                    f"spans {density.min():.3g} to {density.max():.3g}); pass a --level in that range.")
  spacing = 2 * bound / (n - 1)
  verts, faces, _, _ = measure.marching_cubes(density, level=args.level, spacing=(spacing,) * 3,
                                              gradient_direction="ascent")  # denser inside
  verts = verts - bound
  _, _, normals = query.query(verts)  # the field's own outward normals at the vertices
  rgb, _, _ = query.query(verts, -normals)  # seen from outside, looking along -normal
  comments = [f"nerfpod export mesh: step {trained.step} of {trained.workdir}",
              f"coordinates: {'normalized scene' if args.normalized else 'capture'}",
              f"marching cubes: {n}^3 grid over [-{bound:g}, {bound:g}]^3 (normalized), density level {args.level:g}"]
  if config.render.space == "contract":
    comments.append("contracted scene: the bounded part only (the unit ball left as it is by the contraction)")
    shared.say("mesh: a contracted scene: the mesh covers its bounded part only (the box [-1, 1]^3 of the "
               "normalised scene; --bound to change)")
  verts_out = trained.points_out(verts, args.normalized)
  normals_out = trained.directions_out(normals, args.normalized)
  if jax.process_index() == 0:
    write = ply.write_obj if str(out).lower().endswith(".obj") else ply.write_ply
    write(out, verts_out, rgb, normals_out, faces, comments=comments)
  shared.say(f"mesh: {len(verts)} vertices, {len(faces)} triangles -> {out}")
  return {"vertices": len(verts), "faces": len(faces)}
