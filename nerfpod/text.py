"""Quantities as a person reads them, written one way by every command: a duration and a size in bytes.
Imports nothing of nerfpod's and neither JAX nor flax, so that every module may use it."""


def duration(seconds: float) -> str:
  """'12.3 ms', '3.2 s' (below 10 s), '45 s', '2 min 5 s', '1 h 3 min'."""
  seconds = max(0.0, float(seconds))
  if seconds < 0.9995:  # (what would round to 1000 ms is '1.0 s')
    return f"{seconds * 1e3:.3g} ms"
  if seconds < 59.5:  # (what would round to 60 s is '1 min 0 s')
    return f"{seconds:.1f} s" if seconds < 9.95 else f"{seconds:.0f} s"
  minutes, s = divmod(int(round(seconds)), 60)
  if minutes < 60:
    return f"{minutes} min {s} s"
  return f"{minutes // 60} h {minutes % 60} min"


def byte_size(n: float) -> str:
  """'1.5 GiB', '12.3 MiB', '20.0 KiB' (one decimal, thousands separated: '1,024.0 GiB'), '512 B'."""
  for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
    if n >= scale:
      return f"{n / scale:,.1f} {unit}"
  return f"{int(n):,} B"
