"""config.compile: how nerfpod's programs are compiled, and the process settings that go with them.

    compiler_options        XLA options of the train step and the renderer, by config and backend
    tune_host               process-wide settings a config asks for (called where the process starts)
    gradient_mean_is_ordered  compile.gradient_mean: the ordered mean or one all-reduce
    memory_budget_bytes, step_memory_bytes, fewest_microbatches
                            train.microbatches=0: the fewest micro-batches whose step fits the memory

On CPU, XLA (jaxlib 0.10) hands dots and some elementwise ops to YNNPACK by default. On the 2-core x86 CPU of
docs/results.md, its own emitters with Eigen dots ran every config's step faster, so nerfpod turns YNNPACK
off on CPUs unless `compile.cpu_ynnpack`.
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


def compiler_options(config, backend: str | None = None) -> dict[str, str]:
  """The options to compile `config`'s step and renderer with on `backend` (default: this process's)."""
  if (backend or jax.default_backend()) != "cpu" or config.compile.cpu_ynnpack:
    return {}
  return dict(CPU_WITHOUT_YNNPACK) if _accepted(CPU_WITHOUT_YNNPACK) else {}


# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4


@functools.cache
def reuse_host_memory() -> bool:
  """compile.cpu_reuse_host_memory: glibc's malloc told to keep freed memory for reuse, not to hand it back.

  XLA:CPU allocates a step's buffers afresh at every execution. Left alone, glibc serves each block over its
  mmap threshold with a fresh mmap and unmaps it when freed, so every step pays the kernel to map and zero
  the same memory again: on a 2-core CPU a fifth of a hash-grid job's CPU time went to the kernel. With no
  mmapped blocks and no trimming, freed blocks are reused, for about 10% more peak memory (figures in
  docs/results.md). Applied once per process (glibc only; a MALLOC_* environment variable of the user's own
  wins). Returns whether it was applied."""
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
  """Process-wide settings a config asks for on this backend (today: reuse_host_memory on a CPU). The entry
  points call it once, where the process starts."""
  if jax.default_backend() == "cpu" and config.compile.cpu_reuse_host_memory:
    reuse_host_memory()


def gradient_mean_is_ordered(config, backend: str | None = None) -> bool:
  """compile.gradient_mean: 'ordered' (distributed.ordered_mean), 'pmean' (one all-reduce) or 'auto':
  ordered on a CPU, where simulated topologies are debugged and must agree bit for bit, one all-reduce on
  accelerators, where a pod's step must cost no more than the gradients' all-reduce (`backend`: JAX's
  default unless given; the pod compile tool asks for 'tpu')."""
  choice = config.compile.gradient_mean
  if choice == "auto":
    return (backend or jax.default_backend()) == "cpu"
  return choice == "ordered"


def update_under_cond(backend: str | None = None) -> bool:
  """Whether the train step computes its optimizer update under `jax.lax.cond`, only for steps that keep it,
  rather than always, selecting the old or the new state after (both skip a step whose loss or gradient is
  not finite, with the same bits otherwise). On a CPU the conditional saves the select's pass over the
  parameters and Adam's moments; on accelerators the state is selected, as the TPU compiler, which shards a
  slice's weight update over its chips, moves the whole update across slices around a conditional (the pod
  compile tool's collectives check reports it). `backend`: JAX's default unless given."""
  return (backend or jax.default_backend()) == "cpu"


# The share of an accelerator's memory the train step may take (runs and the pod compile tool alike).
ACCELERATOR_MEMORY_SHARE = 0.85


def memory_budget_bytes(config) -> int:
  """The memory one device's train step may use: on accelerators 85% of what the device reports (the rest
  for the runtime, the renderer, fragmentation); on a CPU, compile.cpu_memory_gib shared by this process's
  simulated devices."""
  accelerator = _accelerator_memory_bytes()
  if accelerator is not None:
    return int(ACCELERATOR_MEMORY_SHARE * accelerator)
  return int(config.compile.cpu_memory_gib * 2**30 / jax.local_device_count())


def device_memory_bytes() -> int:
  """What one device has: an accelerator's memory as it reports it; on a CPU, the host's physical memory
  shared by this process's simulated devices."""
  accelerator = _accelerator_memory_bytes()
  if accelerator is not None:
    return accelerator
  return int(physical_memory_bytes() / jax.local_device_count())


def _accelerator_memory_bytes() -> int | None:
  """An accelerator's memory as it reports it; None on a CPU (or where a device reports none)."""
  stats = jax.local_devices()[0].memory_stats() or {}
  if jax.default_backend() != "cpu" and stats.get("bytes_limit"):
    return int(stats["bytes_limit"])
  return None


def physical_memory_bytes() -> int:
  """This host's physical memory."""
  return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def step_memory_bytes(compiled) -> int | None:
  """What one device needs to run a compiled step, from XLA's own buffer assignment: its arguments, outputs
  and temporaries, less the outputs that reuse (donated) arguments' buffers. None where XLA reports none."""
  analysis = compiled.memory_analysis()
  if analysis is None:
    return None
  return int(analysis.argument_size_in_bytes + analysis.output_size_in_bytes + analysis.temp_size_in_bytes
             - analysis.alias_size_in_bytes)


def fewest_microbatches(per_device: int, budget: int, step_bytes) -> tuple[int, int | None]:
  """The fewest micro-batches (a divisor of the `per_device` rays) whose step fits `budget` bytes per device,
  and that step's bytes; `step_bytes(count)` compiles the step with `count` micro-batches and returns XLA's
  memory analysis of it (step_memory_bytes). Each try is one compilation; the next count tried is scaled by
  how far the last one was over the budget. Where none fits, the most there can be."""
  divisors = [m for m in range(1, per_device + 1) if per_device % m == 0]
  count = 1
  while True:
    need = step_bytes(count)
    if need is None or need <= budget or count == divisors[-1]:
      return count, need
    wanted = count * need / max(budget, 1)  # activations dominate, and shrink with the slice
    count = next((m for m in divisors if m > count and m >= wanted), divisors[-1])
