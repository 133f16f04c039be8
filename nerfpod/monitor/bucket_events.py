"""TensorBoard's event files in a bucket (a gs:// workdir).

Cloud Storage objects cannot be appended to, and tensorboardX's own gs:// writer uploads the whole event file
again at each flush, which sends a run's events N/2 times over N flushes. The event file there is a series of
objects instead, NAME.00000000, NAME.00000001, ... (NAME: tensorboardX's event file name, in the workdir
itself), each flush uploading only what was written since the last one (BucketEventFile); TensorBoard reads
every events.out.tfevents.* file of a folder, in name order, as one run. A local workdir has tensorboardX's one
event file, as before (logdir).
"""
import threading

from nerfpod import storage
from nerfpod.monitor.warn import reason, warn

BUCKET_EVENTS_SCHEME = "nerfpod-gs"  # tensorboardX's logdir for a gs:// workdir: its files are BucketEventFiles
SEGMENT_DIGITS = 8  # NAME.00000000: names that sort in upload order for 10^8 flushes (31 years at one per 10 s)


def logdir(workdir: str) -> str:
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
        warn(f"{len(self._flushed)} bytes of TensorBoard events could not be uploaded to {self.url}: lost.")
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
          warn(f"TensorBoard events could not be uploaded to {self.url} ({reason(error)}); the next flush "
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
