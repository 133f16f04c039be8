"""A bucket that stops answering (or fails) mid-run, for a training run's checkpoints.

For a workdir in a bucket, what a training run waits on there (the opening of the checkpoints, the previous
save when the next one is due, the last one at the end or at a preemption) is waited on for at most
checkpoint.storage_timeout_s (bounded, through nerfpod.storage.within); past it, or on a storage client's failure
(failures.storage_failure), the run stops with one storage.Stopped sentence naming the bucket, what failed and
the newest committed checkpoint, the save under way left behind uncommitted. The arrays' tensorstore requests
are retried TENSORSTORE_TRIES times at most (BoundedRequests).
"""
import orbax.checkpoint as ocp

from nerfpod import storage
from nerfpod.errors import UserError
from nerfpod.workdir import failures

# tensorstore's gcs driver retries a request up to 32 times, waiting up to 32 s between tries: nerfpod's
# arrays' requests are tried TENSORSTORE_TRIES times, at most checkpoint.storage_timeout_s apart (each try ends
# after that long without a byte: storage.bound_clients), as gcsfs tries its own.
TENSORSTORE_TRIES = 6


class BoundedRequests(ocp.type_handlers.ArrayHandler):
  """orbax's ArrayHandler whose arrays' tensorstore requests are retried TENSORSTORE_TRIES times at most
  (tensorstore's `gcs_request_retries` context resource, in a context whose parent is orbax's own, so that
  its other resources stay shared)."""

  def __init__(self, storage_timeout_s: float, **kwargs):
    super().__init__(**kwargs)
    self._retries = {"gcs_request_retries": {"max_retries": TENSORSTORE_TRIES - 1, "initial_delay": "1s",
                                             "max_delay": f"{min(32.0, storage_timeout_s):g}s"}}

  def _bounded(self, infos):
    import tensorstore as ts
    children = {}
    for info in infos:
      parent = info.ts_context
      if parent is not None:
        if id(parent) not in children:
          children[id(parent)] = ts.Context(ts.Context.Spec(self._retries), parent=parent)
        info.ts_context = children[id(parent)]
    return infos

  async def serialize(self, values, infos, args=None):
    return await super().serialize(values, self._bounded(infos), args)

  async def deserialize(self, infos, args=None):
    return await super().deserialize(self._bounded(infos), args)


def bounded(workdir: str, timeout_s: float | None, doing: str, work, committed: int | None):
  """work() (a part of `doing`, in words: "saving the checkpoint of step 20"). For a workdir in a bucket
  (`timeout_s` not None), waited on for at most timeout_s (storage.within); a bucket that gives no answer in
  that time, or fails (failures.storage_failure: an error of another kind is raised as it is), is one
  storage.Stopped sentence naming it, what failed and the newest committed checkpoint (`committed`)."""
  if timeout_s is None:
    return work()
  bucket = storage.bucket_of(workdir)
  try:
    return storage.within(workdir, timeout_s, work)
  except storage.NoAnswer:
    what = f"stopped answering while {doing} (no answer in {timeout_s:g} s)"
  except UserError:
    raise
  except Exception as e:  # noqa: BLE001 (whatever orbax, tensorstore or gcsfs raise when storage fails)
    if not failures.storage_failure(e):
      raise
    what = f"failed while {doing} ({failures.reason(e)})"
    storage.mark_stopped(workdir)  # (the run stops on it: its other calls there give up at once)
  newest = (f"the newest committed checkpoint is step {committed}: rerun the same command once storage "
            f"is back (it resumes from there)" if committed is not None else
            "no checkpoint had been committed yet: rerun the same command once storage is back")
  raise storage.Stopped(f"the bucket {bucket} {what}; {newest}.")


def failed_reading(workdir: str, step: int, reason: str) -> storage.Stopped:
  """The sentence for a bucket that failed while a training run read the checkpoint of `step` (marked
  stopped): the step is left as it is, never set aside as damaged."""
  storage.mark_stopped(workdir)
  return storage.Stopped(f"the bucket {storage.bucket_of(workdir)} failed while reading the checkpoint of step "
                         f"{step} ({reason}); it is left as it is: rerun the same command once storage is back.")
