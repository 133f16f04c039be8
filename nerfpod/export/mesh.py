"""`nerfpod export mesh`: a coloured triangle mesh (PLY, or OBJ) of the trained density, by marching cubes.

The density of the trained NeRF field is sampled on a grid of --resolution points per side over the box
[-b, b]^3 of the normalised scene (b: the hash grid's bound; --bound sets it), slab after slab over the
whole mesh's devices, and scikit-image's marching cubes (the `mesh` extra) extracts the surface where it
crosses --level (density per unit of the normalised scene). Each vertex's normal is the field's outward
normal (minus the density gradient), its colour the field's colour seen along the normal, from outside.
Vertices and normals are written in the capture's own coordinates (the inverse of the run's capture ->
scene similarity in scene.json), or in the normalised scene's with --normalized. A contracted (unbounded)
scene's mesh covers its bounded part only: the unit ball (b = 1), inside the contraction; a forward-facing
(NDC) scene is refused (its field lives in NDC space; export a point cloud).
"""
import jax
import numpy as np
from absl import flags

from nerfpod.errors import UserError
from nerfpod.export import ply, trained as trained_lib

ABOUT = "a coloured triangle mesh (PLY or OBJ) by marching cubes on the density"
DEFAULT_OUT = "mesh.ply"
MISSING = "mesh export needs scikit-image (marching cubes): pip install 'nerfpod[mesh]'"


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


def export(args, trained: trained_lib.Trained, out: str) -> dict:
  from skimage import measure  # the mesh extra
  config = trained.config
  if config.render.space == "ndc":
    raise UserError("a forward-facing scene's field lives in NDC space (render.space=ndc), where no mesh of the "
                    "world can be cut; export a point cloud instead (nerfpod export pointcloud).")
  bound = trained_lib.box_bound(trained, args.bound)
  n = args.resolution
  axis = np.linspace(-bound, bound, n)
  query = trained_lib.FieldQuery(trained, max(config.eval.chunk, 65536))
  density = np.empty((n, n, n), np.float32)
  plane = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
  slabs = max(1, min(n, 2_000_000 // (n * n)))  # x-planes per query: ~2M points
  progress = trained_lib.Progress("mesh: density", n, "planes")
  for start in range(0, n, slabs):
    xs = axis[start:start + slabs]
    points = np.concatenate([np.concatenate([np.full((len(plane), 1), x), plane], 1) for x in xs])
    density[start:start + len(xs)] = query.density(points).reshape(len(xs), n, n)
    progress.update(start + len(xs))
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
    trained_lib.say("mesh: a contracted scene: the mesh covers its bounded part only (the box [-1, 1]^3 of the "
                    "normalised scene; --bound to change)")
  verts_out = trained.points_out(verts, args.normalized)
  normals_out = trained.directions_out(normals, args.normalized)
  if jax.process_index() == 0:
    write = ply.write_obj if str(out).lower().endswith(".obj") else ply.write_ply
    write(out, verts_out, rgb, normals_out, faces, comments=comments)
  trained_lib.say(f"mesh: {len(verts)} vertices, {len(faces)} triangles -> {out}")
  return {"vertices": len(verts), "faces": len(faces)}
