"""The workdir's files, and nothing lost in them.

    files          config.json and scene.json (the resolved config and the scene a run trained on)
    checkpoints    orbax checkpoints: asynchronous saves, rotation, the newest good one restored, damaged ones set
                   aside, never a damaged or non-finite one over a good one
    watchdog       a bucket that stops answering or fails mid-run: what a training run waits on there, bounded,
                   and its one sentence
    failures       what a failed read or write was: a full disk, a storage client's failure, why in one line
    quiet          the libraries' reports of nerfpod's own doing kept out of a process's output (log filters,
                   the unraisable hook)
    library_texts  the words of other libraries' reports that nerfpod still reads, in one place, each pinned to
                   the version that words it (tests/test_library_texts.py)
    finite         whether a pytree is all finite (what may be saved)
    lock           the single-writer lock: one training run writes a workdir, local or gs://

Local folders and gs:// buckets alike, through nerfpod.storage and orbax.
"""
