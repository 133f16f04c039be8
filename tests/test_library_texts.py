"""Each library text nerfpod still matches (nerfpod.workdir.library_texts) is made here by the library that
words it, installed as it is, and the pattern is checked to still match it: a version that words it otherwise
fails here, rather than letting its report through unseen. And what is told by a category and a module instead
(JAX's warning about fork, around ffmpeg's start: nerfpod.render.video) is seen to be told so."""
import asyncio
import errno
import gc
import logging
import os
import subprocess
import traceback
import warnings

import jax
import pytest

from nerfpod.workdir import failures, library_texts, quiet


def test_orbax_names_its_temporary_folder_and_its_files_as_matched(tmp_path):
  from etils import epath
  import orbax.checkpoint as ocp
  from orbax.checkpoint._src.path import atomicity
  temporary = atomicity.AtomicRenameTemporaryPath.from_final(epath.Path(tmp_path / "20")).get()
  assert library_texts.is_cut_off_save(temporary.name), temporary
  assert not library_texts.is_cut_off_save("20") and not library_texts.is_cut_off_save(".rotated")
  assert library_texts.in_orbax(ocp.__file__) and library_texts.in_orbax(atomicity.__file__)
  assert not library_texts.in_orbax(__file__)


def test_tensorstore_errors_begin_with_a_status_code_and_carry_the_os_error_number(tmp_path):
  """A write under a regular file (ENOTDIR) and an open of nothing (NOT_FOUND): the status code begins the
  message, and the OS's error is its number and the OS's own words (so a full disk, ENOSPC, reads as
  failures.disk_full)."""
  import tensorstore as ts
  (tmp_path / "file").write_text("not a folder")
  with pytest.raises(ValueError) as written:
    ts.KvStore.open({"driver": "file", "path": str(tmp_path / "file" / "under") + "/"}).result().write(
        "key", b"value").result()
  assert library_texts.status_code(written.value) == "FAILED_PRECONDITION", written.value
  assert library_texts.os_error_number(str(written.value)) == errno.ENOTDIR, written.value
  assert os.strerror(errno.ENOTDIR) in str(written.value)
  assert not failures.disk_full(written.value)
  full = ValueError(str(written.value).replace(f"'{errno.ENOTDIR}'", f"'{errno.ENOSPC}'").replace(
      os.strerror(errno.ENOTDIR), os.strerror(errno.ENOSPC)))
  assert failures.disk_full(full) and failures.disk_full(OSError(errno.ENOSPC, "full"))
  with pytest.raises(ValueError) as opened:
    ts.open({"driver": "zarr", "kvstore": {"driver": "file", "path": str(tmp_path / "none") + "/"}},
            open=True).result()
  assert library_texts.status_code(opened.value) == "NOT_FOUND", opened.value
  assert library_texts.status_code(ValueError("could not convert 'x'")) is None


def _in_file(filename: str, source: str) -> dict:
  namespace = {}
  exec(compile(source, filename, "exec"), namespace)  # pylint: disable=exec-used
  return namespace


def test_asyncio_words_its_reports_of_abandoned_tasks_as_matched(caplog, monkeypatch):
  """A failed task nobody awaited and one still pending when collected, each of a coroutine in orbax's files
  and in another: asyncio words and names them so that only the other's are reported once quieted."""
  orbax_file = f"{os.sep}site-packages{os.sep}orbax{os.sep}checkpoint{os.sep}serialization.py"
  sources = {where: _in_file(where, "async def fails():\n  raise ValueError('read failed')\n"
                                    "async def waits():\n  import asyncio\n  await asyncio.sleep(3600)\n")
             for where in (orbax_file, __file__)}
  asyncio_log = logging.getLogger("asyncio")
  monkeypatch.setattr(asyncio_log, "filters", [])  # the library as it is, before nerfpod configures it

  def reports() -> list[logging.LogRecord]:
    caplog.clear()
    # The tasks' cycles are collected with what was made after gc.freeze: the session's older objects (JAX's
    # caches, every module imported; seconds of a full collection, four times) are not walked.
    gc.freeze()
    try:
      with caplog.at_level(logging.ERROR, logger="asyncio"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (a coroutine never awaited)
        for namespace in sources.values():
          loop = asyncio.new_event_loop()
          failed = loop.create_task(namespace["fails"]())
          loop.run_until_complete(asyncio.sleep(0))
          assert failed.done()
          pending = loop.create_task(namespace["waits"]())
          loop.close()
          del failed, pending
          gc.collect()
    finally:
      gc.unfreeze()
    return [r for r in caplog.records if r.name == "asyncio"]

  said = [r.getMessage() for r in reports()]
  assert sum(library_texts.NEVER_RETRIEVED in m for m in said) == 2, said
  assert sum(m.startswith(library_texts.DESTROYED_PENDING) for m in said) == 2, said
  assert sum(library_texts.in_orbax(m) for m in said) == 2, said
  quieting = quiet._AbandonedReadTasks()
  asyncio_log.addFilter(quieting)
  left = [r.getMessage() for r in reports()]
  assert len(left) == 2 and all(os.path.basename(__file__) in m for m in left), left


def test_a_call_into_a_closed_loop_is_worded_as_matched():
  loop = asyncio.new_event_loop()
  loop.close()
  with pytest.raises(RuntimeError) as called:
    loop.call_soon_threadsafe(lambda: None)
  assert str(called.value) == library_texts.CLOSED_LOOP
  assert "call_soon_threadsafe" in [frame.name for frame in traceback.extract_tb(called.tb)]


def test_jaxs_warning_about_fork_is_told_by_its_category_and_module(tmp_path):
  """JAX warns at a fork once its backend is up (a RuntimeWarning, attributed to subprocess, which forks for
  ffmpeg with a function to run before exec, as imageio-ffmpeg's does); nerfpod.render.video's quieting drops
  it by those two, lets others through, and an mp4 is written with no warning."""
  import numpy as np

  from nerfpod.render import video
  jax.devices()  # (JAX's fork hook is installed with its backends)

  def fork():
    subprocess.run(["true"], check=True, preexec_fn=os.setpgrp)  # pylint: disable=subprocess-popen-preexec-fn
  with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    fork()
  assert [(w.category, os.path.basename(w.filename)) for w in seen] == [(RuntimeWarning, "subprocess.py")], [
      str(w.message) for w in seen]
  with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    with video.quiet_fork_warning():
      fork()
      warnings.warn("another warning", RuntimeWarning)
  assert [str(w.message) for w in seen] == ["another warning"]
  if not video.mp4_available():
    pytest.skip("no ffmpeg for imageio")
  with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    writer = video.VideoWriter(str(tmp_path / "a.mp4"), fps=2)
    writer.append(np.zeros((16, 16, 3), np.uint8))
    writer.close()
  assert [str(w.message) for w in seen] == []
