"""Stopping training at a step every process agrees on, after a SIGTERM (preemption) or a first Ctrl-C.

A TPU VM gets SIGTERM before maintenance. With several processes, JAX's distributed runtime catches it on
whichever host gets it and makes all hosts agree on one step (`reached`: the step after the furthest one any
process had reached); with one process, a SIGTERM handler sets a flag. Either way the training loop saves
that step, whatever the checkpoint interval, and stops there.

A first Ctrl-C (SIGINT) in training is a preemption too (the current step is saved, the run stops and exits
with checkpoint.preempted_exit_code); a second one stops the process at once, like a kill (exit 130). Ctrl-C
outside training's steps is the command's (errors.Command.run).
"""
import os
import signal
import sys
import threading

import jax

from nerfpod.errors import INTERRUPTED_EXIT_CODE


def _service_reached(step: int) -> bool:
  """JAX's preemption sync point (all processes agree on the step); False where the service is off."""
  from jax.experimental import multihost_utils
  try:
    return multihost_utils.reached_preemption_sync_point(step)
  except RuntimeError:  # the preemption service is disabled (jax_enable_preemption_service)
    return False


class Watch:
  """The preemption watch of one training run: `reached(step)` is True at the one step all processes agree
  to stop at. Use as a context manager, or call close() (gives the signals back to their handlers)."""

  def __init__(self, resumed_step: int):
    """`resumed_step`: the step the run resumes after (0 for a new run)."""
    self._agree = jax.process_count() > 1
    self._signalled = threading.Event()
    self._interrupts = 0
    self._previous_sigterm = self._previous_sigint = None
    main_thread = threading.current_thread() is threading.main_thread()
    if self._agree:
      # Tell the preemption service where this run stands: a SIGTERM before the first step then makes the
      # processes agree on the first step, not on step 1.
      self.reached(resumed_step)
    elif main_thread:
      # One process (jax.distributed or not): nobody to agree with, so just note the signal. (JAX's service
      # would also do, but orbax's save-finalising thread reports older steps to it, which with one process
      # can make the agreed step one the loop has already passed.)
      self._previous_sigterm = signal.signal(signal.SIGTERM, lambda *_: self._signalled.set())
    if main_thread:
      self._previous_sigint = signal.signal(signal.SIGINT, self._on_sigint)

  def _on_sigint(self, *_):
    """A first Ctrl-C: a preemption (the current step is saved, then the run stops); a second: stop now."""
    self._interrupts += 1
    if self._interrupts > 1:
      print("nerfpod: interrupted again: stopping now, without saving", file=sys.stderr, flush=True)
      os._exit(INTERRUPTED_EXIT_CODE)
    print("nerfpod: interrupted: saving the current step, then stopping (Ctrl-C again to stop at once)",
          file=sys.stderr, flush=True)
    if self._agree:
      os.kill(os.getpid(), signal.SIGTERM)  # JAX's preemption service makes every process agree on the step
    else:
      self._signalled.set()

  def reached(self, step: int) -> bool:
    """True at the step where every process stops after a SIGTERM reached any of them.

    Call it at every step, with the same steps on every process (the distributed runtime picks the step
    after the furthest one any process had reached when the signal came).
    """
    if self._agree:
      return _service_reached(step)
    return self._signalled.is_set()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def close(self) -> None:
    """Gives SIGTERM and SIGINT back to their previous handlers. Once."""
    if self._previous_sigterm is not None:
      signal.signal(signal.SIGTERM, self._previous_sigterm)
      self._previous_sigterm = None
    if self._previous_sigint is not None:
      signal.signal(signal.SIGINT, self._previous_sigint)
      self._previous_sigint = None
