"""Step functions along rays, as (edges, weights) pairs: the arithmetic of importance and proposal sampling.

A ray's histogram is `edges_RxB1` (R, B+1), increasing, and `weights_RxB` (R, B) >= 0: weight i lies on
[edges[i], edges[i+1]] with uniform density. `inverse_cdf` is the one inverse-CDF sampler: the paper's
hierarchical sampling draws its fine samples with it from the coarse weights (nerf/model.py), and proposal
sampling (mip-NeRF 360) draws the NeRF's intervals from a cheap field's histogram (`sample_intervals`); the
cheap field learns to *bound* the NeRF's histogram (`interlevel_loss`, mip-NeRF 360 eq. 12-13), so that its
samples cover every place the NeRF puts weight; `distortion_loss` (eq. 15) pulls each ray's weight together
into one compact interval. `blurred_interlevel_loss` is Zip-NeRF's anti-aliased form of the interlevel loss:
the NeRF's histogram blurred by a box and resampled onto the proposal's intervals (`blurred_weights`), a
target that moves smoothly with the intervals' positions instead of jumping as an interval's edge crosses
another's (z-aliasing).

Everything here works in any 1-D domain; the model uses the normalised ray distance s in [0, 1] (so that the
losses do not depend on the scene's scale). Shapes are static: B and the number of samples are Python ints,
and every search is a broadcast comparison (no data-dependent shapes, which TPUs and jit need).
"""
import jax
import jax.numpy as jnp

# Keeps divisions by a weight finite (multinerf's eps: float32's machine epsilon).
EPS = float(jnp.finfo(jnp.float32).eps)


def _searchsorted(sorted_RxK, values_RxN, strict: bool = False):
  """(R, N) counts of entries of each row of `sorted_RxK` that are <= each value (< with `strict`): the index
  of the first entry > value (>= value). A broadcast comparison, O(N K), which beats a binary search at the
  sizes used here (tens of entries) and has static shapes."""
  compare = jnp.less if strict else jnp.less_equal
  return jnp.sum(compare(sorted_RxK[..., None, :], values_RxN[..., :, None]), axis=-1)


def inverse_cdf(edges_RxB1, weights_RxB, uniform_RxN):
  """The points whose CDF under the histogram is `uniform_RxN` (numbers in [0, 1]), (R, N).

  Zero-weight intervals are never hit (except by u = 0 or 1 exactly); a ray whose weights are all zero
  gets the uniform distribution over its edges' span. No gradient flows through the result.
  """
  total = jnp.sum(weights_RxB, axis=-1, keepdims=True)
  uniform_weights = jnp.ones_like(weights_RxB) / weights_RxB.shape[-1]
  pdf = jnp.where(total > 0, weights_RxB / jnp.where(total > 0, total, 1.0), uniform_weights)
  cdf = jnp.concatenate([jnp.zeros_like(pdf[..., :1]), jnp.minimum(1.0, jnp.cumsum(pdf, axis=-1))], axis=-1)
  cdf = cdf.at[..., -1].set(1.0)
  above = jnp.clip(_searchsorted(cdf, uniform_RxN), 1, cdf.shape[-1] - 1)  # interval i = above - 1
  below = above - 1
  cdf_lo = jnp.take_along_axis(cdf, below, axis=-1)
  cdf_hi = jnp.take_along_axis(cdf, above, axis=-1)
  edge_lo = jnp.take_along_axis(edges_RxB1, below, axis=-1)
  edge_hi = jnp.take_along_axis(edges_RxB1, above, axis=-1)
  span = cdf_hi - cdf_lo
  frac = jnp.clip((uniform_RxN - cdf_lo) / jnp.where(span > 0, span, 1.0), 0.0, 1.0)
  return jax.lax.stop_gradient(edge_lo + frac * (edge_hi - edge_lo))


def stratified_uniforms(num: int, jitter_RxN=None, shape=()):
  """N numbers in [0, 1], one per stratum [i/N, (i+1)/N): at `jitter` within each (training), or at the
  strata's centres (evaluation, `jitter` None; `shape` gives the leading shape then)."""
  if jitter_RxN is None:
    return jnp.broadcast_to((jnp.arange(num) + 0.5) / num, tuple(shape) + (num,))
  return (jnp.arange(num) + jitter_RxN) / num


def sample_intervals(edges_RxB1, weights_RxB, num: int, jitter_RxN=None, domain=(0.0, 1.0)):
  """`num` (>= 2) intervals drawn from the histogram: their (R, num + 1) edges, sorted, without gradient.

  `num` points are drawn by stratified inverse CDF (`jitter`: (R, num) numbers in [0, 1), or None for the
  strata's centres); the edges are the midpoints between neighbouring points, and the outermost points
  mirrored about their neighbouring midpoint, clipped to `domain` (multinerf's sample_intervals). Where the
  histogram is dense the intervals are short: the next field is queried where the weight is.
  """
  u = stratified_uniforms(num, jitter_RxN, weights_RxB.shape[:-1])
  points = inverse_cdf(edges_RxB1, weights_RxB, u)
  mids = 0.5 * (points[..., 1:] + points[..., :-1])
  first = jnp.maximum(domain[0], 2.0 * points[..., :1] - mids[..., :1])
  last = jnp.minimum(domain[1], 2.0 * points[..., -1:] - mids[..., -1:])
  edges = jnp.concatenate([first, mids, last], axis=-1)
  return jax.lax.stop_gradient(edges)


def resampling_weights(weights_RxB, padding: float = 0.0, anneal=None):
  """The histogram the next round draws its intervals from (R, B): the proposal's weights raised to `anneal`
  (a number in [0, 1], or None for 1) plus `padding` in every interval (nerfacto's ProposalNetworkSampler and
  PDFSampler: w^a + padding).

  Without either, resampling has an absorbing state: once a proposal puts nearly all its mass in one interval,
  every next sample lands inside it, every next interval overlaps it, `outer` is about 1 everywhere and the
  interlevel loss is 0 with no gradient whatever the next field's weights are, so the proposal never learns
  again (tests/test_proposal_trap.py). `padding` keeps that much of every interval of this round reachable (a
  share of the samples follows this round's own intervals, so the next window spans the whole ray); `anneal`
  below 1 flattens the histogram early in training (w^0 = 1: the intervals alike), before the proposal has
  learnt where matter is.
  """
  if anneal is not None:  # (w at 1 itself, not pow's rounding of it: annealing over, the step is the plain one)
    weights_RxB = jnp.where(anneal < 1.0, jnp.power(weights_RxB, anneal), weights_RxB)
  return weights_RxB + padding if padding else weights_RxB


def anneal_exponent(step, anneal_steps: int, slope: float = 10.0):
  """nerfacto's annealing of the proposal weights' exponent at `step`: x = min(step / anneal_steps, 1), then
  slope x / ((slope - 1) x + 1), rising from 0 to 1 (fast at first: 0.53 at a tenth of the way); 1 where
  `anneal_steps` is 0."""
  if not anneal_steps:
    return jnp.ones((), jnp.float32)
  x = jnp.clip(jnp.asarray(step, jnp.float32) / anneal_steps, 0.0, 1.0)
  return slope * x / ((slope - 1.0) * x + 1.0)


def outer(edges_RxB1, env_edges_RxK1, env_weights_RxK):
  """For each interval of `edges`, the summed weight of every interval of the envelope histogram that
  overlaps it, (R, B): the smallest value a histogram on the envelope's intervals may hold there if its
  mass is to cover that interval (mip-NeRF 360 eq. 13)."""
  cumulative = jnp.concatenate([jnp.zeros_like(env_weights_RxK[..., :1]), jnp.cumsum(env_weights_RxK, -1)], -1)
  k = env_weights_RxK.shape[-1]
  # The first envelope interval each interval overlaps, j with env[j] <= left < env[j + 1], and the last,
  # j with env[j] < right <= env[j + 1] (clipped to 0..K-1): intervals that only touch do not overlap.
  first = jnp.clip(_searchsorted(env_edges_RxK1, edges_RxB1[..., :-1]) - 1, 0, k - 1)
  last = jnp.clip(_searchsorted(env_edges_RxK1, edges_RxB1[..., 1:], strict=True) - 1, 0, k - 1)
  lo = jnp.take_along_axis(cumulative, first, axis=-1)     # mass before the first overlapped
  hi = jnp.take_along_axis(cumulative, last + 1, axis=-1)  # mass up to the last overlapped
  return jnp.maximum(hi - lo, 0.0)


def interlevel_loss(edges_RxB1, weights_RxB, env_edges_RxK1, env_weights_RxK, radius: float | None = None,
                    eps: float = EPS):
  """mip-NeRF 360's proposal loss (eq. 12), per ray (R,): sum_i max(0, w_i - outer_i)^2 / (w_i + eps).

  `weights` are the NeRF's (the target: pass them through stop_gradient), `env_*` the proposal's. Zero
  exactly when the proposal's histogram bounds the NeRF's everywhere; the gradient raises the proposal's
  weights where they fall short. With a `radius` (train.interlevel_blur), Zip-NeRF's anti-aliased form
  instead (blurred_interlevel_loss).
  """
  if radius is not None:
    return blurred_interlevel_loss(edges_RxB1, weights_RxB, env_edges_RxK1, env_weights_RxK, radius, eps)
  bound = outer(edges_RxB1, env_edges_RxK1, env_weights_RxK)
  return jnp.sum(jnp.maximum(0.0, weights_RxB - bound)**2 / (weights_RxB + eps), axis=-1)


def _sum_of_uniforms_cdf(z, short, long):
  """The CDF at z of the sum of two independent uniform variables on [0, short] and [0, long]
  (0 <= short <= long): a trapezoid's density, rising over [0, short], flat to `long`, falling to short + long.
  Piecewise, so that each piece is computed from small numbers (no cancellation of large squares), and exact
  where short = 0 (the uniform CDF on [0, long]) or long = 0 (a step at 0)."""
  product = jnp.maximum(short * long, jnp.finfo(jnp.float32).tiny)
  rising = z * z / (2.0 * product)
  flat = (z - 0.5 * short) / jnp.maximum(long, jnp.finfo(jnp.float32).tiny)
  falling = 1.0 - (short + long - z)**2 / (2.0 * product)
  return jnp.where(z <= 0.0, 0.0, jnp.where(z >= short + long, 1.0,
                   jnp.where(z < short, rising, jnp.where(z <= long, flat, falling))))


def blurred_weights(edges_RxB1, weights_RxB, query_RxK1, radius: float):
  """The histogram's weights on the intervals of `query` (R, K), its density first blurred by a box of
  half-width `radius` (Zip-NeRF's blur_and_resample_weights): interval i's weight, uniform on [e_i, e_i+1],
  becomes a trapezoid over [e_i - radius, e_i+1 + radius], and query interval k receives the part of every
  trapezoid that lies on it. radius = 0 resamples the histogram exactly; weight blurred past the query's ends
  is not counted. Each interval against each query edge (R x K+1 x B, tens of each): every part is computed
  from that interval's own numbers, so an interval far from a query edge gives it exactly 0 or 1."""
  lo = edges_RxB1[..., None, :-1]                     # (R, 1, B)
  width = jnp.diff(edges_RxB1, axis=-1)[..., None, :]
  box = 2.0 * radius
  short, long = jnp.minimum(width, box), jnp.maximum(width, box)
  # The blurred interval's CDF at each query edge (R, K+1, B): the sum of U[lo, lo + width] and U[-r, r].
  cdf = _sum_of_uniforms_cdf(query_RxK1[..., :, None] - (lo - radius), short, long)
  mass_before = jnp.sum(weights_RxB[..., None, :] * cdf, axis=-1)  # (R, K+1)
  return jnp.maximum(jnp.diff(mass_before, axis=-1), 0.0)


def blurred_interlevel_loss(edges_RxB1, weights_RxB, env_edges_RxK1, env_weights_RxK, radius: float,
                            eps: float = EPS):
  """Zip-NeRF's anti-aliased interlevel loss, per ray (R,): sum_k max(0, w~_k - p_k)^2 / (p_k + eps) over
  the proposal's intervals k, w~ the NeRF's weights blurred by a box of half-width `radius` and resampled
  onto them (blurred_weights), p the proposal's weights. As interlevel_loss, pass the NeRF's weights through
  stop_gradient; the gradient raises the proposal's weights where they fall short of the blurred target."""
  target = blurred_weights(edges_RxB1, weights_RxB, env_edges_RxK1, radius)
  return jnp.sum(jnp.maximum(0.0, target - env_weights_RxK)**2 / (env_weights_RxK + eps), axis=-1)


def distortion_loss(edges_RxB1, weights_RxB):
  """mip-NeRF 360's distortion loss (eq. 15), per ray (R,): the double integral of w(u) w(v) |u - v| over the
  ray, w being the histogram's density: sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (e_{i+1} - e_i), m the
  midpoints. The pairwise sum is computed in O(B) with prefix sums (the midpoints are sorted)."""
  mids = 0.5 * (edges_RxB1[..., 1:] + edges_RxB1[..., :-1])
  weight_before = jnp.cumsum(weights_RxB, axis=-1) - weights_RxB          # sum_{j<i} w_j
  moment_before = jnp.cumsum(weights_RxB * mids, axis=-1) - weights_RxB * mids  # sum_{j<i} w_j m_j
  inter = 2.0 * jnp.sum(weights_RxB * (mids * weight_before - moment_before), axis=-1)
  intra = jnp.sum(weights_RxB**2 * jnp.diff(edges_RxB1, axis=-1), axis=-1) / 3.0
  return inter + intra
