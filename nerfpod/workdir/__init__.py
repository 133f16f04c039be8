"""The workdir's files, and nothing lost in them.

    files        config.json and scene.json (the resolved config and the scene a run trained on)
    checkpoints  orbax checkpoints: asynchronous saves, the newest good one restored, damaged ones set aside,
                 never a damaged or non-finite one over a good one; the quieting of orbax's abandoned reads
    finite       whether a pytree is all finite (what may be saved)
    lock         the single-writer lock: one training run writes a workdir, local or gs://

Local folders and gs:// buckets alike, through nerfpod.storage and orbax.
"""
