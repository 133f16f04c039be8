"""Training's monitor (Monitor): its scalars and images through the run's Writer, and its console line."""
import time

import jax
import numpy as np

from nerfpod.monitor.writer import summary_writer
from nerfpod.text import duration

class Monitor:
  """Training's scalars and images (TensorBoard, and W&B where config.monitor.wandb asks) and its console
  lines (step, loss, PSNR, lr, with proposal sampling the interlevel term and the NeRF's window, rays/s, ETA).

  Every process makes one and calls it alike; only process 0's writes anything. `writer` (a Writer; None
  elsewhere) is shared with evaluation and the orbit, so that all of a run's events go to one file and one
  W&B run. `config`: the run's (None: TensorBoard only).
  """

  def __init__(self, workdir: str, num_steps: int, batch_size: int, config=None):
    self.enabled = jax.process_index() == 0
    self.num_steps, self.batch_size = num_steps, batch_size
    self.writer = summary_writer(workdir, config, flush_secs=10)
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
    if "interlevel" in metrics:  # (a collapsing proposal sampler drives it to 0: docs/training.md)
      line += f" | interlevel {float(metrics['interlevel']):.2e}"
    if "window" in metrics:
      line += f" | window {float(metrics['window']):.3f}"
    if rays_per_s is not None:
      self.writer.add_scalar("train/rays_per_sec", rays_per_s, step)
      line += f" | {rays_per_s:,.0f} rays/s | ETA {duration(eta)}"
    print(line, flush=True)

  def images(self, step: int, images: dict) -> None:
    if self.enabled:
      for name, image in images.items():
        self.writer.add_image(name, np.clip(image, 0.0, 1.0), step, dataformats="HWC")

  def close(self, exit_code: int = 0) -> None:
    if self.writer is not None:
      self.writer.close(exit_code)
      self.writer = None
