"""The NeRF model: sample along rays, query the field(s), composite; coarse-to-fine or proposal sampling."""
import functools
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from nerfpod.nerf import compositing, coord, fields, pose_correction, sampling, stepfun
from nerfpod.nerf import regions as nerf_regions  # (NeRF.regions is its count)


# The name of the region fields' parameters (NeRF's vmapped RegionRenderer): their leaves carry the regions
# on their first axis, and so do the optimiser's moments of them.
REGIONS = "regions"


def in_region(path) -> bool:
  """Whether a leaf's tree path is under the region fields' parameters (or their optimiser state)."""
  return any(getattr(k, "key", None) == REGIONS for k in path)


class NeRF(nn.Module):
  """Renders a batch of rays, in one of three ways.

  - Stratified: `num_samples` stratified samples go to the field.
  - Hierarchical (`num_importance` > 0, the paper's): that many more are drawn from the coarse weights by
    inverse CDF and a fine field is queried at the union of both sets; each level returns its rendering.
  - Proposal (`proposal_samples`, mip-NeRF 360 / nerfacto): each round draws that many intervals from the
    previous round's histogram (the first from the whole ray) and a small density-only proposal field
    weighs them; the NeRF field is then queried at `num_samples` intervals drawn from the last proposal.
    Rounds work in the normalised distance s in [0, 1] (`_warp` maps it to t under `spacing`), and no
    gradient reaches the sample positions. The rendering carries `s_edges` and, per proposal round, its
    (s_edges, weights): train.py supervises the proposals with the interlevel loss.

  `space` says where the field lives (nerf/coord.py): 'euclidean', the world itself; 'ndc', a forward-facing
  scene's NDC cube (the rays are mapped there first, with the view directions taken from the world rays as
  the original does, and near/far are NDC parameters in [0, 1]); 'contract', mip-NeRF 360's contracted ball
  of radius 2 (sample points are contracted before the field; rays are not clipped, every point lands in
  the ball). `spacing` places the samples evenly in distance ('linear'), in inverse distance ('inverse',
  for unbounded scenes with a far bound of 1e6) or in distance to 1 and inverse distance beyond ('piecewise',
  nerfacto's): samples are drawn in s in [0, 1] and mapped to t (proposal rounds too; nerf/coord.py).

  A bounded field (the hash grid) has each ray's [near, far] clipped to its box first (not in contracted space).
  Real captures (NeRF-W, nerfacto): with `model_config.appearance_dim` > 0, an appearance code per training
  frame (a learned table of `num_frames` rows, GLO, zeros at the start) joins the colour head's input, never
  the density's; with `pose_refine`, a correction per training frame (nerf/pose_correction.py, zeros at the
  start) moves each training ray before anything else. Both take the rays' training-frame indices `frames`;
  without them (held-out views, orbits, the viewer) every ray gets the mean of the training codes and no
  correction: held-out frames are rendered from their given poses (docs/training.md says why).
  Regions (`regions` = K > 1, NeRF-XL, nerf/regions.py): space is cut into K convex regions (`region_planes`,
a nerf_regions.Partition as nested tuples), each with its own NeRF field and proposal fields, their parameters
stacked on a leading axis of K under 'regions' (`RegionRenderer`, vmapped). Each region renders its own
segment of each ray with the configured samples (proposal rounds, or stratified samples over even
intervals), from transmittance 1, into per-ray partial sums (`render_partials`, for any subset of the
regions: a device's own); nerf_regions.composite_regions composites them in ray order. With a capacity (the training
step's, model.region_capacity) each region renders only the rays whose segment meets it, within a static number of
rows; with model.region_split, a segment renders 2^-j of the samples, j the class of its share of the ray, each
class within rows of its own (a flat cost per ray). Called directly, the model renders every region and composites: one device holding the whole model. K = 1
is the model above, unchanged.
  Randomness comes in as arrays of uniform numbers, one (R, n) array per round of `sample_counts()` (none:
  deterministic evaluation), so the module is a pure function of its inputs. Every attribute comes from
  the config (nerfpod.run.components.make_model).
  """
  model_config: Any
  num_samples: int
  num_importance: int
  last_delta: float
  dtype: Any
  space: str = "euclidean"
  spacing: str = "linear"
  ndc_camera: tuple[float, float, float, float] | None = None  # (fx, fy, width, height) defining the NDC cube
  proposal_samples: tuple = ()
  proposal_padding: float = 0.0  # render.proposal_padding: added to each proposal interval's weight (stepfun)
  num_frames: int = 0        # training frames: rows of the appearance codes and pose corrections
  pose_refine: bool = False  # learn a pose correction per training frame
  near_gradient_distance: float = 0.0  # > 0: the field's gradients scaled by min(1, (distance / this)^2)
  pixel_angle: float = 0.0    # > 0 (model.hashgrid.scale_aware): a pixel's width at distance 1, radians
  regions: int = 1            # K: fields, one per convex region of space (1: one field everywhere)
  region_planes: tuple = ()   # regions > 1: the nerf_regions.Partition's three arrays as nested tuples

  def sample_counts(self) -> tuple:
    """How many uniform numbers per ray each sampling round takes, in the order __call__ takes them."""
    if self.proposal_samples:
      return tuple(self.proposal_samples) + (self.num_samples,)
    return (self.num_samples,) + ((self.num_importance,) if self.num_importance else ())
  grid_matmul_max_rows: int = 0  # hash grid: dense levels up to this many rows looked up by matmuls
  grid_materialize: bool = False  # hash grid: its points and corner rows kept in memory (CPUs)
  grid_layout: str = "rows"  # hash grid: its lookup's layout (compile.hashgrid_layout; the same parameters)
  grid_lookup: str = "gather"  # hash grid: its gathered levels' lookup, 'gather' or 'sparsecore' (TPU v5p/v6e)

  def _render(self, field, origins, directions, viewdirs, t_RxS, background, codes, opened=None):
    points = self._points(origins, directions, t_RxS)
    dirs = jnp.broadcast_to(viewdirs[..., None, :], points.shape)
    rgb, sigma = field(points.reshape(-1, 3), dirs.reshape(-1, 3), *_per_point(codes, points.shape[:-1]),
                       **self._footprints(origins, directions, t_RxS), **_opened(opened))
    rgb, sigma = near_gradients(rgb.reshape(points.shape), sigma.reshape(points.shape[:-1]), t_RxS,
                                 directions, self.near_gradient_distance)
    out = compositing.composite(rgb, sigma, t_RxS, directions, last_delta=self.last_delta,
                                background=background)
    out["t"] = t_RxS
    return self._in_world_units(out, t_RxS)

  def _in_world_units(self, out, t_RxS):
    """In NDC space, depth along the NDC camera's axis and disparity its inverse (coord.ndc_to_disparity),
    rather than the NDC ray parameter."""
    if self.space == "ndc":
      out["disparity"] = jnp.sum(out["weights"] * coord.ndc_to_disparity(t_RxS), axis=-1)
      out["depth"] = out["acc"] / jnp.maximum(out["disparity"], 1e-10)
    return out

  def _distances(self, near, far, num: int, uniform):
    """Stratified ray distances (R, num): even in t ('linear'), or even in s and warped to t."""
    if self.spacing == "linear":
      return sampling.stratified(near, far, num, uniform)
    return coord.s_to_t(sampling.stratified(0.0, 1.0, num, uniform), near, far, self.spacing)

  def _per_frame(self, origins_Rx3, directions_Rx3, frames_R):
    """(origins, directions, appearance codes (R, A) or None): the rays moved by their frames' pose
    corrections and their frames' codes (`frames_R` None: unmoved, and the mean of the codes)."""
    codes = None
    if self.model_config.appearance_dim:
      table = self.param("appearance", nn.initializers.zeros,
                         (self.num_frames, self.model_config.appearance_dim), jnp.float32)
      if frames_R is None:
        codes = jnp.broadcast_to(jnp.mean(table, axis=0), origins_Rx3.shape[:-1] + table.shape[1:])
      else:
        codes = table[frames_R]
    if self.pose_refine:
      corrections = self.param(pose_correction.PARAM, nn.initializers.zeros, (self.num_frames, 6), jnp.float32)
      if frames_R is not None:
        origins_Rx3, directions_Rx3 = pose_correction.correct_rays(origins_Rx3, directions_Rx3,
                                                                   corrections[frames_R])
    return origins_Rx3, directions_Rx3, codes

  @nn.compact
  def __call__(self, origins_Rx3, directions_Rx3, near, far, background, *uniforms, frames=None,
               region_ids=None, opened=None, anneal=None, capacity=0, gather=None):
    """A list of renderings (dicts of rgb, depth, acc, disparity, weights, t), coarse first.

    near, far: floats or (R, 1); background: (3,) or (R, 3) (nerf.compositing.composite); uniforms: one
    (R, n) array of numbers in [0, 1) per entry of `sample_counts()`, or none at all (evaluation); frames:
    (R,) int32 training-frame index of each ray (training), or None; opened: the hash grid's levels'
    coarse-to-fine weights (num_levels,) for the NeRF field (training with train.coarse_to_fine), or None;
    anneal: the exponent the proposal weights are raised to before resampling (training with
    train.proposal_anneal_steps: stepfun.anneal_exponent), or None (1: evaluation).
    """
    if self.regions > 1:
      # render_partials' (with `region_ids`), or every region here, composited: uniforms (K, R, n) per round.
      partials, local = self._region_partials(origins_Rx3, directions_Rx3, near, far,
                                              jnp.arange(self.regions) if region_ids is None else region_ids,
                                              uniforms or None, frames, anneal, capacity, gather)
      if region_ids is not None:
        return partials, local
      out = nerf_regions.composite_regions(partials, background)
      return [{k: out[k] for k in compositing.OUTPUTS}]
    uniforms = uniforms or (None,) * len(self.sample_counts())
    origins_Rx3, directions_Rx3, codes = self._per_frame(origins_Rx3, directions_Rx3, frames)
    viewdirs = directions_Rx3 / jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
    if self.space == "ndc":
      if self.ndc_camera is None:
        raise ValueError("render.space='ndc' needs the scene's camera (make_model(..., ndc_camera=...))")
      origins_Rx3, directions_Rx3 = coord.ndc_rays(origins_Rx3, directions_Rx3, *self.ndc_camera, near=1.0)
    if self.model_config.field == "hashgrid" and self.space != "contract":  # bounded: sample inside its box
      near, far = sampling.clip_to_box(origins_Rx3, directions_Rx3, near, far,
                                       self.model_config.hashgrid.bound)
    if self.proposal_samples:
      return [self._proposal_render(origins_Rx3, directions_Rx3, viewdirs, near, far, background, uniforms,
                                    codes, opened, anneal)]
    t = self._distances(near, far, self.num_samples, uniforms[0])
    t = jnp.broadcast_to(t, origins_Rx3.shape[:-1] + (self.num_samples,))
    coarse_field = fields.make_field(self.model_config, self.dtype, name="coarse",
                                   matmul_max_rows=self.grid_matmul_max_rows,
                                   materialize=self.grid_materialize, layout=self.grid_layout, lookup=self.grid_lookup)
    coarse = self._render(coarse_field, origins_Rx3, directions_Rx3, viewdirs, t, background, codes, opened)
    if self.num_importance == 0:
      return [coarse]
    # Importance samples are drawn in s, where the coarse samples are evenly spread ('linear': s is t).
    s = t if self.spacing == "linear" else coord.t_to_s(t, near, far, self.spacing)
    mids = 0.5 * (s[..., 1:] + s[..., :-1])
    u = uniforms[1]
    if u is None:  # evaluation: evenly spaced from 0 to 1 inclusive, the original's deterministic samples
      u = jnp.broadcast_to(jnp.linspace(0.0, 1.0, self.num_importance), s.shape[:-1] + (self.num_importance,))
    # The original pads the coarse weights by 1e-5: a little of every interval stays reachable.
    s_fine = stepfun.inverse_cdf(mids, coarse["weights"][..., 1:-1] + 1e-5, u)
    t_fine = s_fine if self.spacing == "linear" else coord.s_to_t(s_fine, near, far, self.spacing)
    t_all = jnp.sort(jnp.concatenate([t, t_fine], axis=-1), axis=-1)
    fine_field = fields.make_field(self.model_config, self.dtype, name="fine",
                                   matmul_max_rows=self.grid_matmul_max_rows,
                                   materialize=self.grid_materialize, layout=self.grid_layout, lookup=self.grid_lookup)
    fine = self._render(fine_field, origins_Rx3, directions_Rx3, viewdirs, t_all, background, codes, opened)
    return [coarse, fine]

  @property
  def partition(self) -> nerf_regions.Partition:
    normals, offsets, closed = self.region_planes
    return nerf_regions.Partition(np.array(normals, np.float32), np.array(offsets, np.float32), np.array(closed, bool))

  @property
  def region_boxes(self) -> tuple[np.ndarray, np.ndarray]:
    """The box each region's fields span (centres (K, 3), half extents (K, 3)), mapped onto the fields' box:
    model.region_box 'own', the region's own (nerf_regions.boxes); 'scene', the fields' box itself (the map
    is then x * 1.0: the same bits as no map)."""
    bound = self.model_config.hashgrid.bound
    if self.model_config.region_box == "own":
      return nerf_regions.boxes(self.partition, bound)
    count = len(self.region_planes[0])
    return np.zeros((count, 3), np.float32), np.full((count, 3), bound, np.float32)

  def render_partials(self, origins_Rx3, directions_Rx3, near, far, region_ids_L, uniforms=(), frames=None,
                      anneal=None, capacity=0, gather=None):
    """(partials, local) of the L regions `region_ids_L` (L,) int32 (with parameters for those L only, the
    first axis of params['regions'], e.g. one device's share): `partials`, what crosses devices, a dict of
    (L, R, ...) arrays (nerf_regions.GATHERED: each ray's segment start and partial sums); `local`, what stays
    (the losses' per-sample histograms): s_edges (L, R, S+1) and weights (L, R, S) of the NeRF field, and
    `proposals`, per round its (s_edges, weights); and `present` (L, R), whether each ray's segment in each
    region is not empty. `uniforms`: per entry of sample_counts() an (L, R, n) array (each region its own
    numbers), or () (evaluation). Needs `regions` > 1. (Through __call__, flax's one compact method.)

    `capacity` C > 0 (model.region_capacity, training): each region renders only C rows, the rays whose
    segment in it is not empty, the first C in ray order (nerf_regions.dispatch), with their rows of the
    same `uniforms`; `partials` are put back into their rays (L, R, ...), a ray without a row taking what an
    empty segment gives (nerf_regions.empty_sums), and `local` holds `present`, `dropped` (L, R) (a segment
    that found no row) and `classes`, one entry here: the histograms per row (L, C, ...) with their `dispatch`
    (nerf_regions.Dispatch: which ray each row is, which segments found no row). 0: every ray in every region
    (dense).

    With model.region_split = J > 1, `capacity` is a tuple (C_0, ..., C_J-1): each segment is of the sample
    class of its share of the ray (nerf_regions.sample_classes), and class j renders its C_j rows with every
    round's count at 2^-j (nerf_regions.class_counts; their first n_j of the `uniforms`); `partials` are put
    back into their rays as before, and `classes` has J entries; `dispatches` are the rows' Dispatches (those of
    `classes` but with model.region_split_by=weights).

    With model.region_split_by=weights the classes of the proposal rounds are the length's, and the NeRF round's
    are those of each segment's share of its ray's proposal weight (nerf_regions.weight_shares), which needs every
    region's segments: `gather` maps a dict of the L regions' (L, R) arrays to the K regions' (the step's gather
    over the region axis; None where L = K). `classes` are then the NeRF round's (their rows' proposal histograms
    carried over), `dispatches` the proposal rounds' (where rays drop), and `downgraded` (L, R) marks the
    segments a full class handed down to fewer samples (nerf_regions.downgrade_dispatch)."""
    return self(origins_Rx3, directions_Rx3, near, far, None, *uniforms, frames=frames, region_ids=region_ids_L,
                anneal=anneal, capacity=capacity, gather=gather)

  def _region_partials(self, origins_Rx3, directions_Rx3, near, far, region_ids_L, uniforms, frames, anneal,
                       capacity=0, gather=None):
    origins_Rx3, directions_Rx3, codes = self._per_frame(origins_Rx3, directions_Rx3, frames)
    viewdirs = directions_Rx3 / jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
    if self.model_config.field == "hashgrid":  # bounded (space is euclidean with regions: schema rule)
      near, far = sampling.clip_to_box(origins_Rx3, directions_Rx3, near, far, self.model_config.hashgrid.bound)
    rays = origins_Rx3.shape[:-1]
    near = jnp.broadcast_to(jnp.asarray(near, jnp.float32), rays + (1,))
    far = jnp.broadcast_to(jnp.asarray(far, jnp.float32), rays + (1,))
    planes = tuple(jnp.asarray(a)[region_ids_L] for a in self.partition)
    boxes = tuple(jnp.asarray(a)[region_ids_L] for a in self.region_boxes)
    if uniforms is None:
      uniforms = (None,) * len(self.sample_counts())
    # Each region's segment of each ray (L, R), cut once: what the regions render, and which are present.
    t_in, t_out = nerf_regions.segments_one_by_one(origins_Rx3, directions_Rx3, near, far, planes)
    settings = dict(model_config=self.model_config, num_samples=self.num_samples, dtype=self.dtype,
                    spacing=self.spacing, proposal_samples=tuple(self.proposal_samples),
                    proposal_padding=self.proposal_padding, grid_matmul_max_rows=self.grid_matmul_max_rows,
                    grid_materialize=self.grid_materialize, grid_layout=self.grid_layout,
                    grid_lookup=self.grid_lookup, near_gradient_distance=self.near_gradient_distance, name=REGIONS)
    if not capacity:  # dense: every ray through every region
      renderer = nn.vmap(RegionRenderer, variable_axes={"params": 0}, split_rngs={"params": True},
                         in_axes=(0, (dict(_SHARED_ROWS, uniforms=0, segment=0),), None), out_axes=0)(**settings)
      rows = dict(uniforms=tuple(uniforms), origins=origins_Rx3, directions=directions_Rx3, viewdirs=viewdirs,
                  codes=codes, near=near, far=far, segment=(t_in, t_out))
      (partials, local), = renderer(boxes, (rows,), anneal)
      local["present"] = t_out > t_in
      return partials, local
    # Compacted: each region's C rows (its rays with a segment there, in ray order), the rays' inputs and
    # numbers gathered by row; a row left over renders an empty segment ([far, far]: weights 0). With
    # model.region_split, a row set per sample class (its rays' segments of that class, C_j rows each).
    present = t_out > t_in
    classes = max(self.model_config.region_split, 1)
    capacities = (capacity,) * classes if isinstance(capacity, int) else tuple(capacity)
    if len(capacities) != classes:
      raise ValueError(f"{len(capacities)} capacities for model.region_split's {classes} sample classes")
    if classes > 1:
      klass = nerf_regions.sample_classes(nerf_regions.segment_shares(t_in, t_out, near, far, self.spacing), classes)
      masks = [present & (klass == j) for j in range(classes)]
    else:
      masks = [present]
    dispatches = [nerf_regions.dispatch_present(m, c) for m, c in zip(masks, capacities)]

    def rows_of(dispatched):  # RegionRenderer's rows of each Dispatch
      return tuple(_class_rows(d, uniforms, origins_Rx3, directions_Rx3, viewdirs, codes, near, far, t_in, t_out)
                   for d in dispatched)

    split_by = self.model_config.region_split_by if classes > 1 else "length"
    renderer = nn.vmap(RegionRenderer, variable_axes={"params": 0}, split_rngs={"params": True},
                       in_axes=(0, 0, None, 0), out_axes=0)(fractions=nerf_regions.class_fractions(classes),
                                                            split_by=split_by, **settings)
    rendered = renderer(boxes, rows_of(dispatches), anneal, None)
    dropped = functools.reduce(jnp.logical_or, [d.dropped_LxR for d in dispatches])
    local = {"present": present, "dropped": dropped, "dispatches": dispatches}
    finals = dispatches
    if split_by == "weights":
      # The NeRF round by each segment's share of its ray's proposal weight: the opacities of every region's
      # segments gathered over the regions (`gather`), the classes of the shares, rows anew (a class over its
      # rows hands segments down), each row with its segment's histograms from the proposal rounds' rows.
      opacity = jax.lax.stop_gradient(nerf_regions.scatter_classes([p["opacity"] for p in rendered], dispatches, 0.0))
      everyone = (gather or (lambda x: x))({"opacity": opacity, "t_in": t_in})
      shares = nerf_regions.weight_shares(everyone["opacity"], everyone["t_in"])[region_ids_L]
      finals = nerf_regions.downgrade_dispatch(nerf_regions.sample_classes(shares, classes), present & ~dropped,
                                               nerf_regions.final_capacities(capacities))
      rendered = renderer(boxes, rows_of(finals), anneal, tuple(_carried(rendered, dispatches, finals)))
      local["downgraded"] = functools.reduce(jnp.logical_or, [d.dropped_LxR for d in finals[:-1]])
    far_R = far[..., 0]
    partials = {k: nerf_regions.scatter_classes([p[k] for p, _ in rendered], finals,
                                                nerf_regions.empty_sums(far_R, k)) for k in rendered[0][0]}
    local["classes"] = [dict(class_local, dispatch=d) for (_, class_local), d in zip(rendered, finals)]
    return partials, local

  def _footprints(self, origins, directions, t_RxS) -> dict:
    """{} without `pixel_angle`, else {"scales_N": ...}: each sample's pixel footprint (R * S,) in the field's
    space, the standard deviation of a pixel's width there (width / sqrt(12)): the pixel's angle times the
    sample's distance from the ray's origin, shrunk by the contraction where space='contract'
    (coord.contraction_scale). One angle for every ray of the scene (its training cameras' median)."""
    if not self.pixel_angle:
      return {}
    distance = t_RxS * jnp.linalg.norm(directions, axis=-1, keepdims=True)
    scales = self.pixel_angle / np.sqrt(12.0) * distance
    if self.space == "contract":
      scales = scales * coord.contraction_scale(_ray_points(origins, directions, t_RxS))[..., 0]
    return {"scales_N": scales.reshape(-1)}

  def _points(self, origins, directions, t_RxS):
    """The sample points at distances t, in the field's space (contracted where space='contract')."""
    points = _ray_points(origins, directions, t_RxS)
    return coord.contract(points) if self.space == "contract" else points

  def _proposal_render(self, origins, directions, viewdirs, near, far, background, uniforms, codes, opened=None,
                       anneal=None):
    if self.spacing == "linear":
      warp = sampling.linear_warp(near, far)
    else:  # even in s is even in inverse distance
      warp = lambda s: coord.s_to_t(s, near, far, self.spacing)  # noqa: E731
    rays = origins.shape[:-1]
    s_edges = jnp.broadcast_to(jnp.array([0.0, 1.0]), rays + (2,))  # round 0 draws from the whole ray
    weights = jnp.ones(rays + (1,))
    proposals = []
    for i, count in enumerate(self.proposal_samples):
      s_edges = stepfun.sample_intervals(s_edges, _drawn_from(weights, i, self.proposal_padding, anneal), count,
                                         uniforms[i])
      t_edges = warp(s_edges)
      t_mids = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
      points = self._points(origins, directions, t_mids)
      field = fields.make_proposal_field(self.model_config, self.dtype, name=f"proposal_{i}",
                                         matmul_max_rows=self.grid_matmul_max_rows,
                                         materialize=self.grid_materialize, layout=self.grid_layout,
                                         lookup=self.grid_lookup)
      sigma = field(points.reshape(-1, 3)).reshape(t_mids.shape)
      weights = compositing.interval_weights(sigma, t_edges, directions)
      proposals.append({"s_edges": s_edges, "weights": weights, "saturated": saturated_share(sigma)})
    s_edges = stepfun.sample_intervals(s_edges, _drawn_from(weights, -1, self.proposal_padding, anneal),
                                       self.num_samples, uniforms[-1])
    t_edges = warp(s_edges)
    t_mids = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
    points = self._points(origins, directions, t_mids)
    dirs = jnp.broadcast_to(viewdirs[..., None, :], points.shape)
    field = fields.make_field(self.model_config, self.dtype, name="coarse",
                              matmul_max_rows=self.grid_matmul_max_rows,
                              materialize=self.grid_materialize, layout=self.grid_layout, lookup=self.grid_lookup)
    rgb, sigma = field(points.reshape(-1, 3), dirs.reshape(-1, 3), *_per_point(codes, points.shape[:-1]),
                       **self._footprints(origins, directions, t_mids), **_opened(opened))
    rgb, sigma = near_gradients(rgb.reshape(points.shape), sigma.reshape(t_mids.shape), t_mids, directions,
                                self.near_gradient_distance)
    out = compositing.composite_intervals(rgb, sigma, t_edges, directions, background=background)
    out.update(t=t_mids, s_edges=s_edges, proposals=proposals, saturated=saturated_share(sigma))
    return self._in_world_units(out, t_mids)


class RegionRenderer(nn.Module):
  """One region's fields (its proposal fields and its NeRF field) rendering its segment of each ray
  (NeRF.render_partials vmaps it over the regions): the segment [t_in, t_out] inside the region's planes is
  [s_in, s_out] in the ray's normalised distance s (of the whole ray's [near, far]), and the samples are
  drawn there as the one-field model draws them over [0, 1]: proposal rounds, the first from the whole
  segment, or (no proposals) stratified points over `num_samples` even intervals, each holding over its
  interval. Every sample holds over an interval inside its segment: the regions' intervals never overlap, and
  composited in ray order they are one rendering of the stitched field (nerf/regions.py). The fields see the
  region's own box (`box`: nerf_regions.boxes) mapped onto theirs, so each spends its resolution there."""
  model_config: Any
  num_samples: int
  dtype: Any
  spacing: str
  proposal_samples: tuple
  grid_matmul_max_rows: int
  near_gradient_distance: float
  grid_materialize: bool = False
  proposal_padding: float = 0.0
  grid_layout: str = "rows"
  grid_lookup: str = "gather"

  fractions: tuple = (1.0,)  # model.region_split: each sample class's share of the samples (regions.class_fractions)
  split_by: str = "length"   # model.region_split_by

  @nn.compact
  def __call__(self, box, rows, anneal, carried=None):
    """`rows`: per sample class (of `fractions`), a dict of the rays it renders: uniforms (a tuple, per
    sampling round (R, n) or None), origins, directions, viewdirs, codes (or None), near, far (R, 1) and
    segment, each ray's (t_in, t_out) (R,) in the region (nerf_regions.segments_one_by_one's cut). Class j
    renders with every round's count at fractions[j] (nerf_regions.class_counts). Returns per class
    (partials, local).

    With `split_by` 'weights' the rendering is two calls: without `carried`, the proposal rounds only,
    returning per class what the NeRF round needs (_proposed: the histogram it draws from, the rounds'
    histograms, the segment's opacity); with `carried` (per class of the NeRF round, those of its rows), the NeRF
    round only, at its own class's count."""
    bound = self.model_config.hashgrid.bound
    local = lambda points: nerf_regions.to_box(points, *box, bound)  # noqa: E731  (the region's own box)
    made = dict(matmul_max_rows=self.grid_matmul_max_rows, materialize=self.grid_materialize,
                layout=self.grid_layout, lookup=self.grid_lookup)
    proposal_fields = [fields.make_proposal_field(self.model_config, self.dtype, name=f"proposal_{i}", **made)
                       for i in range(len(self.proposal_samples))]
    field = fields.make_field(self.model_config, self.dtype, name="coarse", **made)
    # Round by round, every class's samples through one call of the round's field (one set of lookups and
    # matmuls for the region, whatever the classes), then each class's own compositing.
    states = [self._start(fraction, **class_rows) for fraction, class_rows in zip(self.fractions, rows)]
    if carried is not None:  # (split_by 'weights', the NeRF round) the proposal rounds' histograms of its rows
      for state, c in zip(states, carried):
        state.update(s_edges=c["s_edges"], drawn=c["drawn"], proposals=c["proposals"])
    else:
      for i, proposal_field in enumerate(proposal_fields):
        points = [self._propose(state, i, anneal) for state in states]
        for state, (sigma,) in zip(states, _fused(lambda p: (proposal_field(p),), [(local(p),) for p in points])):
          sigma = sigma.reshape(state["t_mids"].shape)
          state["weights"] = compositing.interval_weights(sigma, state["t_edges"], state["directions"])
          state["proposals"].append({"s_edges": state["s_edges"], "weights": state["weights"]})
      if self.split_by == "weights":
        return tuple(self._proposed(state, anneal) for state in states)
    inputs = [self._place(state, anneal) for state in states]
    outputs = _fused(field, [(local(points), dirs, *codes) for points, dirs, codes in inputs])
    return tuple(self._finish(state, rgb, sigma) for state, (rgb, sigma) in zip(states, outputs))

  def _start(self, fraction, uniforms, origins, directions, viewdirs, codes, near, far, segment) -> dict:
    """A sample class's rows before their first round: its counts (at `fraction`), the segments in s."""
    t_in, t_out = (t[:, None] for t in segment)
    to_s = lambda t: jnp.clip(coord.t_to_s(t, near, far, self.spacing), 0.0, 1.0)  # noqa: E731
    s_in, s_out = to_s(t_in), jnp.maximum(to_s(t_out), to_s(t_in))
    rays = origins.shape[:-1]
    return dict(counts=nerf_regions.class_counts(tuple(self.proposal_samples) + (self.num_samples,), fraction),
                uniforms=uniforms, origins=origins, directions=directions, viewdirs=viewdirs, codes=codes, near=near,
                far=far, t_in=t_in, s_in=s_in, s_out=s_out, s_edges=jnp.concatenate([s_in, s_out], axis=-1),
                weights=jnp.ones(rays + (1,)), proposals=[])

  def _warp(self, state, s):
    return coord.s_to_t(s, state["near"], state["far"], self.spacing)

  @staticmethod
  def _points_at(state, t):
    return state["origins"][..., None, :] + t[..., None] * state["directions"][..., None, :]

  @staticmethod
  def _uniforms(state, i: int, count: int):
    u = state["uniforms"][i]
    return u if u is None or u.shape[-1] == count else u[..., :count]  # (a class's first `count`)

  def _propose(self, state, i: int, anneal):
    """Proposal round i's intervals of a class's rows (drawn from the last round's weights): its points (N, 3)."""
    count = state["counts"][i]
    state["s_edges"] = stepfun.sample_intervals(state["s_edges"], _drawn_from(state["weights"], i,
                                                                              self.proposal_padding, anneal),
                                                count, self._uniforms(state, i, count),
                                                domain=(state["s_in"], state["s_out"]))
    state["t_edges"] = self._warp(state, state["s_edges"])
    state["t_mids"] = 0.5 * (state["t_edges"][..., 1:] + state["t_edges"][..., :-1])
    return self._points_at(state, state["t_mids"]).reshape(-1, 3)

  def _proposed(self, state, anneal) -> dict:
    """(split_by 'weights') A class's rows after the proposal rounds: the histogram the NeRF round draws from
    (s_edges, drawn), every round's (proposals), and the segment's opacity (the last proposal's weights summed)."""
    return dict(s_edges=state["s_edges"], drawn=_drawn_from(state["weights"], -1, self.proposal_padding, anneal),
                proposals=state["proposals"], opacity=jnp.sum(state["weights"], axis=-1))

  def _place(self, state, anneal):
    """The NeRF field's samples of a class's rows: (points (N, 3), directions (N, 3), per-point codes)."""
    count = state["counts"][-1]
    if self.proposal_samples:
      drawn = state.get("drawn")
      if drawn is None:
        drawn = _drawn_from(state["weights"], -1, self.proposal_padding, anneal)
      state["s_edges"] = stepfun.sample_intervals(state["s_edges"], drawn, count, self._uniforms(state, -1, count),
                                                  domain=(state["s_in"], state["s_out"]))
      state["t_edges"] = self._warp(state, state["s_edges"])
      state["t_points"] = 0.5 * (state["t_edges"][..., 1:] + state["t_edges"][..., :-1])
    else:
      s_in, s_out = state["s_in"], state["s_out"]
      state["s_edges"] = s_in + (s_out - s_in) * jnp.linspace(0.0, 1.0, count + 1)
      u = 0.5 if state["uniforms"][0] is None else self._uniforms(state, 0, count)
      state["t_edges"] = self._warp(state, state["s_edges"])
      state["t_points"] = self._warp(state, state["s_edges"][..., :-1] + u * jnp.diff(state["s_edges"], axis=-1))
    points = self._points_at(state, state["t_points"])
    dirs = jnp.broadcast_to(state["viewdirs"][..., None, :], points.shape)
    return points.reshape(-1, 3), dirs.reshape(-1, 3), _per_point(state["codes"], points.shape[:-1])

  def _finish(self, state, rgb, sigma):
    """A class's (partials, local) from its NeRF samples' colours and densities."""
    t_points, directions = state["t_points"], state["directions"]
    rgb, sigma = near_gradients(rgb.reshape(t_points.shape + (3,)), sigma.reshape(t_points.shape), t_points,
                                directions, self.near_gradient_distance)
    sums = nerf_regions.partial_sums(rgb, sigma, t_points, jnp.diff(state["t_edges"], axis=-1), directions,
                                     state["s_edges"])
    partials = {k: sums[k] for k in nerf_regions.GATHERED if k in sums}
    partials["t_in"] = state["t_in"][..., 0]
    return partials, {"proposals": state["proposals"], "s_edges": state["s_edges"], "weights": sums["weights"]}


def _fused(fn, inputs: list) -> list:
  """fn applied to each of `inputs` (tuples of (N_i, ...) arrays), as one call on their rows concatenated, its
  outputs (a tuple of (sum N_i, ...) arrays) split back; one input: fn itself (the same program as a plain call)."""
  if len(inputs) == 1:
    return [fn(*inputs[0])]
  sizes = np.cumsum([x[0].shape[0] for x in inputs])[:-1]
  out = fn(*(jnp.concatenate(parts, axis=0) for parts in zip(*inputs)))
  pieces = [jnp.split(o, sizes, axis=0) for o in out]
  return [tuple(p[i] for p in pieces) for i in range(len(inputs))]


def _class_rows(d, uniforms, origins, directions, viewdirs, codes, near, far, t_in_LxR, t_out_LxR) -> dict:
  """RegionRenderer's rows of one Dispatch `d`: the rays' inputs and each region's own numbers and segments
  gathered by row; a row left over renders an empty segment ([far, far]: weights 0)."""
  rows = lambda x: None if x is None else nerf_regions.gather_rows(x, d)  # noqa: E731
  own_rows = lambda x: None if x is None else nerf_regions.gather_rows(x, d, per_region=True)  # noqa: E731
  far_rows = rows(far)  # (L, C, 1)
  used = d.rows_LxC < t_in_LxR.shape[1]
  segment = (jnp.where(used, own_rows(t_in_LxR), far_rows[..., 0]),
             jnp.where(used, own_rows(t_out_LxR), far_rows[..., 0]))
  return dict(uniforms=tuple(own_rows(u) for u in uniforms), origins=rows(origins), directions=rows(directions),
              viewdirs=rows(viewdirs), codes=rows(codes), near=rows(near), far=far_rows, segment=segment)


def _carried(proposed, dispatches, finals) -> list:
  """(model.region_split_by=weights) Per class of the NeRF round (`finals`, Dispatches), its rows' histograms
  from the proposal rounds (`proposed`, RegionRenderer._proposed's per length class, on the rows of
  `dispatches`): the classes' rows one after the other, every histogram padded to the longest (its last edge
  repeated, weight 0: never drawn from, adding nothing to a loss), gathered by each row's ray."""
  rays = dispatches[0].slots_LxR.shape[1]
  source = jnp.zeros_like(dispatches[0].slots_LxR)  # each segment's row among all the proposal rounds' rows
  for d, offset in zip(dispatches, np.cumsum([0] + [d.capacity for d in dispatches])[:-1]):
    source = jnp.where(d.slots_LxR < d.capacity, int(offset) + d.slots_LxR, source)

  def stacked(edges, weights):  # per class (L, C_j, B_j + 1), (L, C_j, B_j) -> (L, sum C_j, ...) padded
    bins = max(w.shape[-1] for w in weights)
    pad = lambda x, n, value: jnp.concatenate(  # noqa: E731
        [x, jnp.broadcast_to(value, x.shape[:-1] + (n,))], axis=-1) if n else x
    return (jnp.concatenate([pad(e, bins - e.shape[-1] + 1, e[..., -1:]) for e in edges], axis=1),
            jnp.concatenate([pad(w, bins - w.shape[-1], jnp.zeros((), w.dtype)) for w in weights], axis=1))

  drawn = stacked([p["s_edges"] for p in proposed], [p["drawn"] for p in proposed])
  rounds = [stacked([p["proposals"][i]["s_edges"] for p in proposed], [p["proposals"][i]["weights"] for p in proposed])
            for i in range(len(proposed[0]["proposals"]))]
  out = []
  for d in finals:
    picked = jnp.take_along_axis(source, jnp.minimum(d.rows_LxC, rays - 1), axis=1)[..., None]  # (L, C, 1)
    take = lambda x: jnp.take_along_axis(x, picked, axis=1)  # noqa: E731
    out.append(dict(s_edges=take(drawn[0]), drawn=take(drawn[1]),
                    proposals=[{"s_edges": take(e), "weights": take(w)} for e, w in rounds]))
  return out


# The dense renderer's inputs that every region shares (its rays), against its own (uniforms, segment).
_SHARED_ROWS = dict(origins=None, directions=None, viewdirs=None, codes=None, near=None, far=None)


def _drawn_from(weights, round_index: int, padding: float, anneal):
  """The histogram sampling round `round_index` draws from (-1: the NeRF's): round 0 the whole ray (or segment)
  as it is; every later one the previous proposal's weights, padded by render.proposal_padding and annealed by
  `anneal` (stepfun.resampling_weights)."""
  return weights if round_index == 0 else stepfun.resampling_weights(weights, padding, anneal)


def saturated_share(sigma_RxS):
  """Per ray (R,), the share of its samples whose density sits at the hash-grid fields' clamp (exp(15)): a
  wall the field can only raise (no gradient above the clamp without model.trunc_exp)."""
  return jnp.mean((sigma_RxS >= SATURATED_DENSITY).astype(jnp.float32), axis=-1)


# Densities at the clamp: exp(15) as float32 computes it, less a hair.
SATURATED_DENSITY = float(np.exp(np.float32(fields.DENSITY_CLAMP))) * (1.0 - 1e-6)


def near_gradients(rgb_RxSx3, sigma_RxS, t_RxS, directions_Rx3, near_distance: float):
  """The field's outputs, unchanged, with their gradients scaled by min(1, (d / near_distance)^2) at
  distance d = t |direction| from the ray's origin (0: unscaled). "Floaters No More" (Philip and Deschaintre
  2023), nerfacto's gradient scaling: space right in front of a training camera is sampled densely by that
  camera alone, and its gradients grew floaters there that other views then look through."""
  if not near_distance:
    return rgb_RxSx3, sigma_RxS
  distance = t_RxS * jnp.linalg.norm(directions_Rx3, axis=-1, keepdims=True)
  scale = jnp.minimum(1.0, jnp.square(distance / near_distance))
  return _scale_gradient(rgb_RxSx3, scale[..., None]), _scale_gradient(sigma_RxS, scale)


@jax.custom_vjp
def _scale_gradient(x, scale):
  """x itself (no work where nothing is differentiated, and an infinite density stays one), whose
  gradient is `scale` times x's; none flows to `scale`."""
  return x


_scale_gradient.defvjp(lambda x, scale: (x, scale),
                       lambda scale, g: (g * scale, jnp.zeros_like(scale)))


def _ray_points(origins_Rx3, directions_Rx3, t_RxS):
  """The points (R, S, 3) at distances t along the rays, in the world (before any contraction)."""
  return origins_Rx3[..., None, :] + t_RxS[..., None] * directions_Rx3[..., None, :]


def _opened(opened_L) -> dict:
  """The NeRF field's keyword for the levels' coarse-to-fine weights: none where every level is whole (the
  field's call, and so the program, as without the option)."""
  return {} if opened_L is None else {"opened_L": opened_L}


def _per_point(codes_RxA, sample_shape) -> tuple:
  """() without appearance codes, else (codes (R * S, A),): each ray's code at each of its S samples."""
  if codes_RxA is None:
    return ()
  return (jnp.broadcast_to(codes_RxA[..., None, :], sample_shape + codes_RxA.shape[-1:]).reshape(
      -1, codes_RxA.shape[-1]),)
