"""Time for the workdir lock's tests (tests/test_workdir_lock*.py): a clock for the lock module that lets a lease
pass at once where nothing beats, and a wait for what a heartbeat brings about, so that a busy 2-core machine
cannot fail them by being slow."""
import threading
import time

from nerfpod.workdir import lock as workdir_lock


class WatchClock:
  """The lock module's clock while it watches a lock that nobody beats: its `sleep` moves this clock's
  `monotonic` on by the time asked (and yields the thread for a moment) instead of waiting, so a lease passes
  in milliseconds; `offset` is the time slept so far. Only where nothing beats meanwhile: a holder's beats run
  on the real clock. `time.time` and the rest are the real module's."""

  def __init__(self):
    self.offset = 0.0
    self._lock = threading.Lock()

  def monotonic(self) -> float:
    return time.monotonic() + self.offset

  def sleep(self, seconds: float) -> None:
    with self._lock:
      self.offset += seconds
    time.sleep(0.0005)

  def __getattr__(self, name):
    return getattr(time, name)


def watch_clock(monkeypatch) -> WatchClock:
  """A WatchClock for the lock module, and its beats every second as a run's are every few (a watch looks at
  the lock every half beat: a few looks a lease rather than tens)."""
  clock = WatchClock()
  monkeypatch.setattr(workdir_lock, "time", clock)
  monkeypatch.setattr(workdir_lock, "HEARTBEAT_SECONDS", 1.0)
  return clock


def until(condition, within_s: float = 10.0) -> None:
  """Waits until condition() holds (polling), for at most within_s: what a beat every 0.1 s brings about is
  awaited, not assumed to come within a fixed time on a busy machine."""
  deadline = time.monotonic() + within_s
  while not condition() and time.monotonic() < deadline:
    time.sleep(0.01)
