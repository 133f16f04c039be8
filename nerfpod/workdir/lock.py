"""One writer per workdir: a training run holds WORKDIR/lock.json from start to end; a second one is refused.

    with WorkdirLock(workdir):   # process 0 of a training run; UserError if another live run holds it
      ...

The lock says who holds it: {"host", "pid", "process_start", "since", "id"} (id: random, so that two holds by one
process differ). It is created only if absent, atomically, on either storage (one small class each below, the
rest is shared):
- a local (or network) directory: the file is created with O_CREAT | O_EXCL;
- a gs:// workdir: the object is uploaded with the precondition ifGenerationMatch=0 (Cloud Storage answers 412
  where it exists).
While the run lasts, a thread beats every HEARTBEAT_SECONDS: it touches the file (its mtime changes), or uploads
the object again with ifGenerationMatch=<the generation it holds> (its generation changes). A beat that finds
the lock no longer this run's (another run took it over) stops beating and says so once on stderr. The run
removes the lock when it ends, however it ends short of SIGKILL, and only if it is still its own (on gs://: a
delete with ifGenerationMatch=<its generation>).

A lock that is there when a run starts is the holder's, unless the holder is gone:
- on this host, the holder process no longer exists (its pid is gone, or now belongs to a process that started
  at another time): taken over at once;
- on another host (its process cannot be seen from here), its heartbeat stopped. A local lock has not beaten
  for LEASE_SECONDS by the file's mtime against this host's clock; one younger than that is watched for the
  rest of the lease. A gs:// lock is always watched for a whole lease by this host's monotonic clock: its
  `updated` is the server's clock, which google-cloud-storage gives nothing to set against (this host's clock
  may be an hour off), so its age is never judged from it. While watched, if the holder beats (a new mtime or
  generation), the run is refused (within seconds, as it beats every HEARTBEAT_SECONDS); if not, the holder is
  taken as dead and the lock taken over. (A run restarted on another host after a lost machine thus waits one
  lease, LEASE_SECONDS, before it takes a gs:// workdir's lock over.)
Taking over removes the stale lock in a way only one of the runs that found it stale succeeds in (the file is
renamed away; the object is deleted with ifGenerationMatch=<the stale generation>), then creates it anew only if
absent, so two runs that find the same stale lock do not both take it.

On gs:// the lock goes through google-cloud-storage (nerfpod.storage.gcs_bucket): to STORAGE_EMULATOR_HOST where
it is set (an emulator, no credentials), else to Cloud Storage with whatever credentials google.auth.default()
finds: gcloud's application-default credentials of a user, a service account's key file or an external
account's configuration (GOOGLE_APPLICATION_CREDENTIALS), or the metadata server of a GCE or TPU VM (its service
account). Every call has a timeout and is retried by the library where that is worth it (429, 5xx, a lost
connection; for at most RETRY_SECONDS), which the generation preconditions make safe: a retried write or delete
whose first try did reach the service finds the generation changed, and a create or beat then finds the lock
that is there to be its own. Without network (one connection is tried first, nerfpod.storage.check_reachable),
credentials, access or the bucket, taking the lock is one sentence saying which. Workdirs of other URL schemes
take no lock.

Evaluation, rendering, the viewer and the exports only read a workdir: they neither take nor look at the lock.
"""
import contextlib
import datetime
import json
import os
import secrets
import socket
import sys
import threading
import time
from typing import NamedTuple

from nerfpod import storage
from nerfpod.errors import UserError

NAME = "lock.json"
HEARTBEAT_SECONDS = 5.0
LEASE_SECONDS = 30.0
HTTP_TIMEOUT_SECONDS = 10.0  # for each request to Cloud Storage (to connect, and then for its answer)
RETRY_SECONDS = 20.0  # how long one call to Cloud Storage is retried (429, 5xx, a lost connection)


def _process_start(pid: int) -> str | None:
  """When process `pid` started (clock ticks since boot, /proc's field 22), None where it does not exist or
  /proc is absent: with the pid, it names one process even after pids are reused."""
  try:
    with open(f"/proc/{pid}/stat") as f:
      return f.read().rsplit(")", 1)[1].split()[19]
  except (OSError, IndexError):
    return None


def _alive(pid: int, process_start: str | None) -> bool:
  """Whether the process `pid` (started at `process_start`, where known) still runs on this host."""
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:  # another user's process: it exists
    pass
  now = _process_start(pid)
  return process_start is None or now is None or now == process_start


def _parse_holder(text: str) -> dict:
  """The holder a lock's text names; {} for a text that is not one (a holder killed while writing it)."""
  try:
    holder = json.loads(text)
  except ValueError:
    return {}
  return holder if isinstance(holder, dict) else {}


class _Look(NamedTuple):
  """What one look at an existing lock finds."""
  holder: dict  # {} where unreadable
  version: object  # changes at every beat: the file's mtime, the object's generation
  age: float | None  # seconds since its last beat, by the storage's clock; None: not known (watched a lease)


class _LocalLock:
  """lock.json in a directory: created with O_EXCL, its mtime is the heartbeat, a stale one is renamed away."""

  def __init__(self, workdir: str):
    self.path = os.path.join(workdir, NAME)
    self._me = None

  def create(self, me: dict) -> bool:
    try:
      fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
      return False
    with os.fdopen(fd, "w") as f:
      f.write(json.dumps(me))
    self._me = me
    return True

  def _holder(self) -> dict | None:
    try:
      with open(self.path) as f:
        return _parse_holder(f.read())
    except FileNotFoundError:
      return None

  def version(self) -> int | None:
    try:
      return os.stat(self.path).st_mtime_ns
    except FileNotFoundError:
      return None

  def look(self) -> _Look | None:
    holder, version = self._holder(), self.version()
    if holder is None or version is None:
      return None
    return _Look(holder, version, time.time() - version / 1e9)

  def beat(self) -> bool:
    """Touches the lock; False where it is no longer this run's."""
    try:
      if self._holder() != self._me:
        return False
      os.utime(self.path)
    except FileNotFoundError:
      return False
    except OSError:  # the disk is unreachable for now: the next beat tries again
      pass
    return True

  def remove_stale(self, look: _Look) -> None:
    stale = f"{self.path}.stale-{os.getpid()}"
    try:
      os.rename(self.path, stale)  # one of the runs that found it stale moves it away
    except FileNotFoundError:
      return
    os.remove(stale)

  def release(self) -> None:
    if self._holder() == self._me:
      try:
        os.remove(self.path)
      except FileNotFoundError:
        pass


def _first_sentence(text: str) -> str:
  """The first sentence of an error's words, on one line, without its full stop."""
  return " ".join(str(text).split()).split(". ")[0].rstrip(".")[:200]


def _api_exceptions():
  """google.api_core.exceptions, imported where a gs:// workdir is used (the gcs extra)."""
  from google.api_core import exceptions
  return exceptions


class _GcsLock:
  """gs://BUCKET/PATH/lock.json through google-cloud-storage (nerfpod.storage.gcs_bucket): creating, beating and
  deleting are each preconditioned on the object's generation (if_generation_match), which every upload changes.
  Each call has a timeout (HTTP_TIMEOUT_SECONDS) and the library's retries for what is worth trying again (429,
  5xx, a lost connection), for at most RETRY_SECONDS; the generation precondition that every write and delete
  carries is what makes them safe to retry (google-cloud-storage's DEFAULT_RETRY_IF_GENERATION_SPECIFIED rule): a
  retry of a write whose first try did reach the service finds the generation changed, and the lock then looks
  whether what is there is its own."""

  def __init__(self, workdir: str):
    bucket, _, prefix = workdir[len("gs://"):].partition("/")
    self.bucket = bucket
    self.name = f"{prefix.strip('/')}/{NAME}" if prefix.strip("/") else NAME
    self.path = f"gs://{bucket}/{self.name}"
    self._bucket, self._credentials = None, "no credentials"
    self._me, self._body, self._generation = None, b"", None

  # The four operations the lock uses.

  def create(self, me: dict) -> bool:
    api = _api_exceptions()
    body = json.dumps(me).encode()
    blob = self._blob()
    try:
      with self._answers():
        blob.upload_from_string(body, content_type="application/json", if_generation_match=0,
                                timeout=HTTP_TIMEOUT_SECONDS, retry=self._retry_if_generation())
      generation = blob.generation
    except api.PreconditionFailed:
      look = self.look()  # a retried create whose first try had made it finds its own lock there
      if look is None or look.holder != me:
        return False
      generation = look.version
    except api.NotFound as e:
      raise UserError(f"could not take the lock {self.path}: Cloud Storage has no bucket {self.bucket} "
                      f"({_why(e)}); check --workdir, or create the bucket first.") from None
    self._me, self._body, self._generation = me, body, int(generation)
    return True

  def version(self) -> int | None:
    api = _api_exceptions()
    blob = self._blob()
    try:
      with self._answers():
        blob.reload(timeout=HTTP_TIMEOUT_SECONDS, retry=self._retry())
    except api.NotFound:
      return None
    return int(blob.generation)

  def look(self) -> _Look | None:
    """The holder and generation of the lock that is there. Its age is not known: Cloud Storage's `updated` is
    the server's clock, and google-cloud-storage does not give the server's time of an answer to set it against
    (this host's clock may be far off the server's), so a lock from another host is watched for a lease."""
    api = _api_exceptions()
    blob = self._blob()
    try:
      with self._answers():
        blob.reload(timeout=HTTP_TIMEOUT_SECONDS, retry=self._retry())
        generation = int(blob.generation)
        text = blob.download_as_bytes(if_generation_match=generation, timeout=HTTP_TIMEOUT_SECONDS,
                                      retry=self._retry_if_generation())
    except (api.NotFound, api.PreconditionFailed):  # removed or replaced meanwhile: the caller looks again
      return None
    return _Look(_parse_holder(text.decode(errors="replace")), generation, None)

  def beat(self) -> bool:
    """Uploads the lock again (a new generation); False where it is no longer this run's."""
    api = _api_exceptions()
    blob = self._blob()
    try:
      with self._answers():
        blob.upload_from_string(self._body, content_type="application/json", if_generation_match=self._generation,
                                timeout=HTTP_TIMEOUT_SECONDS, retry=self._retry_if_generation())
    except (api.NotFound, api.PreconditionFailed):
      look = self.look()  # a beat whose answer was lost (and then retried) may have made the generation there
      if look is not None and look.holder == self._me:
        self._generation = look.version
        return True
      return False
    self._generation = int(blob.generation)
    return True

  def remove_stale(self, look: _Look) -> None:
    self._delete(look.version)  # NotFound or PreconditionFailed: another run took it first

  def release(self) -> None:
    self._delete(self._generation)  # not ours any more: left alone

  # google-cloud-storage.

  def _delete(self, generation: int) -> None:
    api = _api_exceptions()
    try:
      with self._answers():
        self._blob().delete(if_generation_match=generation, timeout=HTTP_TIMEOUT_SECONDS,
                            retry=self._retry_if_generation())
    except (api.NotFound, api.PreconditionFailed):
      pass

  def _blob(self):
    """The lock's Blob, on a client made at the first call (after one connection to its endpoint: no network
    is one sentence at once)."""
    if self._bucket is None:
      storage.check_reachable(self.path)
      from google.auth.exceptions import DefaultCredentialsError
      try:
        found = storage.gcs_bucket(self.path)
      except DefaultCredentialsError as e:
        raise UserError(f"could not take the lock {self.path}: there are no credentials for Cloud Storage "
                        f"({_why(e)}); run `gcloud auth application-default login`, point "
                        f"GOOGLE_APPLICATION_CREDENTIALS at a service account's key file, run on a VM with a "
                        f"service account, or pass a local --workdir.") from None
      self._bucket, self._credentials = found.bucket, found.credentials
    return self._bucket.blob(self.name)

  @staticmethod
  def _retry():
    """storage's retry policy (google-cloud-storage's DEFAULT_RETRY), for at most RETRY_SECONDS: for reads."""
    return storage.gcs_retry(RETRY_SECONDS)

  @staticmethod
  def _retry_if_generation():
    """storage's retry policy for writes and deletes, for at most RETRY_SECONDS: retried only where they carry a
    generation precondition (every one of the lock's does)."""
    return storage.gcs_retry_if_generation(_GcsLock._retry())

  @contextlib.contextmanager
  def _answers(self):
    """NotFound and PreconditionFailed (the answers the lock expects) as they are, any other failure of a call
    to Cloud Storage one sentence."""
    api = _api_exceptions()
    from google.auth import exceptions as auth
    try:
      yield
    except (UserError, api.NotFound, api.PreconditionFailed):
      raise
    except Exception as e:  # noqa: BLE001 (what the client raises: HTTP answers, auth, connections)
      error = e.cause if isinstance(e, api.RetryError) and e.cause is not None else e
      if isinstance(error, (api.Unauthorized, api.Forbidden)):
        raise UserError(f"could not take the lock {self.path}: Cloud Storage refused {self._credentials} "
                        f"({_why(error)}); give them write access to bucket {self.bucket}, or pass a local "
                        f"--workdir.") from None
      if isinstance(error, auth.RefreshError):
        raise UserError(f"could not take the lock {self.path}: {self._credentials} gave no access token "
                        f"({_why(error)}); renew them (`gcloud auth application-default login`, a new key file), "
                        f"or pass a local --workdir.") from None
      if isinstance(error, api.GoogleAPICallError):
        raise UserError(f"could not take the lock {self.path}: Cloud Storage answered {_why(error)}; try again, "
                        f"or pass a local --workdir.") from None
      raise UserError(f"could not take the lock {self.path}: Cloud Storage did not answer ({_why(error)}) "
                      f"within {RETRY_SECONDS:g} s of retries; check this machine's network access to it, or "
                      f"pass a local --workdir.") from None


def _why(error: Exception) -> str:
  """An error of the client in a few words: 'HTTP 403: Access denied' for an answer of the service (the message
  of its JSON), the first of its arguments for others (google.auth's RefreshError: 'invalid_grant: ...')."""
  api = _api_exceptions()
  if isinstance(error, api.GoogleAPICallError) and error.code is not None:
    try:
      message = json.loads(error.response.text)["error"]["message"]
    except (AttributeError, ValueError, KeyError, TypeError):  # no answer kept, or not Cloud Storage's JSON
      message = error.message.split(": ", 1)[-1] if error.message.startswith(("GET ", "POST ", "DELETE ")) else \
          error.message
    return f"HTTP {int(error.code)}: {_first_sentence(message)}"
  words = error.args[0] if error.args and isinstance(error.args[0], str) else str(error)
  return _first_sentence(words) or type(error).__name__


class WorkdirLock:
  """The lock of a local or gs:// workdir (see the module's docstring); a no-op for other URL schemes."""

  def __init__(self, workdir: str):
    self.workdir = str(workdir)
    if self.workdir.startswith("gs://"):
      self._store = _GcsLock(self.workdir)
    elif storage.is_url(self.workdir):
      self._store = None
    else:
      self._store = _LocalLock(self.workdir)
    self.path = self._store.path if self._store is not None else f"{self.workdir.rstrip('/')}/{NAME}"
    self._stop = threading.Event()
    self._thread = None
    self._held = False

  def __enter__(self):
    self.acquire()
    return self

  def __exit__(self, *exc):
    self.release()

  def _is_stale(self, look: _Look) -> bool:
    """Whether the holder of the lock is gone (see the module's docstring); may watch its heartbeat for up to
    one lease."""
    holder = look.holder
    if holder.get("host") == socket.gethostname() and isinstance(holder.get("pid"), int):
      return not _alive(holder["pid"], holder.get("process_start"))
    if look.age is not None and look.age > LEASE_SECONDS:
      return True
    deadline = time.monotonic() + LEASE_SECONDS - max(0.0, look.age or 0.0)
    while time.monotonic() < deadline:
      time.sleep(min(1.0, HEARTBEAT_SECONDS / 2))
      version = self._store.version()
      if version is None:
        return True  # released meanwhile
      if version != look.version:
        return False  # it beats
    return True

  def acquire(self) -> None:
    """Takes the lock, or raises a UserError naming the live run that holds it (or, on gs://, saying why it
    could not be taken)."""
    if self._store is None:
      return
    me = {"host": socket.gethostname(), "pid": os.getpid(), "process_start": _process_start(os.getpid()),
          "since": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
          "id": secrets.token_hex(8)}
    for _ in range(10):  # each pass either takes the lock, refuses, or clears a stale one
      if self._store.create(me):
        self._held = True
        self._thread = threading.Thread(target=self._beat, name="nerfpod-workdir-lock", daemon=True)
        self._thread.start()
        return
      look = self._store.look()
      if look is None:
        continue  # released between the two looks
      if not self._is_stale(look):
        holder = look.holder
        who = (f"process {holder.get('pid', '?')} on host {holder.get('host', '?')} since "
               f"{holder.get('since', '?')}")
        raise UserError(f"workdir {self.workdir} is in use by another training run ({who} holds {self.path}); "
                        f"wait for that run to end or stop it, or pass another --workdir (evaluation, rendering, "
                        f"the viewer and the exports may read it meanwhile).")
      self._store.remove_stale(look)
    raise UserError(f"could not take the lock {self.path}: other runs keep taking and releasing it; start one "
                    f"run on workdir {self.workdir} at a time.")

  def _beat(self) -> None:
    while not self._stop.wait(HEARTBEAT_SECONDS):
      try:
        ours = self._store.beat()
      except UserError:  # the storage does not answer for now: the next beat tries again
        continue
      if not ours:
        print(f"nerfpod: warning: another run took the lock {self.path} over (it had not seen this run's "
              f"heartbeat for {LEASE_SECONDS:g} s, or the lock was replaced); this run goes on but no longer "
              f"keeps other training runs off workdir {self.workdir}", file=sys.stderr, flush=True)
        return

  def release(self) -> None:
    """Stops the heartbeat and removes the lock, if this process still holds it."""
    if not self._held:
      return
    self._held = False
    self._stop.set()
    if storage.stopped(self.workdir):  # (the run stops on it with one sentence; its lease runs out)
      return
    if self._thread is not None:
      self._thread.join()
    try:
      self._store.release()
    except UserError:  # the storage does not answer: the lock is taken over once its lease has run out
      print(f"nerfpod: warning: could not remove the lock {self.path}; the next run takes it over after "
            f"{LEASE_SECONDS:g} s", file=sys.stderr, flush=True)
