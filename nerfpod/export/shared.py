"""What the exports of a trained run share: the field and the renderer over the whole device mesh, the output
path's check, progress lines.

The workdir comes restored read-only through nerfpod.run.trained (`Trained`: DIR/config.json, the newest
checkpoint that reads back whole, scene.json's capture -> scene similarity and the capture's own
coordinates), so a user passes nothing else. Rendering and field queries span every device of every host (as
evaluation does); every process passes the same inputs and only process 0 writes files.
"""
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P

from nerfpod import distributed, storage
from nerfpod.render import renderer
from nerfpod.run.trained import Trained
from nerfpod.errors import UserError
from nerfpod.nerf import coord, fields
from nerfpod.nerf import model as nerf_model
from nerfpod.nerf import regions as nerf_regions


def say(line: str) -> None:
  """One console line, from process 0."""
  if jax.process_index() == 0:
    print(f"nerfpod: export: {line}", flush=True)


class Progress:
  """'nerfpod: export: WHAT 40/100 UNIT' lines from process 0, at most one every `seconds`, and the last."""

  def __init__(self, what: str, total: int, unit: str, seconds: float = 5.0):
    self.what, self.total, self.unit, self.seconds = what, int(total), unit, seconds
    self.started = self.shown = time.monotonic()

  def update(self, done: int, extra: str = "") -> None:
    now = time.monotonic()
    if done < self.total and now - self.shown < self.seconds:
      return
    self.shown = now
    say(f"{self.what} {done}/{self.total} {self.unit}{extra} ({now - self.started:.0f} s)")


def output_path(out: str | None, default: str, workdir: str, kind: str) -> str:
  """--out (default: WORKDIR/exports/`default`), checked writable before any work: its folder is made and a
  probe file written and removed (local paths; gs:// is left to its own errors)."""
  path = str(out) if out else str(storage.path(workdir) / "exports" / default)
  if storage.is_url(path) or jax.process_index() != 0:
    return path
  target = storage.path(path)
  folder = target if kind == "folder" else target.parent
  if target.exists() and (target.is_dir() != (kind == "folder")):
    raise UserError(f"--out={path} is an existing {'file' if kind == 'folder' else 'folder'}; pass a "
                    f"{kind} path.")
  probe = folder / f".nerfpod-export-probe-{id(path)}"
  try:
    folder.mkdir(parents=True, exist_ok=True)
    probe.write_text("")
    probe.unlink()
  except OSError as e:
    raise UserError(f"--out={path} cannot be written ({e.strerror or e}); pass a path this user may write.") from None
  return path


def box_bound(trained: Trained, bound: float) -> float:
  """Half the side of the box [-b, b]^3 (the scene's normalised frame) that exports keep: `bound` where > 0,
  else where the field lives: the hash grid's box, or the unit ball's for a contracted (unbounded) scene,
  whose field past it is the contracted background."""
  if bound > 0:
    return float(bound)
  if trained.config.render.space == "contract":
    return 1.0
  return float(trained.config.model.hashgrid.bound)


def hit_points(out: dict, origins_Nx3, directions_Nx3, space: str, min_opacity: float):
  """(points (N, 3), hit (N,) bool) where the rays of a rendering `out` end: at their expected depth given
  that they hit something (the composited depth over the opacity, as nerfstudio's expected depth), where the
  opacity reaches `min_opacity`. In NDC space the renderer's depth is already the world depth along -z."""
  acc = np.asarray(out["acc"], np.float64)
  origins, directions = np.asarray(origins_Nx3, np.float64), np.asarray(directions_Nx3, np.float64)
  if space == "ndc":
    with np.errstate(divide="ignore", invalid="ignore"):
      t = (-np.asarray(out["depth"], np.float64) - origins[:, 2]) / directions[:, 2]
  else:
    t = np.asarray(out["depth"], np.float64) / np.maximum(acc, 1e-10)
  points = origins + t[:, None] * directions
  hit = (acc >= min_opacity) & np.isfinite(points).all(1)
  return points, hit


def render_rays(trained: Trained, origins_Nx3, directions_Nx3, chunk: int) -> dict:
  """renderer.render_rays of the run's renderer over every device of every host."""
  comps = trained.comps
  return renderer.render_rays(comps.renderer, trained.params, comps.mesh, np.asarray(origins_Nx3, np.float32),
                            np.asarray(directions_Nx3, np.float32), chunk)


class FieldQuery:
  """The trained NeRF field at points (in the scene's frame; contracted first in a contracted scene), split
  over every device of every host in chunks of `chunk` points:

      density(points_Nx3) -> sigma (N,)
      query(points_Nx3, viewdirs_Nx3=None) -> rgb (N, 3), sigma (N,), normals (N, 3)

  rgb is the colour seen along the view directions (default: looking down -z), normals the outward unit
  normals (minus the density's gradient, normalised).

  A region model (model.regions = K > 1) is the stitched field: each point takes the density, colour and
  normal of the field of the region it lies in (nerf/regions.py's region_of, the rule the stitched field of
  the renderer's samples follows), so a mesh of the whole scene runs on across the regions' boundaries.
  Each device evaluates, for its share of the points, the field of each region present among them, one
  after the other (by_region); the points are put in order on the ground plane on the host first
  (ground_order), so that a device's share meets a few regions, not K."""

  def __init__(self, trained: Trained, chunk: int):
    self.trained, self.mesh = trained, trained.comps.mesh
    self.chunk = max(self.mesh.size, chunk - chunk % self.mesh.size)
    model = trained.comps.model
    field = fields.make_field(trained.config.model, model.dtype, matmul_max_rows=model.grid_matmul_max_rows,
                              materialize=model.grid_materialize)
    name, contracted = trained.field_name(), trained.config.render.space == "contract"
    self.partition = model.partition if model.regions > 1 else None
    self.boxes = model.region_boxes if model.regions > 1 else None

    bound = trained.config.model.hashgrid.bound

    def apply(field_params, points, viewdirs, codes, box):
      # A region's field sees its own box mapped onto the field's (nerf_regions.to_box), as in rendering.
      points = points if box is None else nerf_regions.to_box(points, *box, bound)
      return field.apply({"params": field_params}, coord.contract(points) if contracted else points, viewdirs,
                         *codes)

    def density(field_params, points, viewdirs, codes, box=None):
      return (apply(field_params, points, viewdirs, codes, box)[1],)

    def full(field_params, points, viewdirs, codes, box=None):
      # The normals are the world density's: the box map is inside what is differentiated.
      sigma, pullback = jax.vjp(lambda p: apply(field_params, p, viewdirs, codes, box)[1], points)
      (gradient,) = pullback(jnp.ones_like(sigma))
      normals = -gradient / jnp.maximum(jnp.linalg.norm(gradient, axis=-1, keepdims=True), 1e-12)
      return apply(field_params, points, viewdirs, codes, box)[0], sigma, normals

    def local(fn):
      def run(params, points, viewdirs):
        # With appearance codes, the colour is the mean code's, as every held-out rendering's (nerf/model.py).
        codes = params["params"].get("appearance")
        codes = () if codes is None else (jnp.broadcast_to(codes.mean(0), points.shape[:-1] + codes.shape[1:]),)
        if self.partition is None:
          return fn(params["params"][name], points, viewdirs, codes)
        return by_region(fn, params["params"][nerf_model.REGIONS][name], self.partition, points, viewdirs, codes,
                         self.boxes)
      return run

    axis = distributed.batch_axes(self.mesh)  # every axis of the mesh (slices too)
    program = lambda fn, outputs: jax.jit(jax.shard_map(local(fn), mesh=self.mesh, in_specs=(P(), P(axis), P(axis)),
                                                        out_specs=(P(axis),) * outputs))
    self._density = program(density, 1)
    self._full = program(full, 3)

  def density(self, points_Nx3) -> np.ndarray:
    return self._map(self._density, points_Nx3, None)[0]

  def query(self, points_Nx3, viewdirs_Nx3=None):
    return self._map(self._full, points_Nx3, viewdirs_Nx3)

  def _map(self, program, points_Nx3, viewdirs_Nx3):
    points = np.asarray(points_Nx3, np.float32).reshape(-1, 3)
    viewdirs = (np.broadcast_to(np.float32([0.0, 0.0, -1.0]), points.shape) if viewdirs_Nx3 is None
                else np.asarray(viewdirs_Nx3, np.float32).reshape(-1, 3))
    if self.partition is None or len(points) == 0:
      return self._map_in_order(program, points, viewdirs)
    order = ground_order(points)  # neighbours together: each device's share meets a few regions
    out = self._map_in_order(program, points[order], viewdirs[order])
    back = np.empty_like(order)
    back[order] = np.arange(len(order))
    return tuple(o[back] for o in out)

  def _map_in_order(self, program, points, viewdirs):
    n = len(points)
    if n == 0:
      return np.zeros((0, 3), np.float32), np.zeros((0,), np.float32), np.zeros((0, 3), np.float32)
    chunk = min(self.chunk, -(-n // self.mesh.size) * self.mesh.size)
    padded = -(-n // chunk) * chunk
    pad = lambda x: np.concatenate([x, np.repeat(x[-1:], padded - n, axis=0)]) if padded > n else x
    points, viewdirs = pad(points), pad(viewdirs)
    rows = distributed.local_slice(chunk, self.mesh)
    pieces = [program(self.trained.params, *distributed.to_global(
        self.mesh, (points[s:s + chunk][rows], viewdirs[s:s + chunk][rows]))) for s in range(0, padded, chunk)]
    pieces = distributed.to_host(pieces)
    return tuple(np.concatenate([p[i] for p in pieces])[:n] for i in range(len(pieces[0])))


def by_region(fn, stacked, partition: nerf_regions.Partition, points_Nx3, viewdirs_Nx3, codes, boxes=None):
  """fn(field_params, points, viewdirs, codes, box) -> a tuple of (N, ...) arrays, of the stitched field: each
  point's entries are those of the field of the region it lies in (nerf_regions.region_of), `stacked` the
  fields' parameters on a leading axis of K, `boxes` the regions' own boxes (centres (K, 3), half extents
  (K, 3): nerf_regions.boxes; None: every field over the whole box), region k's box handed to fn as box. The regions present among the points are evaluated one after
  the other, each at every point, and kept where the points are its own: as many field evaluations as
  regions present, not K. (A loop inside one device's program: fn's own derivatives, the normals, are taken
  inside each pass; nothing is differentiated through the loop.)"""
  count = partition.size
  ids = nerf_regions.region_of(points_Nx3, partition)
  first = jax.tree.map(lambda p: p[0], stacked)
  # Zeros made from the points: inside shard_map the loop's carry must vary over the devices as they do.
  zeros = lambda s: jnp.broadcast_to(jnp.zeros_like(points_Nx3[:, 0], s.dtype).reshape(  # noqa: E731
      (-1,) + (1,) * (len(s.shape) - 1)), s.shape)
  box_of = lambda k: None if boxes is None else tuple(jnp.asarray(b)[k] for b in boxes)  # noqa: E731
  init = tuple(zeros(s) for s in jax.eval_shape(fn, first, points_Nx3, viewdirs_Nx3, codes, box_of(0)))

  def one_region(carry):
    k, outs = carry
    own = fn(jax.tree.map(lambda p: p[k], stacked), points_Nx3, viewdirs_Nx3, codes, box_of(k))
    mine = ids == k
    outs = tuple(jnp.where(mine.reshape(mine.shape + (1,) * (o.ndim - 1)), o_k, o) for o, o_k in zip(outs, own))
    return jnp.min(jnp.where(ids > k, ids, count)), outs  # the next region present (K: none)

  _, outs = jax.lax.while_loop(lambda carry: carry[0] < count, one_region, (jnp.min(ids), init))
  return outs


def ground_order(points_Nx3) -> np.ndarray:
  """A permutation of the points that puts them in Z-order (Morton order) on the ground plane: x and y
  quantised to 16 bits over the points' extent, their bits interleaved, sorted. A run of consecutive points
  in Z-order lies in a few squares of about its own size, and the regions are columns over the ground plane
  (nerf_regions.grid, voronoi), so each device's share of a chunk meets a few regions. A hint for cost only
  (by_region is right in any order), and cheap: a sort of N integers, where finding each point's region on
  the host would take K x P plane values a point."""
  ground = np.asarray(points_Nx3, np.float32)[:, :2]
  low, span = ground.min(0), np.maximum(np.ptp(ground, axis=0), 1e-30)
  place = np.clip((ground - low) * (65535 / span), 0, 65535).astype(np.uint32)
  for shift, mask in ((8, 0x00FF00FF), (4, 0x0F0F0F0F), (2, 0x33333333), (1, 0x55555555)):  # spread the bits
    place = (place | (place << np.uint32(shift))) & np.uint32(mask)
  return np.argsort(place[:, 0] | (place[:, 1] << np.uint32(1)), kind="stable")
