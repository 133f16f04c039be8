"""A profile of chosen training steps: `train.profile_steps = (first, last)` records a jax.profiler trace of
steps first..last (counted from 1) into the workdir, where TensorBoard's profile tab and xprof read it:

    WORKDIR/plugins/profile/<date_time>/<host>.xplane.pb      (one file per process, each its own host's)

Every process records its own trace (the profiler is per process), so a pod's run leaves one file per host in
one folder. The trace starts before step `first` is dispatched and stops once step `last` has finished on the
devices, so it holds whole steps; a run resumed inside the range records from its first step on, and a run
that stops inside it (preempted, an error) stops the trace where it is.
"""
import sys

import jax


class StepProfile:
  """Starts and stops the trace around the training steps of `steps` ((first, last), or () for none)."""

  def __init__(self, workdir: str, steps):
    self.log_dir = str(workdir)
    self.first, self.last = (int(steps[0]), int(steps[1])) if len(steps) else (0, -1)
    self.active = False

  def starting(self, step: int) -> None:
    """Call before dispatching step `step` (counted from 1)."""
    if not self.active and self.first <= step <= self.last:
      jax.profiler.start_trace(self.log_dir)
      self.active = True

  def finished(self, step: int, state) -> None:
    """Call after dispatching step `step`; at the range's last step, waits for it and stops the trace."""
    if self.active and step >= self.last:
      jax.block_until_ready(state)
      self.close()
      if jax.process_index() == 0:
        print(f"nerfpod: profile of steps {self.first}..{self.last} written under {self.log_dir}/plugins/profile "
              f"(tensorboard --logdir {self.log_dir}, its Profile tab)", file=sys.stderr, flush=True)

  def close(self) -> None:
    """Stops the trace if it runs (a run that stops inside the range)."""
    if self.active:
      self.active = False
      jax.profiler.stop_trace()
