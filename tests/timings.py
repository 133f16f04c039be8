"""Where the test suite's time goes: per test, its seconds split into JAX's tracing, lowering and compiling
(XLA's, the persistent cache's reads included) and the rest (running, processes it starts, Python), with the
persistent compilation cache's requests and hits. Off unless NERFPOD_TEST_TIMINGS names a file prefix:

    NERFPOD_TEST_TIMINGS=/tmp/t python -m pytest -q -n 2 -m "not slow" tests
    python tests/timings.py /tmp/t.*.jsonl          # the table: files, then the costliest tests

Each process (xdist worker, or the only one) appends a line per test to PREFIX.<worker>.jsonl. A session
fixture's building counts in the first test that asks for it; processes a test starts count as its rest.
"""
import collections
import json
import os
import sys
import time

EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile"}
COUNTS = {"/jax/compilation_cache/compile_requests_use_cache": "cache_requests",
          "/jax/compilation_cache/cache_hits": "cache_hits",
          "/jax/compilation_cache/cache_misses": "cache_misses"}


class Recorder:
  """A pytest plugin: the JAX monitoring events of each test, one JSON line per test."""

  def __init__(self, prefix: str):
    self.path = f"{prefix}.{os.environ.get('PYTEST_XDIST_WORKER', 'main')}.jsonl"
    self.current = collections.Counter()
    self.started = {}  # nodeid -> perf_counter at its start (where it runs: not xdist's controller)
    import jax
    jax.monitoring.register_event_duration_secs_listener(self._duration)
    jax.monitoring.register_event_listener(self._event)

  def _duration(self, event, duration, **_):
    if event in EVENTS:
      self.current[EVENTS[event]] += duration

  def _event(self, event, **_):
    if event in COUNTS:
      self.current[COUNTS[event]] += 1

  def pytest_runtest_protocol(self, item, nextitem):  # noqa: ARG002  (pytest's hook signature)
    self.current = collections.Counter()
    self.started[item.nodeid] = time.perf_counter()

  def pytest_runtest_logfinish(self, nodeid, location):  # noqa: ARG002
    if nodeid not in self.started:  # xdist's controller hears of every test a worker finishes
      return
    row = {"test": nodeid, "total": time.perf_counter() - self.started.pop(nodeid), **self.current}
    with open(self.path, "a") as f:
      f.write(json.dumps(row) + "\n")


def summarize(paths, top: int = 25) -> str:
  """The table of the lines in `paths`: per file, then the `top` costliest tests, in seconds."""
  rows = [json.loads(line) for path in paths for line in open(path)]
  keys = ("total", "trace", "lower", "compile")
  def line(name, r):
    rest = r["total"] - r["trace"] - r["lower"] - r["compile"]
    hits = f"{r['cache_hits']:.0f}/{r['cache_requests']:.0f}" if r["cache_requests"] else "-"
    return (f"| {name} | {r['total']:.1f} | {r['trace']:.1f} | {r['lower']:.1f} | {r['compile']:.1f} | {rest:.1f} "
            f"| {hits} |")
  head = ("| {} | seconds | tracing | lowering | compiling | the rest | cache hits/requests |\n"
          "| --- | --- | --- | --- | --- | --- | --- |")
  files = collections.defaultdict(collections.Counter)
  for r in rows:
    files[r["test"].split("::")[0]].update({k: r.get(k, 0.0) for k in keys + tuple(COUNTS.values())})
  total = collections.Counter()
  for c in files.values():
    total.update(c)
  out = [head.format("file"), line(f"all {len(rows)} tests", total)]
  out += [line(name, c) for name, c in sorted(files.items(), key=lambda kv: -kv[1]["total"])]
  out += ["", head.format("test")]
  for r in sorted(rows, key=lambda r: -r["total"])[:top]:
    out.append(line(r["test"], collections.Counter({k: r.get(k, 0.0) for k in keys + tuple(COUNTS.values())})))
  return "\n".join(out)


if __name__ == "__main__":
  print(summarize(sys.argv[1:]))
