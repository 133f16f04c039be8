"""The one monitor interface (Writer): each call goes to TensorBoard and, with config.monitor.wandb.mode
'online' or 'offline', to W&B as well, so both sinks get the same values at the same steps; process 0 gets it
from summary_writer."""
import jax
import numpy as np

from nerfpod import storage
from nerfpod.monitor import bucket_events
from nerfpod.monitor.wandb_run import WandbRun
from nerfpod.monitor.warn import warn


def summary_writer(workdir: str, config=None, **kwargs):
  """Process 0: a Writer of workdir's TensorBoard events and, where `config` (the run's) asks for it, of its
  W&B run; None on the other processes: only process 0 writes. kwargs go to tensorboardX.SummaryWriter."""
  if jax.process_index() != 0:
    return None
  import tensorboardX
  tensorboard = tensorboardX.SummaryWriter(logdir=bucket_events.logdir(str(workdir)), **kwargs)
  wandb_run = None
  if config is not None and config.monitor.wandb.mode != "disabled":
    wandb_run = WandbRun.start(workdir, config)
  return Writer(tensorboard, wandb_run, workdir=str(workdir))


class Writer:
  """The one monitor interface: each call goes to TensorBoard and, where there is one, to the W&B run.

  Images are HWC (or CHW, HW: `dataformats`), floats in [0, 1] or uint8. Tables (e.g. metrics per view) are
  text in TensorBoard and tables in W&B; videos (files) go to W&B only (TensorBoard shows the orbit's contact
  sheet)."""

  def __init__(self, tensorboard, wandb_run=None, workdir: str = ""):
    self.tensorboard, self.wandb, self.workdir = tensorboard, wandb_run, workdir

  def add_scalar(self, tag: str, value, step: int) -> None:
    self.tensorboard.add_scalar(tag, value, step)
    if self.wandb is not None:
      self.wandb.add(step, tag, float(value))

  def add_image(self, tag: str, image, step: int, dataformats: str = "CHW") -> None:
    self.tensorboard.add_image(tag, image, step, dataformats=dataformats)
    if self.wandb is not None:
      self.wandb.add_media(step, tag, "Image", to_uint8_hwc(image, dataformats))

  def add_table(self, tag: str, columns: list[str], rows: list[list], step: int) -> None:
    header = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    self.tensorboard.add_text(tag, header + "\n".join("| " + " | ".join(map(str, r)) + " |" for r in rows), step)
    if self.wandb is not None:
      self.wandb.add_media(step, tag, "Table", columns=list(columns), data=[list(r) for r in rows])

  def add_video(self, tag: str, path: str, step: int) -> None:
    """A video file (local or gs://) into W&B; TensorBoard shows the orbit's contact sheet instead."""
    if self.wandb is not None:
      self.wandb.add_video(step, tag, str(path))

  def flush(self) -> None:
    self.tensorboard.flush()
    if self.wandb is not None:
      self.wandb.commit()

  def close(self, exit_code: int = 0) -> None:
    """Closes both sinks; `exit_code` != 0 marks the W&B run as stopped early or failed. TensorBoard's last
    events, where they go to a bucket, are waited on for at most checkpoint.storage_timeout_s (storage.within),
    and not at all where the bucket stopped answering: then they are lost."""
    try:
      storage.within(self.workdir, storage.gcs_timeout(), self.tensorboard.close)
    except storage.NoAnswer as e:
      if e.seconds:  # (0: the bucket had stopped answering before, and the run says so)
        warn(f"the last TensorBoard events could not be uploaded to {self.workdir} (no answer in "
              f"{e.seconds:g} s): lost.")
    if self.wandb is not None:
      self.wandb.finish(exit_code)
      self.wandb = None


def to_uint8_hwc(image, dataformats: str = "HWC") -> np.ndarray:
  """An image as TensorBoard takes it -> uint8 HxWxC, or HxW for one channel."""
  array = np.asarray(image)
  if dataformats == "CHW":
    array = np.moveaxis(array, 0, -1)
  elif dataformats == "HW":
    array = array[..., None]
  elif dataformats != "HWC":
    raise ValueError(f"dataformats {dataformats!r}: use 'HWC', 'CHW' or 'HW'")
  if array.dtype != np.uint8:
    array = np.round(np.clip(np.nan_to_num(array.astype(np.float32)), 0.0, 1.0) * 255.0).astype(np.uint8)
  return array[..., 0] if array.shape[-1] == 1 else array
