"""The gs:// workdir lock (google-cloud-storage) against a Cloud Storage JSON API of the test's own that enforces
ifGenerationMatch as the service does: a second run is refused naming the holder, the holder beats (a new
generation each time), a beating holder on another host is refused within a second and a stopped one taken over
after a lease, with the server's clock an hour off this host's either way; of two runs racing for a stale lock
exactly one takes it; a release deletes only its own generation; a 503 is retried, and a write whose answer was
lost is found to be the lock's own; no network, no bucket or no credentials is one sentence. As Cloud Storage
itself (not an emulator), it wants a bearer token, which the lock gets from every kind of credentials
google.auth.default() finds that a test can point at it: a VM's metadata server, a user's application-default
credentials (a refresh token), and a service account's key file (a signed JWT)."""
import base64
import email.utils
import hashlib
import http.server
import itertools
import json
import logging
import os
import socket
import threading
import time
import urllib.parse

import pytest

from gcs import _multipart_related as multipart_related
from lock_clock import until, watch_clock
from nerfpod import storage
from nerfpod.workdir import lock as workdir_lock
from nerfpod.errors import UserError

BUCKET = "nerfpod-test"
WORKDIR = f"gs://{BUCKET}/runs/cup 1"  # a space and slashes in the object's name: URL-encoded on the way
NAME = "runs/cup 1/lock.json"
PATH = f"gs://{BUCKET}/{NAME}"
GOOGLE_TOKEN_URI = "https://oauth2.googleapis.com/token"  # a service account's JWT's audience, wherever it is sent


class FakeGcs:
  """Cloud Storage's JSON API for what the lock's client (google-cloud-storage) sends, in memory, on 127.0.0.1
  (port 0, a thread): uploads (POST /upload/storage/v1/b/B/o, uploadType=multipart with the name in its metadata
  part, or uploadType=media&name=N), metadata reads (GET /storage/v1/b/B/o/N), downloads (GET
  /download/storage/v1/b/B/o/N?alt=media, and /storage/v1/... with alt=media) and deletes, each honouring
  ifGenerationMatch as the service does (0: only if absent; else 412 unless the object has that generation), and
  a download's generation=G (404 unless the object has it). Every upload makes a new generation; one bucket,
  BUCKET (404 for any other; its metadata at GET /storage/v1/b/B, which the client reads by itself). Other query parameters (projection, prettyPrint, ...) are taken and ignored.

  With `token` set it also serves the endpoints credentials get their access tokens from, and wants that bearer
  token on every storage request (`wanted`): the metadata server of a VM (its ping at /, its service account and
  token under /computeMetadata/v1/, each wanting Metadata-Flavor: Google), and an OAuth token endpoint (/token)
  taking a user's refresh token ("refresh-me") or a service account's signed JWT (the JWT-bearer grant, its
  RS256 signature checked against `service_account`'s public key, its claims: that account, Google's token
  endpoint as the audience, a Cloud Storage scope).

  `faults[what]` (what: "upload", "meta", "media", "delete") is a list of what the next such requests meet, one
  each: "503" (refused before anything is done) or "lost" (done, but answered 503, as if the answer were lost)."""

  def __init__(self, skew=0.0, token=None):
    self.skew = skew  # seconds this server's clock is ahead of this host's (its Date headers and `updated`)
    self.token = token  # the token its token endpoints give
    self.wanted = token  # the token its storage requests need (None: none, as an emulator)
    self.service_account = None  # (client_email, RSA public key) whose signed JWTs /token takes
    self.objects = {}  # (bucket, name) -> {"data": bytes, "generation": int, "updated": float}
    self.requests = []  # (method, what, status), what: "upload", "meta", "media", "delete", "token", "metadata"
    self.faults = {}  # what -> ["503" | "lost", ...]
    self._lock = threading.Lock()
    self._generations = itertools.count(1_764_000_000_000_000)
    self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _handler(self))
    self.url = f"http://127.0.0.1:{self.server.server_port}"
    self.host = f"127.0.0.1:{self.server.server_port}"
    self._thread = threading.Thread(target=self.server.serve_forever, args=(0.05,), daemon=True)
    self._thread.start()

  def close(self):
    self.server.shutdown()
    self.server.server_close()

  def now(self) -> float:
    return time.time() + self.skew

  def put(self, holder, age=0.0, name=NAME) -> int:
    """Writes the lock as another run would (its last beat `age` s ago by this server's clock); returns its
    generation."""
    with self._lock:
      generation = next(self._generations)
      self.objects[(BUCKET, name)] = {"data": json.dumps(holder).encode(), "generation": generation,
                                      "updated": self.now() - age}
      return generation

  def beat(self, name=NAME):
    """Another host's heartbeat: the same lock uploaded again."""
    self.put(self.holder(name), name=name)

  def holder(self, name=NAME) -> dict | None:
    found = self.objects.get((BUCKET, name))
    return None if found is None else json.loads(found["data"])

  def generation(self, name=NAME) -> int | None:
    found = self.objects.get((BUCKET, name))
    return None if found is None else found["generation"]

  def count(self, what, status) -> int:
    return sum(1 for _, w, s in self.requests if (w, s) == (what, status))

  def handle(self, method, path, query, headers, body) -> tuple[int, dict | bytes, dict]:
    """The status, body and extra headers of the answer to one request."""
    if path == "/" or path.startswith("/computeMetadata/"):
      return self._metadata_server(path, headers)
    if path == "/token" and method == "POST":
      return self._token_endpoint(urllib.parse.parse_qs(body.decode()))
    if self.wanted is not None and headers.get("Authorization") != f"Bearer {self.wanted}":
      return _error(401, "Invalid Credentials.")
    parts = path.split("/")  # the name is one segment: its slashes arrive as %2F
    if method == "GET" and parts[:4] == ["", "storage", "v1", "b"] and len(parts) == 5:
      if urllib.parse.unquote(parts[4]) != BUCKET:  # (the client's own look at the bucket, in the background)
        return _error(404, "The specified bucket does not exist.")
      return 200, {"kind": "storage#bucket", "name": BUCKET, "projectNumber": "123456", "location": "US"}, {}
    if parts[:2] == ["", "download"]:
      parts = [""] + parts[2:]  # the same object, its media
      query = {**query, "alt": "media"}
    if method == "POST" and parts[:5] == ["", "upload", "storage", "v1", "b"] and parts[6:] == ["o"]:
      bucket = urllib.parse.unquote(parts[5])
      if query.get("uploadType") == "media" and "name" in query:
        return self._upload(bucket, query["name"], query, body)
      if query.get("uploadType") == "multipart":
        upload = multipart_related(body, headers.get("Content-Type", ""))
        return self._upload(bucket, upload["meta"]["name"], query, upload["content"])
    if parts[:4] == ["", "storage", "v1", "b"] and len(parts) == 7 and parts[5] == "o" and \
       method in ("GET", "DELETE"):
      key = (urllib.parse.unquote(parts[4]), urllib.parse.unquote(parts[6]))
      if key[0] != BUCKET:
        return _error(404, "The specified bucket does not exist.")
      with self._lock:
        found = self.objects.get(key)
        if found is None or ("generation" in query and int(query["generation"]) != found["generation"]):
          return _error(404, "No such object: " + "/".join(key))
        if not _precondition_holds(found, query):
          return _error(412, "At least one of the pre-conditions you specified did not hold.")
        if method == "DELETE":
          del self.objects[key]
          return 204, b"", {}
        if query.get("alt") == "media":
          return 200, found["data"], {"x-goog-generation": str(found["generation"]),
                                      "x-goog-hash": "md5=" + base64.b64encode(hashlib.md5(found["data"]).digest())
                                      .decode(), "Content-Type": "application/json"}
        return 200, _metadata(key, found), {}
    return _error(404, f"Not Found: {method} {path}")

  def _upload(self, bucket, name, query, body):
    if bucket != BUCKET:
      return _error(404, "The specified bucket does not exist.")
    with self._lock:
      found = self.objects.get((bucket, name))
      if not _precondition_holds(found, query):
        return _error(412, "At least one of the pre-conditions you specified did not hold.")
      found = self.objects[(bucket, name)] = {"data": body, "generation": next(self._generations),
                                              "updated": self.now()}
      return 200, _metadata((bucket, name), found), {}

  def _metadata_server(self, path, headers):
    flavor = {"Metadata-Flavor": "Google"}
    if self.token is None:
      return 404, b"", {}
    if headers.get("Metadata-Flavor") != "Google":
      return 403, {"error": "Missing Metadata-Flavor:Google header"}, flavor
    # The account by its alias or by its email, as a VM's metadata server serves it (google-auth asks by the
    # email once it has read it, e.g. when its regional access boundary lookup, in a thread of its own, got it
    # first).
    email = "vm@nerfpod-test.iam.gserviceaccount.com"
    account = next((f"/computeMetadata/v1/instance/service-accounts/{name}/" for name in ("default", email)
                    if path.startswith(f"/computeMetadata/v1/instance/service-accounts/{name}/")), None)
    if path == "/":
      return 200, b"", flavor
    if path == account:
      return 200, {"aliases": ["default"], "email": email,
                   "scopes": ["https://www.googleapis.com/auth/cloud-platform"]}, flavor
    if account and path == account + "token":
      return 200, {"access_token": self.token, "expires_in": 3599, "token_type": "Bearer"}, flavor
    return 404, b"not found", flavor

  def _token_endpoint(self, form):
    grant = (form.get("grant_type") or [""])[0]
    if grant == "refresh_token" and form.get("refresh_token") == ["refresh-me"]:
      return 200, {"access_token": self.token, "expires_in": 3599, "token_type": "Bearer"}, {}
    if grant == "urn:ietf:params:oauth:grant-type:jwt-bearer" and self.service_account is not None:
      claims = _verified_jwt((form.get("assertion") or [""])[0], self.service_account[1])
      if claims is not None and claims.get("iss") == self.service_account[0] and \
         claims.get("aud") == GOOGLE_TOKEN_URI and "devstorage" in claims.get("scope", ""):
        return 200, {"access_token": self.token, "expires_in": 3599, "token_type": "Bearer"}, {}
    return 400, {"error": "invalid_grant", "error_description": "Bad Request"}, {}


def _verified_jwt(assertion: str, public_key) -> dict | None:
  """The claims of a JWT signed with RS256 by the key whose public half is `public_key`, None for any other."""
  from cryptography.exceptions import InvalidSignature
  from cryptography.hazmat.primitives import hashes
  from cryptography.hazmat.primitives.asymmetric import padding

  def decode(part):
    return base64.urlsafe_b64decode(part + "=" * (-len(part) % 4))

  try:
    header, payload, signature = assertion.split(".")
    if json.loads(decode(header)).get("alg") != "RS256":
      return None
    public_key.verify(decode(signature), f"{header}.{payload}".encode(), padding.PKCS1v15(), hashes.SHA256())
    return json.loads(decode(payload))
  except (ValueError, InvalidSignature):
    return None


def _error(code, message):
  return code, {"error": {"code": code, "message": message, "errors": [{"message": message}]}}, {}


def _precondition_holds(found, query) -> bool:
  if "ifGenerationMatch" not in query:
    return True
  want = int(query["ifGenerationMatch"])
  return found is None if want == 0 else found is not None and found["generation"] == want


def _metadata(key, found) -> dict:
  updated = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(found["updated"])) + \
      f".{int(found['updated'] % 1 * 1000):03d}Z"
  return {"kind": "storage#object", "bucket": key[0], "name": key[1], "generation": str(found["generation"]),
          "metageneration": "1", "size": str(len(found["data"])), "updated": updated,
          "contentType": "application/json"}


def _what(method, path, query) -> str:
  if path == "/token":
    return "token"
  if path == "/" or path.startswith("/computeMetadata/"):
    return "metadata"
  if path.count("/") == 4:
    return "bucket"
  return ("upload" if path.startswith("/upload/") else "delete" if method == "DELETE" else
          "media" if path.startswith("/download/") or query.get("alt") == "media" else "meta")


def _handler(fake):
  class Handler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"  # keep-alive, as the client's connection pool expects

    def _serve(self):
      url = urllib.parse.urlsplit(self.path)
      query = {k: v[0] for k, v in urllib.parse.parse_qs(url.query).items()}
      body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
      what = _what(self.command, url.path, query)
      fault = None
      with fake._lock:
        if fake.faults.get(what):
          fault = fake.faults[what].pop(0)
      if fault == "503":
        status, answer, headers = _error(503, "Service Unavailable: try again.")
      else:
        status, answer, headers = fake.handle(self.command, url.path, query, self.headers, body)
        if fault == "lost":
          status, answer, headers = _error(503, "Service Unavailable: try again.")
      fake.requests.append((self.command, what, status))
      data = answer if isinstance(answer, bytes) else json.dumps(answer).encode()
      self.send_response(status)
      headers = {"Content-Type": "application/json", **headers}
      for name, value in headers.items():
        self.send_header(name, value)
      self.send_header("Content-Length", str(len(data)))
      self.end_headers()
      self.wfile.write(data)

    do_GET = do_POST = do_DELETE = _serve

    def date_time_string(self, timestamp=None):
      return email.utils.formatdate(fake.now() if timestamp is None else timestamp, usegmt=True)

    def log_message(self, *args):
      pass

  return Handler


def _serve(monkeypatch, fake):
  monkeypatch.setenv("STORAGE_EMULATOR_HOST", fake.host)  # host:port, no scheme (tests/gcs.py's has http://)
  monkeypatch.setattr(workdir_lock, "HEARTBEAT_SECONDS", 0.1)
  monkeypatch.setattr(workdir_lock, "LEASE_SECONDS", 1.5)


@pytest.fixture
def gcs(monkeypatch):
  fake = FakeGcs()
  _serve(monkeypatch, fake)
  yield fake
  fake.close()


@pytest.fixture
def cloud(monkeypatch, tmp_path):
  """FakeGcs as Cloud Storage itself (not an emulator: requests carry credentials, which google.auth.default()
  finds), wanting the token "ya29.fake"; no credentials anywhere yet: no GOOGLE_APPLICATION_CREDENTIALS, an empty
  gcloud configuration, and a metadata server on a port nothing listens on."""
  fake = FakeGcs(token="ya29.fake")
  _serve(monkeypatch, fake)
  monkeypatch.delenv("STORAGE_EMULATOR_HOST")
  monkeypatch.setattr(storage, "GCS_ENDPOINT", fake.url)
  monkeypatch.delenv("GOOGLE_APPLICATION_CREDENTIALS", raising=False)
  monkeypatch.setenv("CLOUDSDK_CONFIG", str(tmp_path / "gcloud"))
  _metadata_server(monkeypatch, f"127.0.0.1:{_closed_port()}")
  yield fake
  fake.close()


def _metadata_server(monkeypatch, host):
  """Points google-auth's look for a GCE metadata server at `host`: its ping reads GCE_METADATA_IP at each look,
  its requests the GCE_METADATA_HOST it read when imported (so the module's copy is set too)."""
  from google.auth.compute_engine import _metadata
  monkeypatch.setenv("GCE_METADATA_IP", host)
  monkeypatch.setenv("GCE_METADATA_HOST", host)
  monkeypatch.setattr(_metadata, "_GCE_METADATA_HOST", host)
  monkeypatch.setattr(_metadata, "detect_gce_residency_linux", lambda: False)  # this machine may be a GCE VM


def _closed_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _one_sentence(message: str) -> str:
  assert message.count(". ") == 0 and message.endswith(".") and "\n" not in message, message
  return message


def test_a_held_gs_workdir_is_refused_naming_the_holder_and_released_at_the_end(gcs):
  with workdir_lock.WorkdirLock(WORKDIR) as lock:
    assert lock.path == PATH
    holder = gcs.holder()
    assert holder["host"] == socket.gethostname() and holder["pid"] == os.getpid()
    with pytest.raises(UserError) as refused:
      workdir_lock.WorkdirLock(WORKDIR).acquire()
    assert f"workdir {WORKDIR} is in use by another training run (process {os.getpid()} on host " \
           f"{socket.gethostname()} since {holder['since']} holds {PATH})" in _one_sentence(str(refused.value))
  assert gcs.holder() is None and gcs.count("delete", 204) == 1
  with workdir_lock.WorkdirLock(WORKDIR):  # free again
    assert gcs.holder()["pid"] == os.getpid()


def test_the_gs_holder_beats_a_new_generation_each_time(gcs):
  with workdir_lock.WorkdirLock(WORKDIR):
    first = gcs.generation()
    updated = gcs.objects[(BUCKET, NAME)]["updated"]
    until(lambda: gcs.count("upload", 200) >= 4)  # the create and three beats (0.1 s apart; a busy machine's 10 s)
    assert gcs.generation() > first and gcs.objects[(BUCKET, NAME)]["updated"] > updated
    assert gcs.count("upload", 200) >= 4 and gcs.count("upload", 412) == 0
    assert gcs.holder()["pid"] == os.getpid()


@pytest.mark.parametrize("skew", [-3600.0, 3600.0], ids=["server-an-hour-behind", "server-an-hour-ahead"])
def test_another_hosts_gs_lock_is_refused_while_it_beats_and_taken_over_once_it_stops(monkeypatch, skew):
  """The server's clock (its `updated`) an hour off this host's either way: a lock's age is never judged from
  it, only from its generation watched by this host's clock."""
  fake = FakeGcs(skew=skew)
  _serve(monkeypatch, fake)
  monkeypatch.setattr(workdir_lock, "LEASE_SECONDS", 3.0)  # well above how long a look takes on a busy machine
  try:
    fake.put({"host": "elsewhere-host", "pid": 12345, "since": "2026-01-01T00:00:00"})
    stop = threading.Event()

    def beat():
      while not stop.wait(0.1):
        fake.beat()

    beating = threading.Thread(target=beat)
    beating.start()
    try:
      started = time.monotonic()
      with pytest.raises(UserError, match="process 12345 on host elsewhere-host since 2026-01-01T00:00:00"):
        workdir_lock.WorkdirLock(WORKDIR).acquire()
      assert time.monotonic() - started < 2.0  # refused at its first beat, not at the end of a lease
    finally:
      stop.set()
      beating.join()
    clock = watch_clock(monkeypatch)  # nothing beats from here on: a lease passes on the watch's clock
    started = clock.monotonic()
    with workdir_lock.WorkdirLock(WORKDIR):  # the holder stopped beating: it is taken over after a lease
      assert fake.holder()["pid"] == os.getpid()
    assert 3.0 < clock.monotonic() - started < 4.5  # the lease, a look's sleep past it and a second of real time
    # A lock whose `updated` says it beat a minute ago (by the server's clock) is watched for a lease all the
    # same: the server's clock is not this host's.
    fake.put({"host": "elsewhere-host", "pid": 1, "since": "x"}, age=60.0)
    started = clock.monotonic()
    with workdir_lock.WorkdirLock(WORKDIR):
      assert fake.holder()["pid"] == os.getpid()
    assert 3.0 < clock.monotonic() - started < 4.5
  finally:
    fake.close()


def _agreed(gcs, lock, within_s=2.0):
  """Whether the lock's generation is the stored object's: beats run every 0.1 s here, so a beat in flight (the
  object written, its answer not yet read) is waited out rather than taken for a disagreement."""
  agree = lambda: gcs.generation() == lock._store._generation  # noqa: E731
  until(agree, within_s)
  return agree()


@pytest.mark.parametrize("late", [False, True], ids=["together", "one-late"])
def test_of_two_runs_racing_for_a_stale_gs_lock_exactly_one_takes_it(gcs, monkeypatch, late):
  """Both runs judge the same lock stale before either removes it; then both remove it at once (together), or
  one removes it only after the other has taken the lock anew (one-late: its delete must miss the new one)."""
  remove_stale = workdir_lock._GcsLock.remove_stale
  both_judged = threading.Barrier(2, timeout=10)
  first_took = threading.Event()

  def remove_when_both_judged(self, look):
    both_judged.wait()
    if late and threading.current_thread().name == "late":
      first_took.wait(timeout=10)
    remove_stale(self, look)

  monkeypatch.setattr(workdir_lock._GcsLock, "remove_stale", remove_when_both_judged)
  clock = watch_clock(monkeypatch)  # the stale lock's lease passes on the watch's clock (nothing beats it)
  for _ in range(3):
    deletes = gcs.count("delete", 204)
    gcs.put({"host": "elsewhere-host", "pid": 1, "since": "x"}, age=60.0)
    locks = [workdir_lock.WorkdirLock(WORKDIR) for _ in range(2)]
    outcomes = [None, None]
    both_judged.reset()
    first_took.clear()

    def run(i):
      try:
        locks[i].acquire()
        outcomes[i] = "took it"
        first_took.set()
      except UserError as e:
        outcomes[i] = str(e)

    threads = [threading.Thread(target=run, args=(i,), name=["early", "late"][i]) for i in range(2)]
    slept = clock.offset
    for t in threads:
      t.start()
    for t in threads:
      t.join()
    assert clock.offset - slept >= workdir_lock.LEASE_SECONDS  # watched for a lease (the two share the clock)
    assert outcomes.count("took it") == 1, outcomes
    refused = [o for o in outcomes if o != "took it"][0]
    assert f"is in use by another training run (process {os.getpid()} on host" in refused
    assert gcs.count("delete", 204) - deletes == 1  # the other delete found the stale generation gone
    winner = locks[outcomes.index("took it")]
    if late:
      assert winner is locks[0]
    assert _agreed(gcs, winner)
    winner.release()
    assert gcs.holder() is None


def test_a_gs_release_deletes_only_its_own_generation(gcs, capfd):
  lock = workdir_lock.WorkdirLock(WORKDIR)
  lock.acquire()
  foreign = gcs.put({"host": "elsewhere-host", "pid": 1, "since": "x"})  # (another run took it over)
  said = []
  until(lambda: said.append(capfd.readouterr().err) or "took the lock" in "".join(said))  # at its next beat
  time.sleep(0.3)  # three more beats' time: the warning is said once, and nothing more is written
  lost = "".join(said) + capfd.readouterr().err
  assert lost.count(f"nerfpod: warning: another run took the lock {PATH} over") == 1, lost  # said once
  assert gcs.generation() == foreign  # and no more beats onto the other run's lock
  lock.release()
  assert gcs.generation() == foreign and gcs.holder()["host"] == "elsewhere-host"
  assert gcs.count("delete", 412) == 1 and gcs.count("delete", 204) == 0


def test_no_storage_endpoint_no_bucket_or_no_credentials_is_one_sentence(monkeypatch, cloud, tmp_path, caplog):
  port = _closed_port()
  monkeypatch.setenv("STORAGE_EMULATOR_HOST", f"127.0.0.1:{port}")
  # The endpoints this process has reached are not checked again (storage.check_reachable): the port, free now,
  # may be one an earlier test's emulator listened on.
  monkeypatch.setattr(storage, "_reached", set())
  started = time.monotonic()
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert _one_sentence(str(refused.value)) == (
      f"cannot reach Cloud Storage at 127.0.0.1:{port} to read {PATH} (Connection refused); start the storage "
      f"emulator that STORAGE_EMULATOR_HOST=127.0.0.1:{port} names, or unset it.")
  monkeypatch.delenv("STORAGE_EMULATOR_HOST")
  missing = tmp_path / "none.json"
  monkeypatch.setenv("GOOGLE_APPLICATION_CREDENTIALS", str(missing))
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert _one_sentence(str(refused.value)) == (
      f"could not take the lock {PATH}: there are no credentials for Cloud Storage (File {missing} was not "
      f"found); run `gcloud auth application-default login`, point GOOGLE_APPLICATION_CREDENTIALS at a service "
      f"account's key file, run on a VM with a service account, or pass a local --workdir.")
  monkeypatch.delenv("GOOGLE_APPLICATION_CREDENTIALS")  # and no gcloud login, no metadata server: google-auth
  # told not to look for one (its NO_GCE_CHECK, as where no VM is), whose looks wait 3 s between them
  from google.auth.compute_engine import _metadata
  monkeypatch.setattr(_metadata, "_NO_GCE_CHECK", True)
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert _one_sentence(str(refused.value)).startswith(
      f"could not take the lock {PATH}: there are no credentials for Cloud Storage (Your default credentials "
      f"were not found")
  assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []  # only the sentence
  monkeypatch.setattr(_metadata, "_NO_GCE_CHECK", False)
  _metadata_server(monkeypatch, cloud.host)  # a VM's service account, on a workdir in a bucket that is not there
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock("gs://no-such-bucket/runs/cup").acquire()
  assert _one_sentence(str(refused.value)) == (
      "could not take the lock gs://no-such-bucket/runs/cup/lock.json: Cloud Storage has no bucket no-such-bucket "
      "(HTTP 404: The specified bucket does not exist); check --workdir, or create the bucket first.")
  assert time.monotonic() - started < 20  # no client's minutes of retries


def test_cloud_storage_is_asked_with_the_vms_or_the_users_token(monkeypatch, cloud, tmp_path):
  _metadata_server(monkeypatch, cloud.host)
  with workdir_lock.WorkdirLock(WORKDIR):  # the metadata server's token (a VM's service account)
    until(lambda: cloud.count("upload", 200) >= 2)  # the create and a beat
    assert cloud.holder()["pid"] == os.getpid() and cloud.count("upload", 200) >= 2
  assert cloud.holder() is None and cloud.count("delete", 204) == 1
  assert all(status != 401 for _, _, status in cloud.requests)
  assert cloud.count("metadata", 200) >= 2 and cloud.count("token", 200) == 0
  _metadata_server(monkeypatch, f"127.0.0.1:{_closed_port()}")
  user = tmp_path / "adc.json"
  user.write_text(json.dumps({"type": "authorized_user", "client_id": "c", "client_secret": "s",
                              "refresh_token": "refresh-me", "token_uri": f"{cloud.url}/token"}))
  monkeypatch.setenv("GOOGLE_APPLICATION_CREDENTIALS", str(user))
  from google.oauth2 import credentials  # a user's token_uri is always Google's (google-auth ignores the file's)
  monkeypatch.setattr(credentials, "_GOOGLE_OAUTH2_TOKEN_ENDPOINT", f"{cloud.url}/token")
  with workdir_lock.WorkdirLock(WORKDIR):  # gcloud's application-default credentials of a user
    assert cloud.holder()["pid"] == os.getpid() and cloud.count("token", 200) >= 1
  cloud.wanted = "ya29.another"  # the service no longer takes the tokens given
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert _one_sentence(str(refused.value)) == (
      f"could not take the lock {PATH}: Cloud Storage refused the application-default credentials in {user} "
      f"(HTTP 401: Invalid Credentials); give them write access to bucket {BUCKET}, or pass a local --workdir.")
  user.write_text(user.read_text().replace("refresh-me", "revoked"))
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert _one_sentence(str(refused.value)) == (
      f"could not take the lock {PATH}: the application-default credentials in {user} gave no access token "
      f"(invalid_grant: Bad Request); renew them (`gcloud auth application-default login`, a new key file), or "
      f"pass a local --workdir.")


def _service_account_key(path, token_uri, email="trainer@nerfpod-test.iam.gserviceaccount.com"):
  """A service account's key file (as the Cloud console makes them) with a new RSA key; returns its public key."""
  from cryptography.hazmat.primitives import serialization
  from cryptography.hazmat.primitives.asymmetric import rsa
  key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
  pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                          serialization.NoEncryption()).decode()
  path.write_text(json.dumps({"type": "service_account", "project_id": "nerfpod-test", "private_key_id": "k1",
                              "private_key": pem, "client_email": email, "client_id": "1",
                              "token_uri": token_uri}))
  return key.public_key()


def test_a_service_account_key_file_takes_the_lock(monkeypatch, cloud, tmp_path):
  """GOOGLE_APPLICATION_CREDENTIALS naming a service account's key file (off a VM): its signed JWT is traded for
  a token (the JWT-bearer grant), which the storage requests carry; the lock is taken and a second run refused."""
  key = tmp_path / "key.json"
  email = "trainer@nerfpod-test.iam.gserviceaccount.com"
  cloud.service_account = (email, _service_account_key(key, f"{cloud.url}/token", email))
  monkeypatch.setenv("GOOGLE_APPLICATION_CREDENTIALS", str(key))
  with workdir_lock.WorkdirLock(WORKDIR):
    until(lambda: cloud.count("upload", 200) >= 2)  # the create and a beat
    assert cloud.holder()["pid"] == os.getpid() and cloud.count("upload", 200) >= 2
    with pytest.raises(UserError, match=f"is in use by another training run \\(process {os.getpid()} on host"):
      workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert cloud.holder() is None and cloud.count("token", 200) >= 1
  assert all(status != 401 for _, _, status in cloud.requests)
  _service_account_key(key, f"{cloud.url}/token", email)  # a key the service account does not have
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert _one_sentence(str(refused.value)) == (
      f"could not take the lock {PATH}: service account {email} (the key file {key}) gave no access token "
      f"(invalid_grant: Bad Request); renew them (`gcloud auth application-default login`, a new key file), or "
      f"pass a local --workdir.")


def test_the_locks_calls_are_retried_and_a_lost_answer_is_its_own(gcs, capfd, monkeypatch):
  """A 503 is tried again (google-cloud-storage's retries, which the generation preconditions allow); a write or
  delete done whose answer was lost is found done on the retry (412 or 404): a create or beat finds the lock
  there its own, a release is done. (The retries wait 0.05-0.2 s here rather than the client's 1 s and more.)"""
  retry = workdir_lock._GcsLock._retry
  monkeypatch.setattr(workdir_lock._GcsLock, "_retry",
                      staticmethod(lambda: retry().with_delay(initial=0.05, maximum=0.2, multiplier=2.0)))
  gcs.faults = {"upload": ["503", "lost"]}  # the create refused once, then done but its answer lost
  with workdir_lock.WorkdirLock(WORKDIR) as lock:
    assert gcs.holder()["pid"] == os.getpid() and _agreed(gcs, lock)
    assert gcs.count("upload", 412) == 1  # the create's retry
    gcs.faults = {"upload": ["lost"]}  # a beat done, its answer lost
    until(lambda: gcs.count("upload", 412) == 2)  # the beat (every 0.1 s), its answer lost, its retry
    assert gcs.count("upload", 412) == 2 and _agreed(gcs, lock)
    gcs.faults = {"delete": ["lost"]}
  assert gcs.holder() is None and gcs.count("delete", 503) == 1 and gcs.count("delete", 404) == 1
  assert "warning" not in capfd.readouterr().err
