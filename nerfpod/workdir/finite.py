"""Whether a pytree's values are all finite: the last check before a train state is saved or after it is
restored (a NaN must never replace a good checkpoint). The train step tests its loss and gradient norm instead
(nerfpod/run/step.py), before its update."""
import jax
import jax.numpy as jnp


@jax.jit
def all_finite(tree) -> jax.Array:
  """Whether every floating-point leaf of `tree` is finite (a scalar bool, on the leaves' devices)."""
  checks = [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.inexact)]
  return jnp.all(jnp.stack(checks)) if checks else jnp.asarray(True)
