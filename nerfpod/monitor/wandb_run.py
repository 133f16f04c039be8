"""The W&B side of a run (the `wandb` extra): its run started or resumed, and what W&B may get.

The run's id is kept in workdir/wandb.json, so a resumed run continues the same W&B run; the same file records
the last step W&B got and the metrics it got at that step, and a resumed run (which re-trains the steps after
its newest checkpoint) sends W&B nothing below that step nor any metric again at it, so W&B's steps never go
backwards. Its x-axis is the metric `step`. A W&B failure (no network, a bad key, ...) is one warning on stderr,
and the run goes on with TensorBoard alone.
"""
import json
import os
import secrets
import shutil
import string
import sys
import tempfile

from nerfpod import storage
from nerfpod.monitor.warn import reason, warn

WANDB_RECORD = "wandb.json"  # in the workdir: {"id", "step", "keys"}
WANDB_STEP = "step"          # the W&B metric every other metric is plotted against
WANDB_FLUSH_SECONDS = 1.0    # W&B's .wandb file is written this often (its default, 15 s, loses more to a kill)


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
      warn(f"Weights & Biases could not start ({reason(e)}); the run goes on with TensorBoard only.")
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
        warn(f"Weights & Biases could not finish its run ({reason(e)}); TensorBoard has everything.")
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
      warn(f"Weights & Biases failed ({reason(e)}); the run goes on with TensorBoard only.")
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
