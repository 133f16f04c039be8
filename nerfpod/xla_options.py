"""XLA compiler options of the train step and the renderer, by config and backend.

On CPU, XLA (jaxlib 0.10) hands dots and some elementwise ops to YNNPACK by default. On the 2-core CPU the
README's figures come from, its own emitters with Eigen dots run the hash-grid steps about 1.5x and the
tutorial's 8x256 MLP about 1.1x faster, so nerfpod turns YNNPACK off there unless `compile.cpu_ynnpack`.
The options apply per compiled function (`jax.jit(compiler_options=...)`), not through XLA_FLAGS: an
option a future jaxlib no longer knows is then dropped with a warning instead of aborting the process.
"""
import functools

import jax
import jax.numpy as jnp
from absl import logging

CPU_WITHOUT_YNNPACK = (("xla_cpu_experimental_ynn_fusion_type", ""),)


@functools.cache
def _accepted(options: tuple[tuple[str, str], ...]) -> bool:
  """Whether this jaxlib compiles with `options` (checked once per process on a trivial function)."""
  try:
    jax.jit(lambda x: x + 1, compiler_options=dict(options)).lower(jnp.zeros(())).compile()
    return True
  except jax.errors.JaxRuntimeError as e:
    logging.warning("XLA does not take the compiler options %s (%s); compiling with its defaults.",
                    dict(options), str(e).splitlines()[0])
    return False


def compiler_options(config) -> dict[str, str]:
  """The options to compile `config`'s step and renderer with on this process's backend."""
  if jax.default_backend() != "cpu" or config.get("compile", {}).get("cpu_ynnpack", False):
    return {}
  return dict(CPU_WITHOUT_YNNPACK) if _accepted(CPU_WITHOUT_YNNPACK) else {}
