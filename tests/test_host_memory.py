"""compile.cpu_reuse_host_memory: glibc's malloc keeps freed memory instead of mapping it afresh per step."""
import os
import platform
import subprocess
import sys

import pytest

from conftest import REPO

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")

# Allocates and frees a 64 MiB block and prints, in MiB, what glibc's mallinfo2 says the process holds in
# mmapped blocks and in free heap memory before, while the block is held and after it is freed.
_PROBE = """
import ctypes, sys
sys.path.insert(0, {repo!r})
from nerfpod.run import compilation
applied = compilation.reuse_host_memory() if {apply} else False
libc = ctypes.CDLL(None)
class Info(ctypes.Structure):
  _fields_ = [(n, ctypes.c_size_t) for n in
              "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]
libc.mallinfo2.restype = Info
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
seen = [libc.mallinfo2()]
block = libc.malloc(64 << 20)
seen.append(libc.mallinfo2())
libc.free(block)
seen.append(libc.mallinfo2())
print(applied, *[i.hblkhd >> 20 for i in seen], *[i.fordblks >> 20 for i in seen])
"""


def _probe(apply: bool, **env) -> tuple[bool, list[int], list[int]]:
  environ = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")} | env
  out = subprocess.run([sys.executable, "-c", _PROBE.format(repo=str(REPO), apply=apply)], env=environ,
                       capture_output=True, text=True, timeout=120, check=True).stdout.split()
  return out[0] == "True", [int(x) for x in out[1:4]], [int(x) for x in out[4:7]]


def test_large_blocks_come_from_the_kept_heap_once_applied():
  # glibc's default: a 64 MiB block is a fresh mapping, handed back to the kernel when freed.
  applied, mapped, free = _probe(False)
  assert not applied and mapped[1] - mapped[0] == 64 and mapped[2] == mapped[0] and free[2] < 64
  # Applied: no mapping; the freed block stays in the heap for the next allocation.
  applied, mapped, free = _probe(True)
  assert applied and mapped[1] == mapped[0] == mapped[2] and free[2] >= 64


def test_a_users_own_malloc_settings_win():
  assert _probe(True, MALLOC_ARENA_MAX="2")[0] is False


def test_the_default_config_asks_for_it():
  from conftest import smoke_config
  assert smoke_config().compile.cpu_reuse_host_memory is True
