"""Which devices each compiled program spans: a hook on JAX's one compile path, for tests.

On a pod every program of a run must span the whole slice: the TPU compiler refuses a program on some of
a slice's chips (v5e pods of 32 chips and more: "device assignment should include all slice devices"),
while a program on one chip (an eager operation, a key, a scalar) compiles anywhere. `record(path)`
appends one JSON line per program this process compiles, `{"name", "devices"}` (the device ids of its
device assignment), to `path`; `subset_programs(records, all_ids)` lists those on more than one device but
not on all of them. Every jit, shard_map, AOT `.lower().compile()` and orbax helper compiles through
jax._src.compiler.compile_or_get_cached, which this wraps (also where the persistent compilation cache
serves the program, so a cached program is recorded too).

tests/procs.py installs it in a test process when NERFPOD_TEST_COMPILES names a folder
(compiles_process_<index>.jsonl there).
"""
import contextlib
import json
import pathlib


def _wrap(original, path: pathlib.Path):
  def compile_or_get_cached(backend, computation, devices, *args, **kwargs):
    try:
      from jax._src.lib.mlir import ir
      name = ir.StringAttr(computation.operation.attributes["sym_name"]).value
    except Exception:  # noqa: BLE001 (a name is only for the message)
      name = "?"
    entry = {"name": name, "devices": sorted(int(d.id) for d in devices.flat)}
    with open(path, "a") as f:
      f.write(json.dumps(entry) + "\n")
    return original(backend, computation, devices, *args, **kwargs)
  compile_or_get_cached.nerfpod_original = original
  return compile_or_get_cached


def install(path) -> None:
  """Records every later compilation of this process into `path` (JSON lines)."""
  from jax._src import compiler
  compiler.compile_or_get_cached = _wrap(compiler.compile_or_get_cached, pathlib.Path(path))


@contextlib.contextmanager
def recording(path):
  """install(path) for the duration of a with-block."""
  from jax._src import compiler
  original = compiler.compile_or_get_cached
  compiler.compile_or_get_cached = _wrap(original, pathlib.Path(path))
  try:
    yield
  finally:
    compiler.compile_or_get_cached = original


def read(*paths) -> list[dict]:
  out = []
  for path in paths:
    path = pathlib.Path(path)
    if path.exists():
      out += [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
  return out


def subset_programs(records: list[dict], all_ids) -> list[dict]:
  """The programs on several devices but not on every one of `all_ids`: what a TPU pod refuses."""
  everything = sorted(all_ids)
  return [r for r in records if len(r["devices"]) > 1 and r["devices"] != everything]
