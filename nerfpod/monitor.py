"""What a person watches: TensorBoard events, a Weights & Biases run (optional) and console lines, written by
process 0 only.

One interface, two sinks: `summary_writer` gives process 0 a `Writer` whose add_scalar / add_image /
add_table / add_video / flush / close go to TensorBoard and, with config.monitor.wandb.mode 'online' or
'offline', to W&B as well. Training (Monitor), evaluation and the orbit call only the Writer, so both sinks
get the same values at the same steps.

TensorBoard in a bucket (a gs:// workdir): Cloud Storage objects cannot be appended to, and tensorboardX's own
gs:// writer uploads the whole event file again at each flush, which sends a run's events N/2 times over N
flushes. The Writer's event file there is a series of objects instead, NAME.00000000, NAME.00000001, ...
(NAME: tensorboardX's event file name, in the workdir itself), each flush uploading only what was written
since the last one (BucketEventFile); TensorBoard reads every events.out.tfevents.* file of a folder, in name
order, as one run. A local workdir has tensorboardX's one event file, as before.

W&B (the `wandb` extra): the run's id is kept in workdir/wandb.json, so a resumed run continues the same W&B
run; the same file records the last step W&B got and the metrics it got at that step, and a resumed run
(which re-trains the steps after its newest checkpoint) sends W&B nothing below that step nor any metric
again at it, so W&B's steps never go backwards. Its x-axis is the metric `step`. A W&B failure (no network,
a bad key, ...) is one warning on stderr, and the run goes on with TensorBoard alone.
"""
import json
import os
import secrets
import shutil
import string
import sys
import tempfile
import threading
import time

import jax
import numpy as np

from nerfpod import storage
from nerfpod.text import duration

WANDB_RECORD = "wandb.json"  # in the workdir: {"id", "step", "keys"}
WANDB_STEP = "step"          # the W&B metric every other metric is plotted against
WANDB_FLUSH_SECONDS = 1.0    # W&B's .wandb file is written this often (its default, 15 s, loses more to a kill)


def summary_writer(workdir: str, config=None, **kwargs):
  """Process 0: a Writer of workdir's TensorBoard events and, where `config` (the run's) asks for it, of its
  W&B run; None on the other processes: only process 0 writes. kwargs go to tensorboardX.SummaryWriter."""
  if jax.process_index() != 0:
    return None
  import tensorboardX
  tensorboard = tensorboardX.SummaryWriter(logdir=_bucket_events_logdir(str(workdir)), **kwargs)
  wandb_run = None
  if config is not None and config.monitor.wandb.mode != "disabled":
    wandb_run = WandbRun.start(workdir, config)
  return Writer(tensorboard, wandb_run, workdir=str(workdir))


BUCKET_EVENTS_SCHEME = "nerfpod-gs"  # tensorboardX's logdir for a gs:// workdir: its files are BucketEventFiles
SEGMENT_DIGITS = 8  # NAME.00000000: names that sort in upload order for 10^8 flushes (31 years at one per 10 s)


def _bucket_events_logdir(workdir: str) -> str:
  """What tensorboardX is given as the logdir of `workdir`: itself, unless it is in a bucket (gs://), where
  tensorboardX's writer factory for BUCKET_EVENTS_SCHEME writes BucketEventFiles to the same folder."""
  if not workdir.startswith("gs://"):
    return workdir
  from tensorboardX import record_writer
  record_writer.register_writer_factory(BUCKET_EVENTS_SCHEME, _BucketEventFiles)
  return BUCKET_EVENTS_SCHEME + workdir[len("gs"):]


class _BucketEventFiles:
  """tensorboardX's writer factory (record_writer.register_writer_factory) for BUCKET_EVENTS_SCHEME paths."""

  @staticmethod
  def open(path: str) -> "BucketEventFile":
    # tensorboardX's writer thread, behind which the training loop's events queue up, never waits on the bucket
    return BucketEventFile("gs" + path[len(BUCKET_EVENTS_SCHEME):], flush_wait_s=0.0)

  @staticmethod
  def directory_check(path: str) -> None:
    """A bucket needs no folder made."""


class BucketEventFile:
  """An event file at gs://BUCKET/NAME as a series of objects NAME.00000000, NAME.00000001, ...: each upload
  holds what was flushed since the previous one, as the next object, so each byte goes up once.

  tensorboardX calls write (a record in four pieces) and flush under one lock, so that an object holds whole
  records: TensorBoard reads the objects of a folder in name order as one stream of events. The numbers go on
  after those already in the bucket (a writer opened again in the same second, so with the same NAME), and an
  object is created only where there is none of its name. Bytes that fail to upload (the network, the
  bucket) stay and go with the next flush; what a killed run loses is what it had not flushed yet, and what
  it had flushed in the last moment, before its upload.

  Uploads go from a thread of the file's own, in order: a flush hands its bytes over and waits for their upload
  for at most `flush_wait_s` (default: checkpoint.storage_timeout_s, storage.gcs_timeout), and only while the
  bucket answers; tensorboardX's files wait 0 s, so that a bucket that stops answering never holds its writer
  thread, nor the training loop whose events queue up behind it. close() waits for what was flushed, for at
  most checkpoint.storage_timeout_s."""

  def __init__(self, url: str, flush_wait_s: float | None = None):
    self.url = url
    self.flush_wait_s = flush_wait_s
    self.name = url[len("gs://"):].partition("/")[2]  # the objects' names' stem in the bucket
    self.pending = bytearray()  # written since the last flush (tensorboardX's thread)
    self.bucket = None
    self.number = None  # the next object's, known at the first upload
    self.failed = False  # the last upload failed (and said so)
    self._flushed = bytearray()  # flushed, not uploaded yet (the uploader's, under _changed)
    self._changed = threading.Condition()
    self._asked = self._answered = 0  # flushes handed over; the last one the uploader has tried
    self._closing = False
    self._uploader = None

  def write(self, data: bytes) -> None:
    self.pending += data

  def flush(self) -> None:
    if storage.stopped(self.url):  # (the run stops on it, with one sentence)
      return
    with self._changed:
      self._flushed += self.pending
      self.pending.clear()
      if not self._flushed:
        return
      self._asked += 1
      asked = self._asked
      if self._uploader is None:
        self._uploader = threading.Thread(target=self._upload_flushed, name="nerfpod-events-upload", daemon=True)
        self._uploader.start()
      self._changed.notify_all()
      wait = storage.gcs_timeout() if self.flush_wait_s is None else self.flush_wait_s
      if not self.failed and wait > 0:
        self._changed.wait_for(lambda: self._answered >= asked, timeout=wait)

  def close(self) -> None:
    self.flush()
    with self._changed:
      if not storage.stopped(self.url):
        self._changed.wait_for(lambda: self._answered >= self._asked, timeout=storage.gcs_timeout())
      self._closing = True
      self._changed.notify_all()
      if self._flushed and not storage.stopped(self.url):
        _warn(f"{len(self._flushed)} bytes of TensorBoard events could not be uploaded to {self.url}: lost.")
      self._flushed.clear()

  def _upload_flushed(self) -> None:
    """The uploader: what was flushed, in one object per try, each time a flush asks."""
    while True:
      with self._changed:
        self._changed.wait_for(lambda: self._asked > self._answered or self._closing)
        if self._closing or storage.stopped(self.url):
          return
        asked, data = self._asked, bytes(self._flushed)
      error = None
      try:
        self._upload(data)
      except Exception as e:  # noqa: BLE001 (the client's errors vary: no network, no access, ...)
        error = e
      with self._changed:
        if error is None:
          del self._flushed[:len(data)]
        elif not self.failed and not storage.stopped(self.url):
          _warn(f"TensorBoard events could not be uploaded to {self.url} ({_reason(error)}); the next flush "
                f"tries again.")
        self.failed = error is not None
        self._answered = asked
        self._changed.notify_all()

  def _upload(self, data: bytes) -> None:
    from google.api_core import exceptions
    # Each request bounded, and its retries too (checkpoint.storage_timeout_s: storage.bound_clients): a
    # bucket that stops answering fails an upload instead of holding tensorboardX's writer thread, and the
    # training loop whose events queue up behind it.
    bounds = {"timeout": storage.gcs_timeout(), "retry": storage.gcs_retry()}
    if self.bucket is None:
      self.bucket = storage.gcs_bucket(self.url).bucket  # (its endpoint and credentials as the lock's)
    if self.number is None:
      numbers = [blob.name[len(self.name) + 1:] for blob in self.bucket.list_blobs(prefix=self.name + ".",
                                                                                    **bounds)]
      self.number = 1 + max((int(n) for n in numbers if n.isdigit()), default=-1)
    while True:
      blob = self.bucket.blob(f"{self.name}.{self.number:0{SEGMENT_DIGITS}d}")
      try:
        blob.upload_from_string(data, content_type="application/octet-stream", if_generation_match=0,
                                timeout=bounds["timeout"], retry=storage.gcs_retry_if_generation())
      except exceptions.PreconditionFailed:  # the name is taken: by this upload (a retry of one that was
        if blob.download_as_bytes(**bounds) != data:  # stored, its answer lost) or another writer's: the next
          self.number += 1
          continue
      self.number += 1
      return


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
        _warn(f"the last TensorBoard events could not be uploaded to {self.workdir} (no answer in "
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


def read_wandb_record(workdir: str) -> dict:
  """workdir/wandb.json: {"id": the W&B run's id, "step": the last step W&B got, "keys": the metrics it got
  at that step}; {} where there is none (or it cannot be read: a new W&B run then starts)."""
  path = storage.path(workdir) / WANDB_RECORD
  try:
    record = json.loads(path.read_text())
  except (OSError, ValueError):
    return {}
  return record if isinstance(record, dict) and isinstance(record.get("id"), str) else {}


def new_run_id() -> str:
  """A new W&B run id: 8 random lowercase letters and digits, as W&B's own."""
  return "".join(secrets.choice(string.ascii_lowercase + string.digits) for _ in range(8))


def _write_json(path, value: dict) -> None:
  """Whole or not at all (PATH.tmp, then renamed)."""
  tmp = path.parent / f"{path.name}.tmp"
  tmp.write_text(json.dumps(value, indent=2))
  tmp.replace(path)


def _warn(message: str) -> None:
  print(f"nerfpod: warning: {message}", file=sys.stderr, flush=True)


class WandbRun:
  """The W&B side of a Writer: one row of metrics per step, sent when the step changes or on flush, with
  nothing below the last step W&B got (workdir/wandb.json) nor a metric it already has at that step."""

  def __init__(self, run, workdir: str, record: dict):
    self.run, self.path = run, storage.path(workdir) / WANDB_RECORD
    self.record = {"id": record["id"], "step": record.get("step"), "keys": list(record.get("keys", []))}
    self.pending_step, self.pending = None, {}
    self.copies = []  # local copies of gs:// videos, removed at the end

  @classmethod
  def start(cls, workdir: str, config) -> "WandbRun | None":
    """Starts (or resumes: the id in workdir/wandb.json) the W&B run of config.monitor.wandb, with the whole
    config; None, after one warning, where W&B fails."""
    wc = config.monitor.wandb
    try:
      if wc.mode == "online":
        _check_wandb_server()
      import wandb
      record = read_wandb_record(workdir)
      if not record:  # the id first: a run killed during wandb.init still resumes the same W&B run
        record = {"id": new_run_id(), "step": None, "keys": []}
        storage.path(workdir).mkdir(parents=True, exist_ok=True)
        _write_json(storage.path(workdir) / WANDB_RECORD, record)
      local = not storage.is_url(workdir)
      try:  # a private setting of W&B's: where a version no longer has it, W&B's own default
        settings = wandb.Settings(x_transaction_log_flush_interval=WANDB_FLUSH_SECONDS)
      except Exception:  # noqa: BLE001
        settings = None
      run = wandb.init(
          id=record["id"], resume="allow", mode=wc.mode, allow_val_change=True,
          project=wc.project or os.environ.get("WANDB_PROJECT") or "nerfpod", entity=wc.entity or None,
          name=wc.name or os.environ.get("WANDB_NAME") or (os.path.basename(os.path.normpath(workdir))
                                                          if local else None),
          tags=list(wc.tags) or None, config=json.loads(config.to_json_best_effort()),
          dir=workdir if local and not os.environ.get("WANDB_DIR") else None, settings=settings)
      run.define_metric(WANDB_STEP)
      run.define_metric("*", step_metric=WANDB_STEP)
    except Exception as e:  # noqa: BLE001 (no network, a bad key, a broken install: W&B's own errors vary)
      _warn(f"Weights & Biases could not start ({_reason(e)}); the run goes on with TensorBoard only.")
      return None
    return cls(run, workdir, record)

  def add(self, step: int, key: str, value) -> None:
    if self.run is None:
      return
    step = int(step)
    if self.pending_step is not None and step != self.pending_step:
      self.commit()
    self.pending_step = step
    self.pending[key] = value

  def add_media(self, step: int, key: str, kind: str, *args, **kwargs) -> None:
    """A wandb.Image, wandb.Table, ... (by name: wandb is imported only where a run exists)."""
    if self.run is not None:
      self._safely(lambda: self.add(step, key, getattr(sys.modules["wandb"], kind)(*args, **kwargs)))

  def add_video(self, step: int, key: str, path: str) -> None:
    if self.run is None:
      return

    def add():
      import wandb
      local = path
      if storage.is_url(path):  # W&B reads local files: a local copy of a gs:// video first
        self.copies.append(tempfile.mkdtemp(prefix="nerfpod-wandb-"))
        local = os.path.join(self.copies[-1], os.path.basename(path))
        storage.path(path).copy(storage.path(local), overwrite=True)
      self.add(step, key, wandb.Video(local, format=os.path.splitext(local)[1].lstrip(".") or None))
    self._safely(add)

  def admitted(self, step: int, row: dict) -> dict:
    """What of `row` W&B may still get at `step`: nothing below its last step, no metric twice at it."""
    last = self.record["step"]
    if last is None or step > last:
      return row
    if step < last:
      return {}
    return {k: v for k, v in row.items() if k not in self.record["keys"]}

  def commit(self) -> None:
    """Sends the pending row (if W&B may have it) and records what W&B got in workdir/wandb.json."""
    if self.run is None or self.pending_step is None:
      return
    step, row = self.pending_step, self.admitted(self.pending_step, self.pending)
    self.pending_step, self.pending = None, {}
    if not row:
      return

    def send():
      self.run.log({**row, WANDB_STEP: step})
      if self.record["step"] == step:
        self.record["keys"] = sorted(set(self.record["keys"]) | set(row))
      else:
        self.record["step"], self.record["keys"] = step, sorted(row)
      _write_json(self.path, self.record)
    self._safely(send)

  def finish(self, exit_code: int = 0) -> None:
    self.commit()
    if self.run is not None:
      run, self.run = self.run, None
      try:
        run.finish(exit_code=exit_code or None)
      except Exception as e:  # noqa: BLE001
        _warn(f"Weights & Biases could not finish its run ({_reason(e)}); TensorBoard has everything.")
    for folder in self.copies:
      shutil.rmtree(folder, ignore_errors=True)

  def _safely(self, work) -> None:
    """Runs `work`; on a W&B failure, one warning and W&B is left alone for the rest of the run."""
    try:
      work()
    except Exception as e:  # noqa: BLE001
      run, self.run = self.run, None
      if run is None:  # it failed before, and said so
        return
      _warn(f"Weights & Biases failed ({_reason(e)}); the run goes on with TensorBoard only.")
      try:
        run.finish(exit_code=1)
      except Exception:  # noqa: BLE001 (already warned once)
        pass


WANDB_CLOUD = "https://api.wandb.ai"
WANDB_CONNECT_SECONDS = 10.0


def _check_wandb_server() -> None:
  """Raises OSError, naming the server, where one TCP connection to W&B's server (WANDB_BASE_URL, else W&B's
  cloud) fails: an online run would otherwise wait out W&B's own retries (over ten seconds) for the same
  failure."""
  import socket
  import urllib.parse
  url = os.environ.get("WANDB_BASE_URL") or WANDB_CLOUD
  parts = urllib.parse.urlsplit(url if "://" in url else "https://" + url)
  port = parts.port or (80 if parts.scheme == "http" else 443)
  try:
    socket.create_connection((parts.hostname or "", port), timeout=WANDB_CONNECT_SECONDS).close()
  except OSError as e:
    raise OSError(f"cannot connect to its server {parts.hostname}:{port}: {e.strerror or type(e).__name__}") from None


def _reason(error: Exception) -> str:
  return " ".join(str(error).split())[:300] or type(error).__name__


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
