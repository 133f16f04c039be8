"""nerfpod.text: the one way every command writes a duration and a size in bytes (the console line's ETA,
prepare's stages, the mesh export's estimate, the pod report), without JAX."""
import subprocess
import sys

import pytest

from conftest import REPO
from nerfpod import text


@pytest.mark.parametrize("seconds, want", [
    (0.0, "0 ms"), (0.0123, "12.3 ms"), (0.9994, "999 ms"), (0.9996, "1.0 s"), (3.21, "3.2 s"), (9.96, "10 s"),
    (45.4, "45 s"), (59.6, "1 min 0 s"), (125, "2 min 5 s"), (3599.6, "1 h 0 min"), (3725, "1 h 2 min"),
    (-1.0, "0 ms")])
def test_a_duration_reads_in_the_unit_that_fits_it(seconds, want):
  assert text.duration(seconds) == want


@pytest.mark.parametrize("n, want", [
    (0, "0 B"), (512, "512 B"), (20 * 2**10, "20.0 KiB"), (16 * 2**20, "16.0 MiB"), (1.5 * 2**30, "1.5 GiB"),
    (1024 * 2**30, "1,024.0 GiB")])
def test_a_size_reads_in_binary_units_with_one_decimal(n, want):
  assert text.byte_size(n) == want


def test_the_formats_import_neither_jax_nor_flax():
  code = ("import sys; from nerfpod import text; "
          "assert not {'jax', 'flax'} & set(sys.modules), sorted(sys.modules)")
  subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=60)
