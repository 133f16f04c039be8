"""What a run does, from a config and a workdir to a trained, evaluated and rendered scene.

    modes        train_and_evaluate (train, then evaluate, then render the orbit), evaluate_workdir,
                 render_workdir
    trained      the one door to a trained workdir: its config, scene and newest checkpoint that reads back
                 whole, read-only (evaluation, rendering, the viewer and the exports start from it)
    components   the one set-up value, Components (the scene optional: the pod tool's have none): model,
                 optimiser, mesh, ray bounds, shapes, batches and renderer, resolved once from the config
    train_state  TrainState, the optimiser and its learning-rate schedule, the initial state, the seeds' streams
    train        the loop: resume, steps, checkpoints, preemption, previews, one log line
    step         the train step: jax.shard_map over the mesh, gradient means, skip of non-finite updates
    evaluate     held-out views -> eval/metrics.json (PSNR, SSIM, LPIPS)
    protocols    what a held-out view is rendered with where training learned per-frame parameters: the
                 aligned cameras (pose refinement), NeRF-W's half-image code fit (appearance codes)
    orbit        the camera path's frames, split over hosts and devices, into the render archive and videos
    preemption   the step all processes agree to stop at after SIGTERM or a first Ctrl-C
    profiling    jax.profiler traces of chosen steps
    compilation  the backend's compiler options and host settings (CPU-only ones stay on the CPU)

Calls flow downward: run uses workdir/, render/, scenes/, nerf/ and the shared modules; nothing below it
imports it (bench, view, export and pod, above it, do).

MODES, here, is the one table of the modes (`nerfpod train|eval|render`, `python -m nerfpod.main --mode=...`):
each one's function in `modes` and the one line its --help and `nerfpod --help` give. It imports nothing, so
that the `nerfpod` command lists the modes without starting JAX.
"""
import dataclasses


@dataclasses.dataclass(frozen=True)
class Mode:
  function: str  # its function in nerfpod.run.modes, (config, workdir) -> ...
  about: str     # the one line of `nerfpod NAME --help` and of `nerfpod --help`


# A way to run on a workdir with a config (docs/architecture.md: how to add a mode).
MODES = {
    "train": Mode("train_and_evaluate",
                  "train (resuming from the workdir), evaluate the held-out views, render the orbit"),
    "eval": Mode("evaluate_workdir", "evaluate the workdir's newest checkpoint -> eval/metrics.json"),
    "render": Mode("render_workdir", "render (or finish) the orbit of the workdir's newest checkpoint, and its videos"),
}
