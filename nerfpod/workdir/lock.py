"""One writer per workdir: a training run holds WORKDIR/lock.json from start to end; a second one is refused.

    with WorkdirLock(workdir):   # process 0 of a training run; UserError if another live run holds it
      ...

The lock says who holds it: {"host", "pid", "process_start", "since"}. It is created only if absent, atomically,
on either storage (one small class each below, the rest is shared):
- a local (or network) directory: the file is created with O_CREAT | O_EXCL;
- a gs:// workdir: the object is uploaded with the precondition ifGenerationMatch=0 (Cloud Storage's JSON API
  answers 412 where it exists).
While the run lasts, a thread beats every HEARTBEAT_SECONDS: it touches the file (its mtime changes), or uploads
the object again with ifGenerationMatch=<the generation it holds> (its generation changes). A beat that finds
the lock no longer this run's (another run took it over) stops beating and says so once on stderr. The run
removes the lock when it ends, however it ends short of SIGKILL, and only if it is still its own (on gs://: a
delete with ifGenerationMatch=<its generation>).

A lock that is there when a run starts is the holder's, unless the holder is gone:
- on this host, the holder process no longer exists (its pid is gone, or now belongs to a process that started
  at another time): taken over at once;
- on another host (its process cannot be seen from here), its heartbeat stopped: the lock has not beaten for
  LEASE_SECONDS, by the storage's own clock (the file's mtime against this host's clock; the object's
  `updated` against the Date of the server's answer, so that the hosts' clocks need not agree). A heartbeat
  younger than that is watched for up to one lease: if the holder beats (a new mtime or generation), the run is
  refused (within seconds, as it beats every HEARTBEAT_SECONDS); if not, the holder is taken as dead and the
  lock taken over.
Taking over removes the stale lock in a way only one of the runs that found it stale succeeds in (the file is
renamed away; the object is deleted with ifGenerationMatch=<the stale generation>), then creates it anew only if
absent, so two runs that find the same stale lock do not both take it.

On gs:// the lock speaks HTTP with the standard library: to STORAGE_EMULATOR_HOST where it is set (an emulator,
no credentials), else to https://storage.googleapis.com with an access token from gcloud's application-default
credentials of a user (`gcloud auth application-default login`) or else from the metadata server of a GCE or
TPU VM (its service account). Without network or credentials, taking the lock is one sentence saying which.
Workdirs of other URL schemes take no lock.

Evaluation, rendering, the viewer and the exports only read a workdir: they neither take nor look at the lock.
"""
import datetime
import email.utils
import http.client
import json
import os
import socket
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import NamedTuple

from nerfpod.errors import UserError

NAME = "lock.json"
HEARTBEAT_SECONDS = 5.0
LEASE_SECONDS = 30.0
GCS_ENDPOINT = "https://storage.googleapis.com"  # Cloud Storage, where STORAGE_EMULATOR_HOST is not set
HTTP_TIMEOUT_SECONDS = 10.0  # for each request to Cloud Storage, the metadata server or gcloud's token endpoint


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
  age: float  # seconds since its last beat, by the storage's clock


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


_DIRECT = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # an emulator, the metadata server
_PROXIED = urllib.request.build_opener()  # Google's endpoints, through the proxy of the environment if any


def _send(opener, request) -> tuple[int, http.client.HTTPMessage, bytes]:
  """The status, headers and body of `request`'s answer, whatever its status; OSError where none came."""
  try:
    with opener.open(request, timeout=HTTP_TIMEOUT_SECONDS) as response:
      return response.status, response.headers, response.read()
  except urllib.error.HTTPError as e:
    with e:
      return e.code, e.headers, e.read()
  except urllib.error.URLError as e:
    raise e.reason if isinstance(e.reason, OSError) else OSError(str(e.reason)) from None
  except http.client.HTTPException as e:
    raise OSError(f"bad answer: {e!r}") from None


def _why(error: OSError) -> str:
  return error.strerror or str(error) or type(error).__name__


def _message(body: bytes) -> str:
  """The first sentence of an error answer's message (Cloud Storage: {"error": {"message": ...}})."""
  try:
    error = json.loads(body)
    message = error["error"] if isinstance(error["error"], str) else error["error"]["message"]
  except (ValueError, KeyError, TypeError):
    message = body.decode(errors="replace")
  return " ".join(str(message).split()).split(". ")[0].rstrip(".")[:200]


class _GcsLock:
  """gs://BUCKET/PATH/lock.json through Cloud Storage's JSON API: creating, beating and deleting are each
  preconditioned on the object's generation (ifGenerationMatch), which every upload changes."""

  def __init__(self, workdir: str):
    bucket, _, prefix = workdir[len("gs://"):].partition("/")
    self.bucket = bucket
    self.name = f"{prefix.strip('/')}/{NAME}" if prefix.strip("/") else NAME
    self.path = f"gs://{bucket}/{self.name}"
    emulator = os.environ.get("STORAGE_EMULATOR_HOST", "")
    if emulator and "://" not in emulator:
      emulator = "http://" + emulator
    self._emulator = emulator.rstrip("/")
    self._endpoint = self._emulator or GCS_ENDPOINT.rstrip("/")
    self._token, self._token_expiry, self._credentials = None, 0.0, "no credentials"
    self._me, self._body, self._generation = None, b"", None

  # The four operations the lock uses.

  def create(self, me: dict) -> bool:
    body = json.dumps(me).encode()
    status, _, answer = self._call("POST", self._upload_url(ifGenerationMatch=0), body)
    if status == 412:
      return False
    self._check(status, answer)
    self._me, self._body, self._generation = me, body, int(json.loads(answer)["generation"])
    return True

  def _metadata(self) -> tuple[dict, float] | None:
    """The object's metadata and the server's time of the answer, None where there is no object."""
    status, headers, answer = self._call("GET", self._object_url())
    if status == 404:
      return None
    self._check(status, answer)
    try:
      now = email.utils.parsedate_to_datetime(headers["Date"]).timestamp()
    except (TypeError, ValueError):  # no Date header: this host's clock is all there is
      now = time.time()
    return json.loads(answer), now

  def version(self) -> int | None:
    found = self._metadata()
    return None if found is None else int(found[0]["generation"])

  def look(self) -> _Look | None:
    found = self._metadata()
    if found is None:
      return None
    metadata, now = found
    generation = int(metadata["generation"])
    status, _, answer = self._call("GET", self._object_url(alt="media", ifGenerationMatch=generation))
    if status in (404, 412):  # removed or replaced meanwhile: the caller looks again
      return None
    self._check(status, answer)
    updated = datetime.datetime.fromisoformat(metadata["updated"]).timestamp()
    return _Look(_parse_holder(answer.decode(errors="replace")), generation, now - updated)

  def beat(self) -> bool:
    """Uploads the lock again (a new generation); False where it is no longer this run's."""
    status, _, answer = self._call("POST", self._upload_url(ifGenerationMatch=self._generation), self._body)
    if status == 200:
      self._generation = int(json.loads(answer)["generation"])
      return True
    if status in (404, 412):
      look = self.look()  # a beat whose answer was lost may have made the generation that is there
      if look is not None and look.holder == self._me:
        self._generation = look.version
        return True
      return False
    return True  # the service failed this time (429, 5xx): the next beat tries again

  def remove_stale(self, look: _Look) -> None:
    status, _, answer = self._call("DELETE", self._object_url(ifGenerationMatch=look.version))
    if status not in (404, 412):  # another run took it first
      self._check(status, answer)

  def release(self) -> None:
    self._call("DELETE", self._object_url(ifGenerationMatch=self._generation))  # not ours any more: left alone

  # HTTP.

  def _object_url(self, **query) -> str:
    url = (f"{self._endpoint}/storage/v1/b/{urllib.parse.quote(self.bucket, safe='')}/o/"
           f"{urllib.parse.quote(self.name, safe='')}")
    return url + ("?" + urllib.parse.urlencode(query) if query else "")

  def _upload_url(self, **query) -> str:
    query = urllib.parse.urlencode({"uploadType": "media", "name": self.name, **query},
                                   quote_via=urllib.parse.quote)
    return f"{self._endpoint}/upload/storage/v1/b/{urllib.parse.quote(self.bucket, safe='')}/o?{query}"

  def _call(self, method: str, url: str, body: bytes | None = None) -> tuple[int, http.client.HTTPMessage, bytes]:
    headers = {"Content-Type": "application/json"} if body is not None else {}
    if not self._emulator:
      headers["Authorization"] = f"Bearer {self._access_token()}"
    request = urllib.request.Request(url, data=body, headers=headers, method=method)
    try:
      return _send(_DIRECT if self._emulator else _PROXIED, request)
    except OSError as e:
      where = (f"the storage emulator at {self._emulator} (STORAGE_EMULATOR_HOST)" if self._emulator else
               f"Cloud Storage at {self._endpoint}")
      fix = ("start it or unset STORAGE_EMULATOR_HOST" if self._emulator else
             "check this machine's network access to it")
      raise UserError(f"could not take the lock {self.path}: {where} does not answer ({_why(e)}); {fix}, or pass "
                      f"a local --workdir.") from None

  def _check(self, status: int, answer: bytes) -> None:
    if status in (200, 204):
      return
    what = f"HTTP {status}: {_message(answer)}"
    if status in (401, 403):
      raise UserError(f"could not take the lock {self.path}: Cloud Storage refused {self._credentials} ({what}); "
                      f"give them write access to bucket {self.bucket}, or pass a local --workdir.")
    if status == 404:
      raise UserError(f"could not take the lock {self.path}: Cloud Storage has no bucket {self.bucket} ({what}); "
                      f"check --workdir, or create the bucket first.")
    raise UserError(f"could not take the lock {self.path}: Cloud Storage answered {what}; try again, or pass a "
                    f"local --workdir.")

  def _access_token(self) -> str:
    """A bearer token for Cloud Storage, kept until a minute before it expires."""
    if self._token is None or time.monotonic() > self._token_expiry - 60:
      user = _user_credentials()
      if user is not None:
        self._credentials = f"the application-default credentials in {user[0]}"
        token = _token_from_user(user, self.path)
      else:
        self._credentials = "this VM's service account"
        token = _token_from_metadata_server(self.path)
      self._token = token["access_token"]
      self._token_expiry = time.monotonic() + float(token.get("expires_in", 300))
    return self._token


def _user_credentials() -> tuple[str, dict] | None:
  """gcloud's application-default credentials of a user (`gcloud auth application-default login`) and their
  file, where there are some; a service account's key file is not one (the metadata server is asked instead)."""
  path = os.environ.get("GOOGLE_APPLICATION_CREDENTIALS") or os.path.join(
      os.environ.get("CLOUDSDK_CONFIG") or os.path.join(os.path.expanduser("~"), ".config", "gcloud"),
      "application_default_credentials.json")
  credentials = _json_file(path)
  return (path, credentials) if credentials is not None and credentials.get("type") == "authorized_user" else None


def _json_file(path: str | None) -> dict | None:
  """The JSON object a credentials file holds, None where there is no such file or object."""
  try:
    with open(path) as f:
      value = json.load(f)
  except (OSError, ValueError, TypeError):
    return None
  return value if isinstance(value, dict) else None


def _token(opener, request) -> tuple[dict | None, str]:
  """The access token an endpoint answers `request` with, or None and why there is none."""
  try:
    status, _, answer = _send(opener, request)
    if status == 200:
      return json.loads(answer), ""
    return None, f"HTTP {status}: {_message(answer)}"
  except OSError as e:
    return None, _why(e)
  except ValueError:
    return None, "not a token"


def _token_from_user(user: tuple[str, dict], lock: str) -> dict:
  path, credentials = user
  form = urllib.parse.urlencode({"grant_type": "refresh_token", "client_id": credentials.get("client_id", ""),
                                 "client_secret": credentials.get("client_secret", ""),
                                 "refresh_token": credentials.get("refresh_token", "")}).encode()
  url = credentials.get("token_uri") or "https://oauth2.googleapis.com/token"
  request = urllib.request.Request(url, data=form, method="POST",
                                   headers={"Content-Type": "application/x-www-form-urlencoded"})
  token, why = _token(_PROXIED, request)
  if token is not None:
    return token
  raise UserError(f"could not take the lock {lock}: the application-default credentials in {path} could not be "
                  f"turned into an access token at {url} ({why}); run `gcloud auth application-default login` "
                  f"again, or pass a local --workdir.")


class _UnsupportedCredentials(UserError):
  """Credentials that Cloud Storage itself takes but this lock's small client cannot use (a service account's
  key file, which needs RSA signing): the run goes on without a lock, saying so (as before there was one)."""


def _service_account_key() -> str | None:
  """GOOGLE_APPLICATION_CREDENTIALS where it names a service account's key file."""
  path = os.environ.get("GOOGLE_APPLICATION_CREDENTIALS")
  key = _json_file(path)
  return path if key is not None and key.get("type") == "service_account" else None


def _token_from_metadata_server(lock: str) -> dict:
  host = os.environ.get("GCE_METADATA_HOST") or "metadata.google.internal"
  request = urllib.request.Request(
      f"http://{host}/computeMetadata/v1/instance/service-accounts/default/token",
      headers={"Metadata-Flavor": "Google"})
  token, why = _token(_DIRECT, request)
  if token is not None:
    return token
  key = _service_account_key()
  if key is not None:
    raise _UnsupportedCredentials(f"no lock on {lock}: the service account key file {key} "
                                  f"(GOOGLE_APPLICATION_CREDENTIALS) is not one the lock can use, and there is no "
                                  f"metadata server ({why}); make sure one training run at a time writes this "
                                  f"workdir (or use `gcloud auth application-default login`)")
  raise UserError(f"could not take the lock {lock}: there are no credentials for Cloud Storage (no "
                  f"application-default credentials of a user, and the metadata server of a GCE or TPU VM at "
                  f"{host} gave no token: {why}); run `gcloud auth application-default login`, run on a VM with a "
                  f"service account, or pass a local --workdir.")


class WorkdirLock:
  """The lock of a local or gs:// workdir (see the module's docstring); a no-op for other URL schemes."""

  def __init__(self, workdir: str):
    self.workdir = str(workdir)
    if self.workdir.startswith("gs://"):
      self._store = _GcsLock(self.workdir)
    elif "://" in self.workdir:
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
    if look.age > LEASE_SECONDS:
      return True
    deadline = time.monotonic() + LEASE_SECONDS - max(0.0, look.age)
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
          "since": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    for _ in range(10):  # each pass either takes the lock, refuses, or clears a stale one
      try:
        created = self._store.create(me)
      except _UnsupportedCredentials as e:
        print(f"nerfpod: warning: {e}", file=sys.stderr, flush=True)
        return
      if created:
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
    if self._thread is not None:
      self._thread.join()
    try:
      self._store.release()
    except UserError:  # the storage does not answer: the lock is taken over once its lease has run out
      print(f"nerfpod: warning: could not remove the lock {self.path}; the next run takes it over after "
            f"{LEASE_SECONDS:g} s", file=sys.stderr, flush=True)
