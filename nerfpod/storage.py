"""Files that may be local or in a bucket (gs://bucket/folder/file): the one path layer scenes are read through.

    is_url, join, normpath           paths of either kind (a URL keeps its '//')
    isfile, isdir, exists, listdir   what a folder holds
    read_bytes(path)                 a whole file, in one request for a URL
    header_reader(path)              a URL's file read lazily in small blocks (an image's size from its header)
    local_copy(paths)                local copies of files in a temporary folder (for readers of local files only)
    forget_listings()                what was listed of a bucket is listed again on the next look
    check_reachable(path)            one sentence at once where a URL's storage cannot be connected to
    missing_bucket(url)              a URL's bucket where it does not exist (what a "not found" under it means)
    gcs_bucket(url)                  google-cloud-storage's Bucket of a gs:// URL, its object name, whose credentials
    Stopped                          the sentence of a bucket that stopped answering mid-run (exit 69)
    bound_clients(seconds)           every storage client's own bounds on a request that gets no answer
    within(url, seconds, work)       work() waited on for at most `seconds`, else NoAnswer (a watchdog)
    stopped(url)                     whether a URL's bucket stopped answering in this process
    path(p)                          the path object of what is written (a workdir's files, exports): etils.epath

A local path takes exactly the route it always took (os, open). A URL goes to fsspec, which reads gs://
through gcsfs (the `gcs` extra; gcsfs reads STORAGE_EMULATOR_HOST, for an emulator, and otherwise finds
credentials as gcloud does). What a loader needs from a bucket is only listing and reading: objects,
and the "folders" their names' slashes make. A folder's listing is kept once made (checking that a
thousand images exist is one request), until forget_listings(): scenes.load calls it before each scene, which
does not change while it loads; nerfpod.workdir.checkpoints before it lists a workdir's steps.

Errors on a URL: a missing object is FileNotFoundError, as for a local file, so the loaders' sentences name
it the same way; anything else (no network, no credentials, no access) is one UserError sentence naming the
path. Before the first request to a storage endpoint, a process connects to it once with a short timeout,
so that no network is one sentence at once rather than after a client's minute of retries.

What nerfpod writes (a workdir's config.json, scene.json and metrics, the exports) goes through path(p): an
etils.epath.Path, local or gs://, the type orbax's checkpoints take too, which reaches gs:// through the same
gcsfs (and its STORAGE_EMULATOR_HOST) as the reads above.

What fsspec does not do, writing an object only if its generation is the one expected (the workdir lock,
TensorBoard's event objects in a bucket: nerfpod.monitor), goes through google-cloud-storage itself, whose
clients are made here only: gcs_bucket() gives its Bucket of a URL, on the same endpoint and with the
credentials every Google client finds (google.auth.default(): gcloud's application-default credentials of a
user, a service account's key file or an external account's configuration in GOOGLE_APPLICATION_CREDENTIALS,
or the metadata server of a GCE or TPU VM); STORAGE_EMULATOR_HOST, where it is set, is an emulator that takes
no credentials, as google-cloud-storage itself has it.

Storage that stops answering mid-run (a partition, an outage, revoked credentials): each client's retries would
otherwise wait minutes before failing, or hang. bound_clients(checkpoint.storage_timeout_s), called where a run
starts, sets each client's own bound on a request that gets no answer: gcsfs's `requests_timeout` (through
fsspec's configuration, for every gs:// file system made afterwards: etils.epath's and orbax's too), tensorstore's
curl low-speed limit (no byte for that long ends a request; its environment variables, read when its HTTP
transport starts; nerfpod.workdir.watchdog bounds its gcs driver's retries), and GCS_TIMEOUT for
google-cloud-storage's calls (gcs_timeout(), gcs_retry(), gcs_retry_if_generation()). Those bound each request
and, but for google-cloud-storage's, not all of a client's retries of it: what a run waits on is bounded by
within(), a watchdog that leaves a call that does not return behind in a daemon thread and raises NoAnswer.
The first NoAnswer marks the bucket stopped (stopped()): the run's later calls to it (the last TensorBoard
events, the lock's release) give up at once, and the run ends with one Stopped sentence (exit 69).
"""
import contextlib
import io
import logging
import os
import posixpath
import shutil
import socket
import sys
import tempfile
import threading
import urllib.parse
from typing import NamedTuple

from nerfpod.errors import UserError

_CLOUD_STORAGE = "https://storage.googleapis.com"
GCS_ENDPOINT = _CLOUD_STORAGE  # Cloud Storage, where STORAGE_EMULATOR_HOST is not set
GCS_SCOPES = ("https://www.googleapis.com/auth/devstorage.read_write",)  # what gcs_bucket's credentials may do
CONNECT_TIMEOUT_SECONDS = 10.0  # the first connection to a storage endpoint
HEADER_BLOCK_BYTES = 64 * 1024  # what header_reader fetches at a time: an image header is in the first block
CREDENTIALS_HINT = ("check the path, and for gs:// the network, your credentials (gcloud auth "
                    "application-default login, or a VM's service account) and their access to the bucket")

_reached: set[str] = set()
_reached_lock = threading.Lock()
GCS_TIMEOUT = 60.0  # google-cloud-storage's bound on one request, and on its retries (bound_clients sets it)
STOPPED_EXIT_CODE = 69  # EX_UNAVAILABLE of sysexits.h: a service (the bucket) is unavailable
_stopped: set[str] = set()  # the buckets (gs://B) that gave no answer within a watchdog's deadline
_set_here: set[str] = set()  # the settings bound_clients made (not the user's): environment variables, fsspec's


def path(p):
  """The path object of `p` (local, or a URL such as gs://bucket/folder/file) for what is written and for
  orbax (module docstring)."""
  from etils import epath
  return epath.Path(p)


def is_url(path) -> bool:
  """Whether `path` is a URL (gs://...) rather than a local path."""
  return "://" in str(path)


def join(folder, *names: str) -> str:
  """`names` under `folder`, a local path or a URL."""
  return posixpath.join(str(folder), *names) if is_url(folder) else os.path.join(folder, *names)


def normpath(path) -> str:
  """os.path.normpath, keeping a URL's scheme: gs://b/x/../y/ -> gs://b/y."""
  if not is_url(path):
    return os.path.normpath(path)
  scheme, rest = str(path).split("://", 1)
  return f"{scheme}://{posixpath.normpath(rest)}"


def _filesystem(path, instance: bool = True):
  """The fsspec file system for a URL's scheme (`instance`=False: only its class, which looks for no
  credentials); one sentence where its package is not installed."""
  scheme = str(path).split("://", 1)[0]
  try:
    import fsspec
    # fsspec keeps one instance per scheme; making it looks for credentials (a metadata server's retries)
    return fsspec.filesystem(scheme) if instance else fsspec.get_filesystem_class(scheme)
  except (ImportError, ValueError) as e:
    if scheme in ("gs", "gcs"):
      raise UserError(f"cannot read {path}: gs:// needs the gcsfs package, which is not installed; install the gcs "
                      f"extra (pip install 'nerfpod[gcs]').") from None
    raise UserError(f"cannot read {path}: no file system for {scheme}:// paths ({' '.join(str(e).split())[:200]}); "
                    f"use a local path or gs://.") from None


def forget_listings() -> None:
  """Drops the folder listings that this process's bucket clients keep (gcsfs keeps every listing it makes,
  for the life of the process, and does not see what other processes write since; etils.epath and orbax list
  a workdir through it): the next look lists again."""
  gcsfs = sys.modules.get("gcsfs")
  if gcsfs is None:  # no bucket read yet
    return
  # etils.epath (orbax's paths, nerfpod's writes) keeps the gcsfs instance it first got in a cache of its own: one
  # that fsspec's cache no longer holds (gcsfs.GCSFileSystem.clear_instance_cache(), as a client for another
  # endpoint calls) would keep its listings below for good. Dropped, epath asks fsspec again.
  epath_backend = sys.modules.get("etils.epath.backend")
  get_filesystem = getattr(getattr(epath_backend, "_FileSystemSpecBackend", None), "_get_filesystem", None)
  if hasattr(get_filesystem, "cache_clear"):
    get_filesystem.cache_clear()
  classes = [gcsfs.GCSFileSystem]
  while classes:  # fsspec keeps the instances of each class (and subclass) apart
    cls = classes.pop()
    classes += cls.__subclasses__()
    for fs in list(getattr(cls, "_cache", {}).values()):
      fs.invalidate_cache()


def endpoint(path) -> tuple[str, int] | None:
  """(host, port) that a URL's requests go to: STORAGE_EMULATOR_HOST for gs:// where it is set, else Cloud
  Storage; None for other schemes."""
  if not str(path).startswith(("gs://", "gcs://")):
    return None
  url = os.environ.get("STORAGE_EMULATOR_HOST") or GCS_ENDPOINT
  url = url if "://" in url else "http://" + url
  parts = urllib.parse.urlsplit(url)
  return parts.hostname or "", parts.port or (443 if parts.scheme == "https" else 80)


def check_reachable(path) -> None:
  """One sentence where a URL's client is not installed or its storage endpoint cannot be connected to (once
  per process and endpoint); local paths and reached endpoints return at once."""
  if not is_url(path):
    return
  _filesystem(path, instance=False)  # its client installed (credentials are looked for once it is reached)
  where = endpoint(path)
  if where is None:
    return
  key = f"{where[0]}:{where[1]}"
  with _reached_lock:
    if key in _reached:
      return
  try:
    socket.create_connection(where, timeout=CONNECT_TIMEOUT_SECONDS).close()
  except OSError as e:
    emulator = os.environ.get("STORAGE_EMULATOR_HOST")
    fix = (f"start the storage emulator that STORAGE_EMULATOR_HOST={emulator} names, or unset it" if emulator
           else "check this machine's network (a pod's hosts reach Cloud Storage through their VPC)")
    raise UserError(f"cannot reach Cloud Storage at {key} to read {path} "
                    f"({e.strerror or type(e).__name__}); {fix}.") from None
  with _reached_lock:
    _reached.add(key)


def _call(path, what: str, function, *args, **kwargs):
  """function(*args, **kwargs) for the URL `path`: FileNotFoundError as it is, any other failure one
  sentence."""
  check_reachable(path)
  try:
    return function(*args, **kwargs)
  except (FileNotFoundError, UserError):
    raise
  except Exception as e:  # noqa: BLE001 (whatever a bucket client raises: HTTP, auth, connection)
    reason = " ".join(str(e).split())[:300] or type(e).__name__
    raise UserError(f"could not {what} {path} ({reason}); {CREDENTIALS_HINT}.") from None


def _info(path) -> dict | None:
  """A URL's object or folder description (fsspec's info), None where there is neither. The parent folder
  is listed first (once: gcsfs keeps the listing), so that checking many files of one folder costs one
  request."""
  fs = _filesystem(path)
  parent = posixpath.dirname(str(path).rstrip("/"))
  if "/" in parent.split("://", 1)[1]:  # below a bucket: list its folder
    try:
      _call(parent, "list", fs.ls, parent, detail=True)
    except FileNotFoundError:
      return None
  try:
    return _call(path, "read", fs.info, path)
  except FileNotFoundError:
    return None


def missing_bucket(url) -> str | None:
  """The bucket of a URL (gs://BUCKET/...) where it does not exist (or these credentials cannot see it), None
  where it does or `url` is a local path: what a "not found" under it means."""
  if not is_url(url):
    return None
  bucket = str(url).split("://", 1)[1].split("/", 1)[0]
  root = f"{str(url).split('://', 1)[0]}://{bucket}"
  try:
    return None if _call(root, "list", _filesystem(root).exists, root) else bucket
  except UserError:
    return None  # unreachable: the caller's own sentence says more


def isfile(path) -> bool:
  if not is_url(path):
    return os.path.isfile(path)
  info = _info(path)
  return info is not None and info.get("type") == "file"


def isdir(path) -> bool:
  if not is_url(path):
    return os.path.isdir(path)
  info = _info(path)
  return info is not None and info.get("type") == "directory"


def exists(path) -> bool:
  if not is_url(path):
    return os.path.exists(path)
  return _info(path) is not None


def listdir(path) -> list[str]:
  """The names in a folder (os.listdir for a local one); FileNotFoundError where it does not exist."""
  if not is_url(path):
    return os.listdir(path)
  fs = _filesystem(path)
  folder = str(path).rstrip("/")
  own = folder.split("://", 1)[1]
  names = _call(path, "list", fs.ls, folder, detail=False)
  return [posixpath.basename(n.rstrip("/")) for n in names if n.rstrip("/") != own]


def read_bytes(path) -> bytes:
  """The whole file: one request for a URL."""
  if not is_url(path):
    with open(path, "rb") as f:
      return f.read()
  return _call(path, "read", _filesystem(path).cat_file, path)


def header_reader(path):
  """A binary file object of a URL's file that fetches HEADER_BLOCK_BYTES at a time: reading an image's header
  through it fetches the first block only. (Local paths: open(path, "rb").)"""
  if not is_url(path):
    return open(path, "rb")
  return _call(path, "read", _filesystem(path).open, path, "rb", block_size=HEADER_BLOCK_BYTES)


def open_binary(path):
  """A binary file object of the whole file: read in one request for a URL (io.BytesIO), opened for a local
  path."""
  return open(path, "rb") if not is_url(path) else io.BytesIO(read_bytes(path))


@contextlib.contextmanager
def local_copy(paths):
  """A local folder holding `paths` under their own names: a temporary copy of URLs (removed afterwards), for
  readers of local files only (pycolmap); local paths must share one folder, which is given as it is."""
  paths = [str(p) for p in paths]
  if not any(is_url(p) for p in paths):
    yield os.path.dirname(paths[0]) if paths else "."
    return
  folder = tempfile.mkdtemp(prefix="nerfpod-copy-")
  try:
    for path in paths:
      with open(os.path.join(folder, posixpath.basename(path)), "wb") as f:
        f.write(read_bytes(path))
    yield folder
  finally:
    shutil.rmtree(folder, ignore_errors=True)


class GcsBucket(NamedTuple):
  """What gcs_bucket() gives: google-cloud-storage's Bucket, the object's name in it, and whose credentials its
  requests carry, in words for a sentence ("service account a@b.iam.gserviceaccount.com (the key file ...)")."""
  bucket: object  # google.cloud.storage.Bucket
  name: str
  credentials: str


def gcs_bucket(url) -> GcsBucket:
  """google-cloud-storage's Bucket of a gs:// URL (gs://BUCKET/NAME) and the object name NAME, with a client of
  its own: on STORAGE_EMULATOR_HOST where it is set (an emulator: no credentials), else on GCS_ENDPOINT with the
  credentials google.auth.default() finds (module docstring). Nothing is sent yet (check_reachable first, for
  one sentence at once where there is no network). One sentence where the package is not installed; where
  there are no credentials, google.auth.exceptions.DefaultCredentialsError, which the caller says in its words
  (what it could not do, and the way out it has)."""
  bucket_name, _, name = str(url).split("://", 1)[1].partition("/")
  try:
    import google.auth
    from google.cloud import storage as gcs
  except ImportError:
    raise UserError(f"cannot use {url}: gs:// needs the google-cloud-storage package, which is not installed; "
                    f"install the gcs extra (pip install 'nerfpod[gcs]').") from None
  emulator = os.environ.get("STORAGE_EMULATOR_HOST")
  if emulator:  # anonymous, as the client itself has it; a bare host:port is http, as for gcsfs
    client = gcs.Client(project=None, client_options={"api_endpoint": emulator if "://" in emulator else
                                                      "http://" + emulator})
    who = "no credentials (the storage emulator at STORAGE_EMULATOR_HOST)"
  else:
    with _quiet("google.auth._default", "google.auth.compute_engine._metadata"):
      credentials, _ = google.auth.default(scopes=GCS_SCOPES)
    # Cloud Storage's own endpoint is the client's default (with its universe and mTLS rules); another one (a
    # test's server) is named
    custom = GCS_ENDPOINT.rstrip("/") != _CLOUD_STORAGE
    client = gcs.Client(project=None, credentials=credentials,
                        client_options={"api_endpoint": GCS_ENDPOINT} if custom else None)
    who = _credentials_name(credentials)
  return GcsBucket(client.bucket(bucket_name), name, who)


@contextlib.contextmanager
def _quiet(*names: str):
  """The loggers `names` log errors only, meanwhile: google.auth warns at each place it looks for credentials
  and finds none (off a VM: three pings of a metadata server), where the caller says so in one sentence."""
  loggers = [logging.getLogger(name) for name in names]
  levels = [logger.level for logger in loggers]
  for logger in loggers:
    logger.setLevel(logging.ERROR)
  try:
    yield
  finally:
    for logger, level in zip(loggers, levels):
      logger.setLevel(level)


def _credentials_name(credentials) -> str:
  """Whose `credentials` (google.auth's) are, in words."""
  kind = type(credentials).__module__
  key_file = os.environ.get("GOOGLE_APPLICATION_CREDENTIALS")
  where = f" (the key file {key_file})" if key_file else ""
  if kind.startswith("google.auth.compute_engine"):
    return "this VM's service account (the metadata server's)"
  if kind == "google.oauth2.service_account":
    return f"service account {credentials.service_account_email}{where}"
  if key_file:
    return f"the application-default credentials in {key_file}"
  if kind == "google.oauth2.credentials":
    return "gcloud's application-default credentials of a user"
  return f"the application-default credentials ({type(credentials).__name__})"


# --- Storage that stops answering (the module's docstring). ---


class Stopped(UserError):
  """A bucket that stopped answering (or failing) mid-run: one sentence naming it and what failed. Ends the
  process at once with STOPPED_EXIT_CODE (errors.fail): threads of the storage clients may still be waiting
  on it, and nothing waits for them."""
  exit_code = STOPPED_EXIT_CODE
  ends_at_once = True


class NoAnswer(Exception):
  """within()'s deadline passed without an answer; `seconds` is the deadline."""

  def __init__(self, url: str, seconds: float):
    super().__init__(f"{bucket_of(url)} gave no answer in {seconds:g} s")
    self.url, self.seconds = url, seconds


def bucket_of(url) -> str:
  """gs://BUCKET of a URL (a local path: itself)."""
  if not is_url(url):
    return str(url)
  scheme, rest = str(url).split("://", 1)
  return f"{scheme}://{rest.split('/', 1)[0]}"


def stopped(url) -> bool:
  """Whether the bucket of `url` gave no answer within a watchdog's deadline (within()) in this process."""
  return is_url(url) and bucket_of(url) in _stopped


def mark_stopped(url) -> None:
  """Marks the bucket of `url` stopped (as within() does past its deadline): for one that failed, so that
  the run's later calls to it give up at once."""
  if is_url(url):
    _stopped.add(bucket_of(url))


def bound_clients(seconds: float) -> None:
  """Sets every storage client's own bound on a request that gets no answer to `seconds` (the module's
  docstring), for the clients made from now on; settings a user made (fsspec's configuration, tensorstore's
  environment variables) are kept. Call it where a run starts, before its first bucket request."""
  global GCS_TIMEOUT
  GCS_TIMEOUT = float(seconds)
  import fsspec.config
  for scheme in ("gs", "gcs"):  # (gcsfs's protocols)
    settings = fsspec.config.conf.setdefault(scheme, {})
    if "requests_timeout" not in settings or f"fsspec:{scheme}" in _set_here:  # (a value of the user's is kept)
      settings["requests_timeout"] = float(seconds)
      _set_here.add(f"fsspec:{scheme}")
  # tensorstore's curl transport: a request with no byte for this long fails (and is retried by its driver)
  for name, value in (("TENSORSTORE_CURL_LOW_SPEED_TIME_SECONDS", str(max(1, round(seconds)))),
                      ("TENSORSTORE_CURL_LOW_SPEED_LIMIT_BYTES", "1")):
    if name not in os.environ or name in _set_here:  # (a value of the user's is kept)
      os.environ[name] = value
      _set_here.add(name)


def gcs_timeout() -> float:
  """google-cloud-storage's `timeout=` for one request (connect, then each read)."""
  return GCS_TIMEOUT


def gcs_retry(seconds: float | None = None):
  """google-cloud-storage's `retry=`: its DEFAULT_RETRY, given up after `seconds` in all (default: GCS_TIMEOUT;
  the workdir lock's calls have a bound of their own)."""
  from google.cloud.storage.retry import DEFAULT_RETRY
  return DEFAULT_RETRY.with_timeout(GCS_TIMEOUT if seconds is None else seconds)


def gcs_retry_if_generation(retry=None):
  """google-cloud-storage's `retry=` for a write or a delete: `retry` (default: gcs_retry()), where the request
  carries a generation precondition (which makes a retry safe), as the library's own
  DEFAULT_RETRY_IF_GENERATION_SPECIFIED."""
  from google.cloud.storage.retry import ConditionalRetryPolicy, is_generation_specified
  return ConditionalRetryPolicy(gcs_retry() if retry is None else retry, is_generation_specified, ["query_params"])


def within(url, seconds: float, work):
  """work() for the storage of `url`, waited on for at most `seconds`; its result, or its exception. Past the
  deadline: NoAnswer, the call left behind in a daemon thread (it may never return), and the bucket marked
  stopped, so that later calls for it raise NoAnswer at once. A local path: work() as it is, unbounded (a
  local disk answers, or fails)."""
  if not is_url(url):
    return work()
  if stopped(url):
    raise NoAnswer(url, 0.0)
  outcome = {}
  done = threading.Event()

  def run():
    try:
      outcome["value"] = work()
    except BaseException as e:  # noqa: BLE001 (handed to the waiting thread as it is)
      outcome["error"] = e
    finally:
      done.set()

  threading.Thread(target=run, name="nerfpod-storage-call", daemon=True).start()
  if not done.wait(seconds):  # (a signal's handler still runs meanwhile: a SIGTERM is noted)
    mark_stopped(url)
    raise NoAnswer(url, seconds)
  if "error" in outcome:
    raise outcome["error"]
  return outcome["value"]
