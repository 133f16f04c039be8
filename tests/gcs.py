"""A Cloud Storage JSON API on 127.0.0.1 for tests: the gcp-storage-emulator package, served by a process of
its own (so that the runs a test starts reach it too) on a free port, with one bucket, in memory.

    with gcs.Emulator(log_path) as emulator:   # skips the test, saying why, where the test extra lacks it
      emulator.env                         # what a process needs to use it (below)
      url = emulator.upload(local_folder, "scene")     # -> gs://nerfpod-test/scene
      emulator.files("runs/a")             # the objects under a prefix, as names relative to it
      emulator.received_bytes()            # the bytes of every request body it has received so far

Every client nerfpod uses reads the emulator's address from its own variable:
- STORAGE_EMULATOR_HOST: gcsfs (scenes, and the workdir's files through etils.epath and orbax) and
  google-cloud-storage (tensorboardX's event files, nerfpod's workdir lock); no credentials are needed;
- TENSORSTORE_GCS_HTTP_URL: tensorstore's gcs driver (orbax's arrays, the render archive);
- GCSFS_EXPERIMENTAL_ZB_HNS_SUPPORT=false stops gcsfs from probing each bucket for a zonal or hierarchical
  namespace over gRPC, which the emulator does not serve (the probe otherwise waits 60 s per bucket).

What the emulator (2026.7.19) gets wrong for these clients, patched in the serving process (`_patch`):
- a media upload (uploadType=media) whose Content-Type is application/json has its body parsed as JSON
  instead of stored as bytes, and the server fails on it (RemoteDisconnected for the client): nerfpod's
  workdir lock once uploaded lock.json that way (its client now sends multipart uploads, below). Its body is
  kept as bytes;
- a multipart upload (uploadType=multipart: gcsfs's and google-cloud-storage's for small objects) goes
  through Python's email parser, which drops a last carriage return or line feed of the object (a JSON or
  text file's final newline, any binary file that ends in one). It is split at its boundaries byte for byte
  instead;
- a listing ignores startOffset and endOffset, the only bounds tensorstore's gcs driver gives when it deletes
  a range of keys (creating an array with delete_existing, the render archive's group): it would delete every
  object of the bucket. Listings keep to [startOffset, endOffset);
- it ignores preconditions (ifGenerationMatch, ifGenerationNotMatch), and its downloads do not say the
  object's generation (x-goog-generation). tensorstore's OCDBT checkpoints re-read their manifest with
  ifGenerationNotMatch=<the generation they wrote>, expect 304 or a generation, and fail a save now and then
  ("Malformed StorageGeneration") without them; the workdir lock creates lock.json only if absent. They are
  enforced, and downloads carry the generation, as Cloud Storage does.

The serving process also prints one line (RECEIVED, then a count) for each request body it reads, so that a
test can measure how much its clients upload (received_bytes).

Run as a script, `python tests/gcs.py PORT BUCKET` serves until it is killed.
"""
import os
import pathlib
import subprocess
import sys
import time
import urllib.request

import pytest

BUCKET = "nerfpod-test"
RECEIVED = "nerfpod-test-emulator received"  # a line of the serving process's output: the bytes of a request body
# gcsfs reads this when it is imported: set before any test imports it (this module is imported at collection).
os.environ.setdefault("GCSFS_EXPERIMENTAL_ZB_HNS_SUPPORT", "false")


def _multipart_related(raw: bytes, content_type: str) -> dict:
  """A multipart/related upload (metadata JSON, then the object's bytes) split at its delimiters byte for byte.
  The line break before a delimiter belongs to it: CRLF (google-cloud-storage) or LF alone (gcsfs)."""
  import json
  delimiter = b"--" + content_type.split("boundary=", 1)[1].split(";")[0].strip().strip('"').encode()
  rest = raw[raw.index(delimiter) + len(delimiter):]
  eol = b"\r\n" if rest.startswith(b"\r\n") else b"\n"
  parts = []
  for piece in rest.split(eol + delimiter)[:-1]:  # the last is the closing "--"
    head, _, body = piece.removeprefix(eol).partition(eol + eol)
    headers = dict(line.decode().split(":", 1) for line in head.split(eol) if b":" in line)
    parts.append(({k.strip().lower(): v.strip() for k, v in headers.items()}, body))
  (_, meta), (headers, content) = parts[0], parts[1]
  return {"meta": json.loads(meta), "content": content,
          "content-type": headers.get("content-type", "application/octet-stream")}


def _patch():
  """Fixes the emulator's uploads (the module's docstring)."""
  from gcp_storage_emulator import server
  read_raw_data = server._read_raw_data

  def read_and_count(request_handler):  # every request body goes through here (server._read_data, below)
    raw = read_raw_data(request_handler)
    if raw:
      print(RECEIVED, len(raw), flush=True)
    return raw

  server._read_raw_data = read_and_count
  read_data = server._read_data

  def read_uploads_exactly(request_handler, query):
    upload = query.get("uploadType")
    content_type = request_handler.headers.get("Content-Type") or ""
    if upload == ["media"] or (upload == ["multipart"] and content_type.startswith("multipart/related")):
      raw = server._decode_raw_data(server._read_raw_data(request_handler), request_handler)
      return raw if upload == ["media"] else _multipart_related(raw, content_type)
    return read_data(request_handler, query)

  server._read_data = read_uploads_exactly

  from gcp_storage_emulator.handlers import objects
  list_objects = objects.ls

  def list_objects_in_range(request, response, storage, *args, **kwargs):
    start = (request.query.get("startOffset") or [""])[0]
    end = (request.query.get("endOffset") or [None])[0]
    get_file_list = storage.get_file_list

    def in_range(*list_args, **list_kwargs):
      files, prefixes = get_file_list(*list_args, **list_kwargs)
      keep = lambda name: start <= name and (end is None or name < end)  # noqa: E731
      return [f for f in files if keep(f["name"])], [p for p in prefixes if keep(p)]

    storage.get_file_list = in_range
    try:
      return list_objects(request, response, storage, *args, **kwargs)
    finally:
      del storage.get_file_list  # the class's own again

  replaced = {list_objects: list_objects_in_range}
  for name in ("get", "download", "delete", "insert"):
    replaced[getattr(objects, name)] = _with_preconditions(getattr(objects, name), reading=name in ("get",
                                                                                                  "download"))
  objects.download = replaced[objects.download]  # objects.get calls it for alt=media
  for _, methods in server.HANDLERS:  # the routes hold the handler functions themselves
    for method, handler in list(methods.items()):
      methods[method] = replaced.get(handler, handler)


def _with_preconditions(handler, reading: bool):
  """`handler` that first answers 412 (or 304, for a read) where the request's ifGenerationMatch or
  ifGenerationNotMatch does not hold for the object as it is, as Cloud Storage does; and whose downloads say
  the object's generation (x-goog-generation), as Cloud Storage's do."""
  from http import HTTPStatus

  from gcp_storage_emulator.exceptions import NotFound

  def handle(request, response, storage, *args, **kwargs):
    bucket = request.params["bucket_name"]
    name = request.params.get("object_id")
    if name is None:  # an upload: the name is in the query or the multipart metadata
      data = request.data if request.query.get("uploadType") == ["multipart"] else None
      name = (request.query.get("name") or [None])[0] or (data or {}).get("meta", {}).get("name")
    try:
      current = storage.get_file_obj(bucket, name)["generation"] if name else None
    except NotFound:
      current = None
    match = (request.query.get("ifGenerationMatch") or [None])[0]
    not_match = (request.query.get("ifGenerationNotMatch") or [None])[0]
    failed = None
    if match is not None and not (reading and current is None):
      if (match == "0" and current is not None) or (match != "0" and current != match):
        failed = HTTPStatus.PRECONDITION_FAILED
    if not_match is not None and current is not None and current == not_match:
      failed = HTTPStatus.NOT_MODIFIED if reading else HTTPStatus.PRECONDITION_FAILED
    if failed is not None:
      response.status = failed
      if failed == HTTPStatus.PRECONDITION_FAILED:
        response.json({"error": {"code": 412, "message": "At least one of the pre-conditions you specified did "
                                                         "not hold."}})
      return None
    result = handler(request, response, storage, *args, **kwargs)
    if reading and current is not None and response.status in (HTTPStatus.OK, HTTPStatus.PARTIAL_CONTENT):
      response["x-goog-generation"] = current
      response["x-goog-metageneration"] = "1"
    return result

  return handle


def serve(port: int, bucket: str) -> None:
  _patch()
  from gcp_storage_emulator.server import create_server
  create_server("127.0.0.1", port, in_memory=True, default_bucket=bucket).run()


class Emulator:
  """The emulator in a process of its own, started on a free port, stopped (killed) on exit."""

  def __init__(self, log_path, bucket: str = BUCKET):
    """`log_path`: a file for the emulator's own output (its errors, where a request failed)."""
    pytest.importorskip("gcp_storage_emulator", reason="the test extra's gcp-storage-emulator is not installed")
    pytest.importorskip("gcsfs", reason="the gcs extra's gcsfs is not installed")
    import portpicker
    self.bucket = bucket
    self.port = portpicker.pick_unused_port()
    self.url = f"http://127.0.0.1:{self.port}"
    self.env = {"STORAGE_EMULATOR_HOST": self.url, "TENSORSTORE_GCS_HTTP_URL": self.url,
                "GCSFS_EXPERIMENTAL_ZB_HNS_SUPPORT": "false"}
    self.log_path = pathlib.Path(log_path)
    self.log = open(self.log_path, "wb")
    self.proc = subprocess.Popen([sys.executable, str(pathlib.Path(__file__)), str(self.port), bucket],
                                 stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + 30
    while True:
      try:
        with urllib.request.urlopen(f"{self.url}/storage/v1/b/{bucket}", timeout=1):
          break
      except OSError:
        if self.proc.poll() is not None or time.monotonic() > deadline:
          self.close()
          raise AssertionError(f"the storage emulator did not start on port {self.port}:\n"
                               + self.log_path.read_text(errors="replace")[-3000:])
        time.sleep(0.1)

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def close(self):
    if self.proc.poll() is None:
      self.proc.kill()
      self.proc.wait()
    self.log.close()

  def filesystem(self):
    """A gcsfs file system of its own on the emulator (no listings cached across calls)."""
    import gcsfs
    with pytest.MonkeyPatch.context() as patch:
      for name, value in self.env.items():
        patch.setenv(name, value)
      return gcsfs.GCSFileSystem(token="anon", endpoint_url=self.url, skip_instance_cache=True,
                                 use_listings_cache=False)

  def upload(self, local, name: str) -> str:
    """Copies a local file or folder (recursively) to gs://BUCKET/name; returns that URL."""
    fs = self.filesystem()
    local = pathlib.Path(local)
    files = [local] if local.is_file() else sorted(p for p in local.rglob("*") if p.is_file())
    for path in files:
      key = name if path == local else f"{name}/{path.relative_to(local).as_posix()}"
      fs.pipe_file(f"{self.bucket}/{key}", path.read_bytes())
    return f"gs://{self.bucket}/{name}"

  def files(self, prefix: str) -> list[str]:
    """The objects under gs://BUCKET/prefix/, as names relative to it, sorted."""
    fs = self.filesystem()
    root = f"{self.bucket}/{prefix.strip('/')}"
    return sorted(p[len(root) + 1:] for p in fs.find(root))

  def received_bytes(self) -> int:
    """The bytes of all the request bodies (uploads, mostly) the emulator has received so far."""
    self.log.flush()
    return sum(int(line.split()[-1]) for line in self.log_path.read_text(errors="replace").splitlines()
               if line.startswith(RECEIVED))

  def read(self, name: str) -> bytes:
    return self.filesystem().cat_file(f"{self.bucket}/{name}")

  def delete(self, name: str) -> None:
    self.filesystem().rm_file(f"{self.bucket}/{name}")


class Proxy:
  """A TCP forwarder on a free port of 127.0.0.1 in front of an emulator, that can stop answering: the storage
  of a run that goes away mid-run (a partition, an outage) and comes back with its objects, which the emulator
  keeps in memory meanwhile.

      with gcs.Proxy(emulator) as proxy:   # proxy.env: the emulator's env, pointing at the proxy
        proxy.silent_at(b"runs/a/checkpoints/10/")  # silent from the first request naming it (unquoted)
        proxy.went_silent.wait()
        proxy.forward()                    # new connections reach the emulator again

  Silent: every connection, open or new, is read but never answered. A connection that went silent stays
  silent (its client gives up on it and opens another); its side towards the emulator is shut, as the
  emulator serves one connection at a time and would wait for the rest of a request cut off."""

  def __init__(self, emulator: Emulator):
    import socket
    import threading
    self.target = ("127.0.0.1", emulator.port)
    self.listener = socket.create_server(("127.0.0.1", 0))
    self.port = self.listener.getsockname()[1]
    self.url = f"http://127.0.0.1:{self.port}"
    self.env = dict(emulator.env, STORAGE_EMULATOR_HOST=self.url, TENSORSTORE_GCS_HTTP_URL=self.url)
    self.went_silent = threading.Event()
    self._marker = None
    self.refusing = False
    self._closed = False
    self._sockets = []
    threading.Thread(target=self._accept, daemon=True).start()

  def silent(self) -> None:
    self.went_silent.set()

  def silent_at(self, marker: bytes) -> None:
    """Goes silent at the first request whose bytes, unquoted (%2F -> /), hold `marker`: it is not answered,
    nor is any request after it."""
    self._marker = marker

  def refuse(self) -> None:
    """Refuses every connection from now on, and cuts the open ones: the emulator's process stopped."""
    self.refusing = True
    for sock in list(self._sockets):
      try:
        sock.shutdown(2)
      except OSError:
        pass

  def forward(self) -> None:
    self._marker = None
    self.refusing = False
    self.went_silent.clear()

  def _accept(self) -> None:
    import socket
    import struct
    import threading
    while not self._closed:
      try:
        client, _ = self.listener.accept()
      except OSError:
        return
      if self.refusing:
        client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # a reset, at once
        client.close()
        continue
      self._sockets.append(client)
      upstream = None
      if not self.went_silent.is_set():
        try:
          upstream = socket.create_connection(self.target)
          self._sockets.append(upstream)
        except OSError:
          client.close()
          continue
      muted = threading.Event()  # this connection went silent: for good
      threading.Thread(target=self._pump, args=(client, upstream, upstream, muted, True), daemon=True).start()
      if upstream is not None:
        threading.Thread(target=self._pump, args=(upstream, client, upstream, muted, False), daemon=True).start()

  def _pump(self, source, sink, upstream, muted, asks: bool) -> None:
    """Copies source to sink (`asks`: the client's side) until either closes; once the proxy is silent, drops
    what comes instead, and shuts the connection's side towards the emulator."""
    import socket
    import urllib.parse
    try:
      while data := source.recv(65536):
        if asks and self._marker is not None and self._marker in urllib.parse.unquote_to_bytes(data):
          self.went_silent.set()
        if self.went_silent.is_set() and not muted.is_set():
          muted.set()
          if upstream is not None:
            try:
              upstream.shutdown(socket.SHUT_RDWR)
            except OSError:
              pass
        if muted.is_set():
          if not asks:
            return
          continue
        sink.sendall(data)
    except OSError:
      pass
    if not muted.is_set() and sink is not None:
      try:
        sink.shutdown(socket.SHUT_WR)
      except OSError:
        pass

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def close(self) -> None:
    self._closed = True
    self.listener.close()
    for sock in self._sockets:
      try:
        sock.close()
      except OSError:
        pass


if __name__ == "__main__":
  serve(int(sys.argv[1]), sys.argv[2])
