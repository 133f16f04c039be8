"""The gs:// workdir lock against a Cloud Storage JSON API of the test's own that enforces ifGenerationMatch
(the gcp-storage-emulator package ignores it): a second run is refused naming the holder, the holder beats (a
new generation each time), a beating holder on another host is refused within a second and a stopped one taken
over after a lease, even with the server's clock an hour off this host's; of two runs racing for a stale lock
exactly one takes it; a release deletes only its own generation; no network or no credentials is one sentence."""
import email.utils
import http.server
import itertools
import json
import os
import socket
import threading
import time
import urllib.parse

import pytest

from nerfpod.workdir import lock as workdir_lock
from nerfpod.errors import UserError

BUCKET = "nerfpod-test"
WORKDIR = f"gs://{BUCKET}/runs/cup 1"  # a space and slashes in the object's name: URL-encoded on the way
NAME = "runs/cup 1/lock.json"
PATH = f"gs://{BUCKET}/{NAME}"
METADATA_TOKEN = "/computeMetadata/v1/instance/service-accounts/default/token"


class FakeGcs:
  """Cloud Storage's JSON API for what the lock uses, in memory, on 127.0.0.1 (port 0, a thread): media uploads
  (POST /upload/storage/v1/b/B/o?uploadType=media&name=N), metadata and media reads (GET /storage/v1/b/B/o/N,
  ?alt=media) and deletes, each honouring ifGenerationMatch as the service does (0: only if absent; else 412
  unless the object has that generation). Every upload makes a new generation. With `token` set it also serves
  the metadata server's and gcloud's token endpoints and wants that bearer token on every storage request."""

  def __init__(self, skew=0.0, token=None):
    self.skew = skew  # seconds this server's clock is ahead of this host's (its Date headers and `updated`)
    self.token = token  # the token its token endpoints give
    self.wanted = token  # the token its storage requests need (None: none, as an emulator)
    self.objects = {}  # (bucket, name) -> {"data": bytes, "generation": int, "updated": float}
    self.requests = []  # (method, what, status), what: "upload", "meta", "media" or "delete"
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
    """Writes the lock as another run would (its last beat `age` s ago); returns its generation."""
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

  def handle(self, method, path, query, headers, body) -> tuple[int, dict | bytes]:
    if path == METADATA_TOKEN and method == "GET":
      if headers.get("Metadata-Flavor") != "Google":
        return 403, {"error": "Missing Metadata-Flavor:Google header"}
      return 200, {"access_token": self.token, "expires_in": 3599, "token_type": "Bearer"}
    if path == "/token" and method == "POST":
      form = urllib.parse.parse_qs(body.decode())
      if form.get("grant_type") != ["refresh_token"] or form.get("refresh_token") != ["refresh-me"]:
        return 400, {"error": "invalid_grant", "error_description": "Bad Request"}
      return 200, {"access_token": self.token, "expires_in": 3599, "token_type": "Bearer"}
    if self.wanted is not None and headers.get("Authorization") != f"Bearer {self.wanted}":
      return 401, {"error": {"code": 401, "message": "Invalid Credentials."}}
    parts = path.split("/")  # the name is one segment: its slashes arrive as %2F
    if method == "POST" and parts[:5] == ["", "upload", "storage", "v1", "b"] and parts[6:] == ["o"] \
       and query.get("uploadType") == "media" and "name" in query:
      return self._upload(urllib.parse.unquote(parts[5]), query["name"], query, body)
    if parts[:4] == ["", "storage", "v1", "b"] and len(parts) == 7 and parts[5] == "o":
      key = (urllib.parse.unquote(parts[4]), urllib.parse.unquote(parts[6]))
      with self._lock:
        found = self.objects.get(key)
        if found is None:
          return 404, {"error": {"code": 404, "message": "No such object: " + "/".join(key)}}
        if not _precondition_holds(found, query):
          return 412, {"error": {"code": 412, "message": "At least one of the pre-conditions you specified "
                                                           "did not hold."}}
        if method == "DELETE":
          del self.objects[key]
          return 204, b""
        if method == "GET":
          return 200, found["data"] if query.get("alt") == "media" else _metadata(key, found)
    return 404, {"error": {"code": 404, "message": f"Not Found: {method} {path}"}}

  def _upload(self, bucket, name, query, body):
    with self._lock:
      found = self.objects.get((bucket, name))
      if not _precondition_holds(found, query):
        return 412, {"error": {"code": 412, "message": "At least one of the pre-conditions you specified did "
                                                         "not hold."}}
      found = self.objects[(bucket, name)] = {"data": body, "generation": next(self._generations),
                                              "updated": self.now()}
      return 200, _metadata((bucket, name), found)


def _precondition_holds(found, query) -> bool:
  if "ifGenerationMatch" not in query:
    return True
  want = int(query["ifGenerationMatch"])
  return found is None if want == 0 else found is not None and found["generation"] == want


def _metadata(key, found) -> dict:
  updated = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(found["updated"])) + \
      f".{int(found['updated'] % 1 * 1000):03d}Z"
  return {"kind": "storage#object", "bucket": key[0], "name": key[1], "generation": str(found["generation"]),
          "metageneration": "1", "size": str(len(found["data"])), "updated": updated}


def _handler(fake):
  class Handler(http.server.BaseHTTPRequestHandler):
    def _serve(self):
      url = urllib.parse.urlsplit(self.path)
      query = {k: v[0] for k, v in urllib.parse.parse_qs(url.query).items()}
      body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
      status, answer = fake.handle(self.command, url.path, query, self.headers, body)
      what = ("upload" if url.path.startswith("/upload/") else "delete" if self.command == "DELETE" else
              "media" if query.get("alt") == "media" else "meta")
      fake.requests.append((self.command, what, status))
      data = answer if isinstance(answer, bytes) else json.dumps(answer).encode()
      self.send_response(status)
      self.send_header("Content-Type", "application/json")
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
  monkeypatch.setenv("STORAGE_EMULATOR_HOST", fake.url)
  monkeypatch.setattr(workdir_lock, "HEARTBEAT_SECONDS", 0.1)
  monkeypatch.setattr(workdir_lock, "LEASE_SECONDS", 1.5)


@pytest.fixture
def gcs(monkeypatch):
  fake = FakeGcs()
  _serve(monkeypatch, fake)
  yield fake
  fake.close()


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
    time.sleep(0.6)
    assert gcs.generation() > first and gcs.objects[(BUCKET, NAME)]["updated"] > updated
    assert gcs.count("upload", 200) >= 4 and gcs.count("upload", 412) == 0  # the create and its beats
    assert gcs.holder()["pid"] == os.getpid()


def test_another_hosts_gs_lock_is_refused_while_it_beats_and_taken_over_once_it_stops(monkeypatch):
  fake = FakeGcs(skew=-3600.0)  # the server's clock an hour behind this host's: ages are the server's
  _serve(monkeypatch, fake)
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
      assert time.monotonic() - started < 1.0  # refused at its first beat, not at the end of a lease
    finally:
      stop.set()
      beating.join()
    started = time.monotonic()
    with workdir_lock.WorkdirLock(WORKDIR):  # the holder stopped beating: it is taken over after a lease
      assert fake.holder()["pid"] == os.getpid()
    assert 1.0 < time.monotonic() - started < 3.0
    # A heartbeat older than a lease (by the server's clock) is stale at once.
    fake.put({"host": "elsewhere-host", "pid": 1, "since": "x"}, age=60.0)
    started = time.monotonic()
    with workdir_lock.WorkdirLock(WORKDIR):
      assert fake.holder()["pid"] == os.getpid()
    assert time.monotonic() - started < 0.5
  finally:
    fake.close()


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
    for t in threads:
      t.start()
    for t in threads:
      t.join()
    assert outcomes.count("took it") == 1, outcomes
    refused = [o for o in outcomes if o != "took it"][0]
    assert f"is in use by another training run (process {os.getpid()} on host" in refused
    assert gcs.count("delete", 204) - deletes == 1  # the other delete found the stale generation gone
    winner = locks[outcomes.index("took it")]
    if late:
      assert winner is locks[0]
    assert gcs.generation() == winner._store._generation
    winner.release()
    assert gcs.holder() is None


def test_a_gs_release_deletes_only_its_own_generation(gcs, capfd):
  lock = workdir_lock.WorkdirLock(WORKDIR)
  lock.acquire()
  foreign = gcs.put({"host": "elsewhere-host", "pid": 1, "since": "x"})  # (another run took it over)
  time.sleep(0.5)
  lost = capfd.readouterr().err
  assert lost.count(f"nerfpod: warning: another run took the lock {PATH} over") == 1, lost  # said once
  assert gcs.generation() == foreign  # and no more beats onto the other run's lock
  lock.release()
  assert gcs.generation() == foreign and gcs.holder()["host"] == "elsewhere-host"
  assert gcs.count("delete", 412) == 1 and gcs.count("delete", 204) == 0


def test_no_storage_endpoint_or_no_credentials_is_one_sentence(monkeypatch, tmp_path):
  port = _closed_port()
  monkeypatch.setenv("STORAGE_EMULATOR_HOST", f"127.0.0.1:{port}")
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert _one_sentence(str(refused.value)) == (
      f"could not take the lock {PATH}: the storage emulator at http://127.0.0.1:{port} (STORAGE_EMULATOR_HOST) "
      f"does not answer (Connection refused); start it or unset STORAGE_EMULATOR_HOST, or pass a local "
      f"--workdir.")
  monkeypatch.delenv("STORAGE_EMULATOR_HOST")
  monkeypatch.setenv("GOOGLE_APPLICATION_CREDENTIALS", str(tmp_path / "none.json"))
  monkeypatch.setenv("GCE_METADATA_HOST", f"127.0.0.1:{port}")
  with pytest.raises(UserError) as refused:
    workdir_lock.WorkdirLock(WORKDIR).acquire()
  assert _one_sentence(str(refused.value)) == (
      f"could not take the lock {PATH}: there are no credentials for Cloud Storage (no application-default "
      f"credentials of a user, and the metadata server of a GCE or TPU VM at 127.0.0.1:{port} gave no token: "
      f"Connection refused); run `gcloud auth application-default login`, run on a VM with a service account, "
      f"or pass a local --workdir.")


def test_cloud_storage_is_asked_with_the_vms_or_the_users_token(monkeypatch, tmp_path):
  fake = FakeGcs(token="ya29.fake")
  _serve(monkeypatch, fake)
  monkeypatch.delenv("STORAGE_EMULATOR_HOST")
  monkeypatch.setattr(workdir_lock, "GCS_ENDPOINT", fake.url)  # Cloud Storage, not an emulator: with a token
  try:
    monkeypatch.setenv("GOOGLE_APPLICATION_CREDENTIALS", str(tmp_path / "none.json"))
    monkeypatch.setenv("GCE_METADATA_HOST", fake.host)
    with workdir_lock.WorkdirLock(WORKDIR):  # the metadata server's token (a VM's service account)
      time.sleep(0.3)
      assert fake.holder()["pid"] == os.getpid() and fake.count("upload", 200) >= 2
    assert fake.holder() is None and all(status != 401 for _, _, status in fake.requests)
    user = tmp_path / "adc.json"
    user.write_text(json.dumps({"type": "authorized_user", "client_id": "c", "client_secret": "s",
                                "refresh_token": "refresh-me", "token_uri": f"{fake.url}/token"}))
    monkeypatch.setenv("GOOGLE_APPLICATION_CREDENTIALS", str(user))
    monkeypatch.setenv("GCE_METADATA_HOST", f"127.0.0.1:{_closed_port()}")
    with workdir_lock.WorkdirLock(WORKDIR):  # gcloud's application-default credentials of a user
      assert fake.holder()["pid"] == os.getpid()
    fake.wanted = "ya29.another"  # the service no longer takes the tokens given
    with pytest.raises(UserError) as refused:
      workdir_lock.WorkdirLock(WORKDIR).acquire()
    assert _one_sentence(str(refused.value)) == (
        f"could not take the lock {PATH}: Cloud Storage refused the application-default credentials in {user} "
        f"(HTTP 401: Invalid Credentials); give them write access to bucket {BUCKET}, or pass a local --workdir.")
    user.write_text(user.read_text().replace("refresh-me", "revoked"))
    with pytest.raises(UserError) as refused:
      workdir_lock.WorkdirLock(WORKDIR).acquire()
    assert _one_sentence(str(refused.value)) == (
        f"could not take the lock {PATH}: the application-default credentials in {user} could not be turned into "
        f"an access token at {fake.url}/token (HTTP 400: invalid_grant); run `gcloud auth application-default "
        f"login` again, or pass a local --workdir.")
  finally:
    fake.close()


def test_a_service_account_key_file_without_a_metadata_server_trains_without_a_lock_saying_so(monkeypatch, tmp_path,
                                                                                             capsys):
  """Cloud Storage takes a service account's key file (orbax and tensorstore do), which this lock's client
  cannot sign with: the run is not refused for it (it trained on such a workdir before the lock existed), it
  goes on without a lock and says so."""
  port = _closed_port()
  key = tmp_path / "key.json"
  key.write_text('{"type": "service_account", "client_email": "a@b.iam.gserviceaccount.com"}')
  monkeypatch.setenv("GOOGLE_APPLICATION_CREDENTIALS", str(key))
  monkeypatch.setenv("GCE_METADATA_HOST", f"127.0.0.1:{port}")
  lock = workdir_lock.WorkdirLock(WORKDIR)
  lock.acquire()
  lock.release()
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and err.startswith(f"nerfpod: warning: no lock on {PATH}: the service account key "
                                                 f"file {key} (GOOGLE_APPLICATION_CREDENTIALS) is not one the lock "
                                                 f"can use"), err
