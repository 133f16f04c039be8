"""XLA compiler options of the train step and the renderer, by config and backend.

On CPU, XLA (jaxlib 0.10) hands dots and some elementwise ops to YNNPACK by default. On the 2-core CPU the
README's figures come from, its own emitters with Eigen dots run the hash-grid steps about 1.5x and the
tutorial's 8x256 MLP about 1.1x faster, so nerfpod turns YNNPACK off there unless `compile.cpu_ynnpack`.
The options apply per compiled function (`jax.jit(compiler_options=...)`), not through XLA_FLAGS: an
option a future jaxlib no longer knows is then dropped with a warning instead of aborting the process.
"""
import ctypes
import functools
import os
import platform

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


# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4


@functools.cache
def reuse_host_memory() -> bool:
  """compile.cpu_reuse_host_memory: glibc's malloc told to keep freed memory for reuse, not to hand it back.

  XLA:CPU allocates a step's buffers afresh at every execution. Left alone, glibc serves each block over its
  mmap threshold with a fresh mmap and unmaps it when freed, so every step pays the kernel to map and zero
  the same memory again: on the 2-core CPU a fifth of a hash-grid job's CPU time went to the kernel. With no
  mmapped blocks and no trimming, freed blocks are reused: the same 600 steps of configs/tiny_fast.py took
  65.5 s instead of 78.1 s start to finish (kernel time 8 s instead of 19 s) for 10% more peak memory.
  Applied once per process (glibc only; a MALLOC_* environment variable of the user's own wins). Returns
  whether it was applied."""
  if platform.libc_ver()[0] != "glibc" or any(k.startswith("MALLOC_") for k in os.environ):
    return False
  try:
    mallopt = ctypes.CDLL(None).mallopt
  except (OSError, AttributeError):
    return False
  mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
  # Trimming only once over 2 GiB is free at the top of the heap (mallopt takes a C int).
  return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))


def tune_host(config) -> None:
  """Process-wide settings a config asks for on this backend (today: reuse_host_memory on a CPU)."""
  if jax.default_backend() == "cpu" and config.get("compile", {}).get("cpu_reuse_host_memory", False):
    reuse_host_memory()
