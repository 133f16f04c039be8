"""One writer per workdir: a training run holds WORKDIR/lock.json from start to end; a second one is refused.

    with WorkdirLock(workdir):   # process 0 of a training run; UserError if another live run holds it
      ...

The lock file is created only if absent (O_CREAT | O_EXCL: atomic on a local or network file system) and says
who holds it: {"host", "pid", "process_start", "since"}. While the run lasts, a thread touches it every
HEARTBEAT_SECONDS; the run removes it when it ends, however it ends short of SIGKILL.

A lock that is there when a run starts is the holder's, unless the holder is gone:
- on this host, the holder process no longer exists (its pid is gone, or now belongs to a process that started
  at another time): taken over at once;
- on another host (its process cannot be seen from here), its heartbeat stopped: the file has not been
  touched for LEASE_SECONDS. A heartbeat younger than that is watched for up to one lease: if the holder
  touches it, the run is refused (within seconds, as it beats every HEARTBEAT_SECONDS); if not, the holder
  is taken as dead and the lock taken over.
Taking over renames the stale file away first (one rename succeeds), then creates the lock anew, so two runs
that find the same stale lock do not both take it.

Evaluation, rendering, the viewer and the exports only read a workdir: they neither take nor look at the lock.
On gs:// the lock is not taken (orbax's own commit protocol protects the checkpoints there); see docs/scale.md.
"""
import datetime
import json
import os
import socket
import threading
import time

from nerfpod.errors import UserError

NAME = "lock.json"
HEARTBEAT_SECONDS = 5.0
LEASE_SECONDS = 30.0


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


class WorkdirLock:
  """The lock of a local workdir (see the module's docstring); a no-op for a gs:// one."""

  def __init__(self, workdir: str):
    self.workdir = str(workdir)
    self.path = os.path.join(self.workdir, NAME)
    self._stop = threading.Event()
    self._thread = None
    self._held = False

  def __enter__(self):
    self.acquire()
    return self

  def __exit__(self, *exc):
    self.release()

  def _holder(self) -> dict | None:
    """The lock file's holder, or None where there is no lock file; an unreadable file (a holder killed while
    writing it) holds {}."""
    try:
      with open(self.path) as f:
        text = f.read()
    except FileNotFoundError:
      return None
    try:
      holder = json.loads(text)
      return holder if isinstance(holder, dict) else {}
    except ValueError:
      return {}

  def _age(self) -> float | None:
    try:
      return time.time() - os.stat(self.path).st_mtime
    except FileNotFoundError:
      return None

  def _create(self) -> bool:
    """Creates the lock file with this process as its holder, if it is absent."""
    me = {"host": socket.gethostname(), "pid": os.getpid(), "process_start": _process_start(os.getpid()),
          "since": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    try:
      fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
      return False
    with os.fdopen(fd, "w") as f:
      f.write(json.dumps(me))
    return True

  def _is_stale(self, holder: dict) -> bool:
    """Whether the holder of the lock is gone (see the module's docstring); may watch its heartbeat for up to
    one lease."""
    if holder.get("host") == socket.gethostname() and isinstance(holder.get("pid"), int):
      return not _alive(holder["pid"], holder.get("process_start"))
    first = self._age()
    if first is None or first > LEASE_SECONDS:
      return True
    deadline = time.monotonic() + LEASE_SECONDS - first
    mtime = os.stat(self.path).st_mtime
    while time.monotonic() < deadline:
      time.sleep(min(1.0, HEARTBEAT_SECONDS / 2))
      try:
        if os.stat(self.path).st_mtime != mtime:
          return False  # it beats
      except FileNotFoundError:
        return True  # released meanwhile
    return True

  def acquire(self) -> None:
    """Takes the lock, or raises a UserError naming the live run that holds it."""
    if "://" in self.workdir:
      return
    for _ in range(10):  # each pass either takes the lock, refuses, or clears a stale one
      if self._create():
        self._held = True
        self._thread = threading.Thread(target=self._beat, name="nerfpod-workdir-lock", daemon=True)
        self._thread.start()
        return
      holder = self._holder()
      if holder is None:
        continue  # released between the two looks
      if not self._is_stale(holder):
        who = (f"process {holder.get('pid', '?')} on host {holder.get('host', '?')} since "
               f"{holder.get('since', '?')}")
        raise UserError(f"workdir {self.workdir} is in use by another training run ({who} holds {self.path}); "
                        f"wait for that run to end or stop it, or pass another --workdir (evaluation, rendering, "
                        f"the viewer and the exports may read it meanwhile).")
      stale = f"{self.path}.stale-{os.getpid()}"
      try:
        os.rename(self.path, stale)  # one of the runs that found it stale moves it away
      except FileNotFoundError:
        continue
      os.remove(stale)
    raise UserError(f"could not take the lock {self.path}: other runs keep taking and releasing it; start one "
                    f"run on workdir {self.workdir} at a time.")

  def _beat(self) -> None:
    while not self._stop.wait(HEARTBEAT_SECONDS):
      try:
        os.utime(self.path)
      except OSError:  # gone (someone removed it) or the disk is unreachable: nothing to do here
        pass

  def release(self) -> None:
    """Stops the heartbeat and removes the lock file, if this process holds it."""
    if not self._held:
      return
    self._held = False
    self._stop.set()
    if self._thread is not None:
      self._thread.join()
    holder = self._holder()
    if holder and holder.get("pid") == os.getpid() and holder.get("host") == socket.gethostname():
      try:
        os.remove(self.path)
      except FileNotFoundError:
        pass
