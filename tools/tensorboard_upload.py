"""How many bytes a run's TensorBoard logging uploads to a gs:// workdir, against the Cloud Storage emulator of
the tests (tests/gcs.py, the test extra), in one command:

    python -m tools.tensorboard_upload [--steps=10000] [--at=1000,2000,5000,10000] [--images]

Makes the calls training makes (nerfpod.run.train through nerfpod.monitor.Monitor), without training: the
scalars of a log step every train.log_every (100) steps and at the first step, with `--images` the preview
images every train.image_every (500) steps at configs/default.py's image size (100x100), and a flush after
each log step, as tensorboardX's timer (every 10 s in training) does where 100 steps take more than 10 s.
Prints one JSON object: at each step of --at, the bytes the emulator has received so far (the request bodies:
the uploads and their metadata) and the bytes of the workdir's event files then.
"""
import argparse
import json
import os
import pathlib
import sys
import tempfile
import time

LOG_EVERY, IMAGE_EVERY, IMAGE_SIZE, BATCH = 100, 500, 100, 1024
SETTLE_SECONDS = 0.02  # for the writer's thread to take a log step's events from its queue before the flush


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--steps", type=int, default=10_000)
  parser.add_argument("--at", default="1000,2000,5000,10000", help="steps at which to report the volume so far")
  parser.add_argument("--images", action="store_true", help="also the preview images every 500 steps")
  args = parser.parse_args(argv)
  at = sorted(int(s) for s in args.at.split(","))

  sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))
  import gcs
  with tempfile.TemporaryDirectory() as tmp, gcs.Emulator(os.path.join(tmp, "emulator.log")) as emulator:
    os.environ.update(emulator.env)
    import jax
    import numpy as np

    from nerfpod import monitor
    jax.config.update("jax_platforms", "cpu")
    workdir = f"gs://{emulator.bucket}/runs/volume"
    fs = emulator.filesystem()

    def event_bytes() -> int:
      return sum(fs.size(f"{emulator.bucket}/runs/volume/{name}") for name in emulator.files("runs/volume")
                 if name.startswith("events.out.tfevents."))

    start = emulator.received_bytes()
    watch = monitor.Monitor(workdir, args.steps, BATCH)
    rng = np.random.default_rng(0)
    rows, started = [], time.perf_counter()
    for done in range(1, args.steps + 1):
      if done % LOG_EVERY == 0 or done == 1:
        metrics = {"loss": 1.0 / done, "mse": 1.0 / done, "psnr": 10 + done / 1000, "psnr_coarse": 9 + done / 1000,
                   "grad_norm": 0.1, "skipped": 0}
        watch.scalars(done, metrics, 5e-4)
      if args.images and done % IMAGE_EVERY == 0:
        watch.images(done, {"preview/rgb": rng.random((IMAGE_SIZE, IMAGE_SIZE, 3)),
                            "preview/depth": rng.random((IMAGE_SIZE, IMAGE_SIZE, 1))})
      if done % LOG_EVERY == 0 or done == 1:
        time.sleep(SETTLE_SECONDS)
        watch.writer.flush()
      if done in at:
        rows.append({"step": done, "uploaded_bytes": emulator.received_bytes() - start, "event_bytes": event_bytes(),
                     "objects": len(emulator.files("runs/volume"))})
    watch.close()
    end = {"uploaded_bytes": emulator.received_bytes() - start, "event_bytes": event_bytes(),
           "objects": len(emulator.files("runs/volume"))}
    print(json.dumps({"steps": args.steps, "images": args.images, "at": rows, "closed": end,
                      "seconds": round(time.perf_counter() - started, 1)}), flush=True)
  sys.stdout.flush()
  os._exit(0)  # tensorboardX's own gs:// writer uploads again when it is collected, to an emulator now gone


if __name__ == "__main__":
  main()
