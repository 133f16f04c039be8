import jax
import jax.numpy as jnp
import numpy as np

from nerfpod.nerf import sampling


def test_stratified_samples_one_per_bin_sorted_and_within_bounds():
  @jax.jit  # one program rather than one per operation
  def run():
    u = jax.random.uniform(jax.random.key(0), (100, 16))
    return (sampling.stratified(2.0, 6.0, 16, u), sampling.stratified(2.0, 6.0, 16),
            sampling.stratified(2.0, 6.0, 16, jnp.full((1, 16), 0.5)))

  t, midpoints, halves = (np.asarray(x) for x in run())
  assert t.shape == (100, 16)
  assert (t >= 2.0).all() and (t <= 6.0).all() and (np.diff(t, axis=-1) >= 0).all()
  centres = np.linspace(2.0, 6.0, 16)
  assert (np.abs(t - centres) <= (4.0 / 15) / 2 + 1e-6).all()  # each sample stays in its own bin
  np.testing.assert_allclose(midpoints[0], centres, rtol=1e-6)
  np.testing.assert_allclose(halves[0, 1:-1], centres[1:-1], rtol=1e-6)


def test_clip_to_box_matches_brute_force_inside_test():
  rng = np.random.default_rng(3)
  origins = rng.normal(size=(500, 3)) * 3.0
  directions = rng.normal(size=(500, 3))
  lo, hi = jax.jit(sampling.clip_to_box, static_argnums=(2, 3, 4))(  # one program rather than one per operation
      origins.astype(np.float32), directions.astype(np.float32), 0.0, 10.0, 1.0)
  lo, hi = np.asarray(lo)[:, 0], np.asarray(hi)[:, 0]
  t = np.linspace(0.0, 10.0, 20001)
  for i in range(len(origins)):
    inside = np.all(np.abs(origins[i] + t[:, None] * directions[i]) <= 1.0, axis=-1)
    if inside.any():
      assert abs(lo[i] - t[inside][0]) < 1e-3 and abs(hi[i] - t[inside][-1]) < 1e-3
    else:
      assert hi[i] - lo[i] <= 1e-3 + 1e-6 and lo[i] == 0.0
