"""What nerfpod prepare prints while a stage runs: a progress line with the count, the time so far and an ETA
(durations as nerfpod.text writes them)."""
import time

from nerfpod.text import duration


def eta(done: float, total: float, elapsed: float) -> str:
  """'about 1 min 20 s left' from the rate so far ('' before anything is done)."""
  if done <= 0 or total <= done:
    return ""
  return f", about {duration(elapsed * (total - done) / done)} left"


class Progress:
  """A line with the count, the time so far and an ETA every `every` seconds, and one at the end."""

  def __init__(self, stage: str, total: int, unit: str, every: float = 5.0, already: int = 0):
    self.stage, self.total, self.unit, self.every, self.already = stage, total, unit, every, already
    self.start = time.monotonic()
    self.last, self.last_done = self.start, None  # the first line after `every` seconds: a rate to go by

  def update(self, done: int, extra: str = "", force: bool = False):
    now = time.monotonic()
    if done == self.last_done and not force:
      return
    if force or done >= self.total or now - self.last >= self.every:
      self.last, self.last_done = now, done
      elapsed = now - self.start
      left = eta(done - self.already, self.total - self.already, elapsed)  # at this run's rate
      print(f"  {self.stage}: {done}/{self.total} {self.unit}{extra}, {duration(elapsed)}{left}", flush=True)
