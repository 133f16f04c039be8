"""Radiance fields: flax modules mapping points (and view directions) to colour and density."""
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from nerfpod.nerf import encodings

_ACTIVATIONS = {"relu": nn.relu, "softplus": nn.softplus, "exp": jnp.exp}

# The raw density output above which the hash-grid fields' exp is clamped: exp(15) = 3.3e6 per unit length.
DENSITY_CLAMP = 15.0


def clamped_exp(h):
  """exp(min(h, DENSITY_CLAMP)), whose gradient is 0 above the clamp: a density saturated there gets no
  signal to come down (the hash-grid fields' activation before model.trunc_exp)."""
  return jnp.exp(jnp.minimum(h, DENSITY_CLAMP))


@jax.custom_jvp
def trunc_exp(h):
  """exp(min(h, DENSITY_CLAMP)) with the gradient exp(min(h, DENSITY_CLAMP)) everywhere: above the clamp the
  gradient keeps the clamp's value instead of 0, so a saturated wall can still be brought down. The gradient
  is nerfacto's (and torch-ngp's) trunc_exp; their forward is exp(h) unclamped, this one keeps the clamp, so
  that the forward is the same as clamped_exp's to the bit."""
  return clamped_exp(h)


@trunc_exp.defjvp
def _trunc_exp_jvp(primals, tangents):
  value = clamped_exp(primals[0])
  return value, value * tangents[0]


def density(h, truncated: bool):
  """The hash-grid fields' density from their raw output: trunc_exp (`truncated`) or clamped_exp."""
  return trunc_exp(h) if truncated else clamped_exp(h)


class MLPField(nn.Module):
  """NeRF's MLP (Mildenhall et al. 2020, fig. 7), sized by config.

  Points are positionally encoded, then `depth` dense layers of `width` with ReLU; the encoded input is
  concatenated back after each (0-based) layer index in `skips` (the tutorial's 8x256, whose input rejoins
  after layer `i % 4 == 0 and i > 0`, is skips=(4,)). Without view directions one linear head gives
  (rgb, sigma), as in the Tiny NeRF tutorial. With them (the paper): sigma from the trunk, then a linear
  bottleneck of `width` concatenated with the encoded direction, one layer of width/2 and the rgb head.
  An appearance code per point (`codes_NxA`, the ray's frame's) joins the encoded direction there; it needs
  the view branch (the colour head is then apart from the density).
  """
  # Sizes and switches come from config.model (configs/default.py documents each); no defaults here.
  depth: int
  width: int
  skips: Sequence[int]
  num_frequencies: int
  use_viewdirs: bool
  viewdir_frequencies: int
  density_activation: str
  dtype: jnp.dtype  # matmul dtype: bfloat16 for mixed precision, params stay float32

  @nn.compact
  def __call__(self, points_Nx3, viewdirs_Nx3=None, codes_NxA=None, scales_N=None):
    del scales_N  # (footprints weigh hash-grid levels; NeRF's encoding has none: schema refuses the pair)
    dense = lambda features, name: nn.Dense(features, dtype=self.dtype, name=name)
    encoded = positional = encodings.positional_encoding(points_Nx3, self.num_frequencies)
    x = encoded
    for i in range(self.depth):
      x = nn.relu(dense(self.width, f"trunk_{i}")(x))
      if i in self.skips and i < self.depth - 1:
        x = jnp.concatenate([x, positional], axis=-1)
    activation = _ACTIVATIONS[self.density_activation]
    if not self.use_viewdirs:
      if codes_NxA is not None:
        raise ValueError("appearance codes need the MLP's view branch (model.use_viewdirs)")  # schema refuses
      raw = dense(4, "output")(x).astype(jnp.float32)
      return nn.sigmoid(raw[..., :3]), activation(raw[..., 3])
    sigma = activation(dense(1, "density")(x).astype(jnp.float32)[..., 0])
    bottleneck = dense(self.width, "bottleneck")(x)
    dirs = encodings.positional_encoding(viewdirs_Nx3, self.viewdir_frequencies)
    head_in = [bottleneck, dirs.astype(x.dtype)] + ([] if codes_NxA is None else [codes_NxA.astype(x.dtype)])
    h = nn.relu(dense(self.width // 2, "view")(jnp.concatenate(head_in, -1)))
    return nn.sigmoid(dense(3, "rgb")(h).astype(jnp.float32)), sigma


class HashGridField(nn.Module):
  """Instant-NGP's field: a hash-grid encoding of the point, a small density MLP, a small colour MLP.

  Points are mapped from the box [-bound, bound]^3 into the unit cube (outside it the density is zero).
  Density is exp of the first output of the density MLP, clamped at DENSITY_CLAMP (Instant-NGP's "trunc_exp"
  forward; its gradient too with `trunc_exp`, else 0 above the clamp); the colour MLP
  takes the remaining features and, with view directions, their degree-4 spherical-harmonic encoding, and
  with appearance codes (`codes_NxA`, each point's ray's frame's), the code (nerfacto's colour head).
  With `scale_aware` and each point's footprint (`scales_N`, a standard deviation in world units of the
  field's space), each level's features are weighted by how well its cells resolve it
  (encodings.level_weights, Zip-NeRF's downweighting). `opened_L`: the levels' coarse-to-fine weights during
  training (encodings.coarse_to_fine_weights), None for every level whole.
  """
  # Sizes and switches come from config.model.hashgrid and config.model; no defaults here.
  bound: float
  num_levels: int
  features_per_level: int
  log2_table_size: int
  base_resolution: int
  max_resolution: int
  hidden_width: int
  geo_features: int
  use_viewdirs: bool
  dtype: jnp.dtype
  scale_aware: bool = False
  trunc_exp: bool = False  # model.trunc_exp: the density's gradient survives its clamp (fields.trunc_exp)
  matmul_max_rows: int = 0  # dense levels up to this many rows: matmul lookup (encodings.dense_level_matmul)
  materialize: bool = False  # the encoding's points and rows kept in memory (encodings.materialized: CPUs)
  layout: str = "rows"  # the lookup's layout (compile.hashgrid_layout: encodings.HashGridEncoding.layout)
  lookup: str = "gather"  # the gathered levels' lookup (encodings.HashGridEncoding.lookup)

  @nn.compact
  def __call__(self, points_Nx3, viewdirs_Nx3=None, codes_NxA=None, scales_N=None, opened_L=None):
    unit = (points_Nx3 + self.bound) / (2.0 * self.bound)
    inside = jnp.all((unit >= 0.0) & (unit <= 1.0), axis=-1)
    unit_scales = None
    if self.scale_aware and scales_N is not None:
      unit_scales = jax.lax.stop_gradient(scales_N) / (2.0 * self.bound)
    features = encodings.HashGridEncoding(
        self.num_levels, self.features_per_level, self.log2_table_size, self.base_resolution,
        self.max_resolution, self.matmul_max_rows, self.materialize, self.layout, self.lookup, name="grid")(
            jnp.clip(unit, 0.0, 1.0), unit_scales, opened_L)
    dense = lambda features, name: nn.Dense(features, dtype=self.dtype, name=name)
    h = nn.relu(dense(self.hidden_width, "density_hidden")(features))
    h = dense(1 + self.geo_features, "density_out")(h).astype(jnp.float32)
    sigma = jnp.where(inside, density(h[..., 0], self.trunc_exp), 0.0)
    colour_in = [h[..., 1:]]
    if self.use_viewdirs:
      colour_in.append(encodings.spherical_harmonics_deg4(viewdirs_Nx3))
    if codes_NxA is not None:
      colour_in.append(codes_NxA)
    c = jnp.concatenate(colour_in, axis=-1)
    c = nn.relu(dense(self.hidden_width, "colour_hidden_0")(c))
    c = nn.relu(dense(self.hidden_width, "colour_hidden_1")(c))
    return nn.sigmoid(dense(3, "rgb")(c).astype(jnp.float32)), sigma


class ProposalField(nn.Module):
  """A proposal network (mip-NeRF 360, nerfacto): density only, from a small hash grid and one hidden layer.

  It is queried at many samples per ray (the NeRF field at few), so it must be cheap: a few coarse levels
  (dense tables for the most part), no colour, no view direction. Its density is trained only by the
  interlevel loss, to bound the NeRF's weights. Points outside the box [-bound, bound]^3 have no density.
  """
  bound: float
  num_levels: int
  features_per_level: int
  log2_table_size: int
  base_resolution: int
  max_resolution: int
  hidden_width: int
  dtype: jnp.dtype
  trunc_exp: bool = False  # as HashGridField's
  matmul_max_rows: int = 0  # dense levels of at most this many rows are read by matmuls, not gathers
  materialize: bool = False  # as HashGridField's
  layout: str = "rows"  # as HashGridField's
  lookup: str = "gather"  # as HashGridField's

  @nn.compact
  def __call__(self, points_Nx3):
    unit = (points_Nx3 + self.bound) / (2.0 * self.bound)
    inside = jnp.all((unit >= 0.0) & (unit <= 1.0), axis=-1)
    features = encodings.HashGridEncoding(
        self.num_levels, self.features_per_level, self.log2_table_size, self.base_resolution,
        self.max_resolution, self.matmul_max_rows, self.materialize, self.layout, self.lookup, name="grid")(
            jnp.clip(unit, 0.0, 1.0))
    h = nn.relu(nn.Dense(self.hidden_width, dtype=self.dtype, name="hidden")(features))
    raw = nn.Dense(1, dtype=self.dtype, name="density")(h).astype(jnp.float32)[..., 0]
    return jnp.where(inside, density(raw, self.trunc_exp), 0.0)


def make_proposal_field(model_config, dtype, name: str | None = None, matmul_max_rows: int = 0,
                        materialize: bool = False, layout: str = "rows",
                        lookup: str = "gather") -> ProposalField:
  """A proposal field sized by config.model.proposal, in the box of config.model.hashgrid.bound;
  `matmul_max_rows`, `materialize`, `layout` and `lookup` as for make_field."""
  return ProposalField(bound=model_config.hashgrid.bound,
                       features_per_level=model_config.hashgrid.features_per_level,
                       **dict(model_config.proposal), dtype=dtype, trunc_exp=bool(model_config.trunc_exp),
                       matmul_max_rows=matmul_max_rows,
                       materialize=materialize, layout=layout, lookup=lookup, name=name)


def make_field(model_config, dtype, name: str | None = None, matmul_max_rows: int = 0,
               materialize: bool = False, layout: str = "rows", lookup: str = "gather") -> nn.Module:
  """The field named by `model.field` ('mlp' or 'hashgrid'), sized by config.model.mlp or .hashgrid;
  `matmul_max_rows`: the hash grid's dense levels up to that many rows are looked up by matmuls;
  `materialize`: the hash grid's points and corner rows kept in memory (encodings.materialized);
  `layout`: the hash grid lookup's layout, 'rows' or 'lane_dense' (encodings.HashGridEncoding.layout);
  `lookup`: its gathered levels' lookup, 'gather' or 'sparsecore' (encodings.HashGridEncoding.lookup)."""
  if model_config.field == "mlp":
    mlp = dict(model_config.mlp)
    return MLPField(**dict(mlp, skips=tuple(mlp["skips"])), use_viewdirs=model_config.use_viewdirs, dtype=dtype,
                    name=name)
  if model_config.field == "hashgrid":
    return HashGridField(**dict(model_config.hashgrid), use_viewdirs=model_config.use_viewdirs, dtype=dtype,
                         trunc_exp=bool(model_config.trunc_exp), matmul_max_rows=matmul_max_rows,
                         materialize=materialize, layout=layout, lookup=lookup, name=name)
  raise ValueError(f"unknown model.field {model_config.field!r}")  # nerfpod.schema refuses it first
