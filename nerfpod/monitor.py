"""What a person watches: TensorBoard events and console lines, written by process 0 only."""
import time

import jax
import numpy as np


def summary_writer(workdir: str, **kwargs):
  """A TensorBoard writer of `workdir` on process 0, None on the others: only process 0 writes events."""
  if jax.process_index() != 0:
    return None
  import tensorboardX
  return tensorboardX.SummaryWriter(logdir=workdir, **kwargs)


def duration(seconds: float) -> str:
  """'1h02m' or '3m07s'."""
  seconds = int(round(seconds))
  if seconds >= 3600:
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m"
  return f"{seconds // 60}m{seconds % 60:02d}s"


class Monitor:
  """Training's TensorBoard scalars and images and its console lines (step, loss, PSNR, lr, rays/s, ETA).

  Every process makes one and calls it alike; only process 0's writes anything. `writer` (None elsewhere)
  is shared with evaluation and the orbit, so that all of a run's events go to one file.
  """

  def __init__(self, workdir: str, num_steps: int, batch_size: int):
    self.enabled = jax.process_index() == 0
    self.num_steps, self.batch_size = num_steps, batch_size
    self.writer = summary_writer(workdir, flush_secs=10)
    self._last = None  # (step, time) of the last console line

  def scalars(self, step: int, metrics: dict, lr: float) -> None:
    now = time.perf_counter()
    if self._last is None or step <= self._last[0]:
      self._last = (step, now)
      rays_per_s = None
    else:
      rays_per_s = (step - self._last[0]) * self.batch_size / (now - self._last[1])
      eta = (self.num_steps - step) * (now - self._last[1]) / (step - self._last[0])
      self._last = (step, now)
    if not self.enabled:
      return
    for name, value in metrics.items():
      if np.isfinite(float(value)):  # a skipped step's NaN loss is counted in train/skipped instead
        self.writer.add_scalar(f"train/{name}", float(value), step)
    self.writer.add_scalar("train/learning_rate", lr, step)
    line = (f"step {step:>6d}/{self.num_steps} | loss {float(metrics['loss']):.5f} | "
            f"psnr {float(metrics['psnr']):6.2f} dB | lr {lr:.2e}")
    if rays_per_s is not None:
      self.writer.add_scalar("train/rays_per_sec", rays_per_s, step)
      line += f" | {rays_per_s:,.0f} rays/s | ETA {duration(eta)}"
    print(line, flush=True)

  def images(self, step: int, images: dict) -> None:
    if self.enabled:
      for name, image in images.items():
        self.writer.add_image(name, np.clip(image, 0.0, 1.0), step, dataformats="HWC")

  def close(self) -> None:
    if self.writer is not None:
      self.writer.close()
      self.writer = None
