"""Inspect a scene before training on it: what was loaded, how long it took, what it holds in memory, and
how fast the data pipeline makes rays from it.

  python -m tools.scene_report --config=configs/default.py --config.data.kind=auto \
      --config.data.path=../shared/data/nerfstudio_fox --config.data.downscale=4

Prints one JSON object: the format (data.kind=auto says what it found), load time, per split the frames,
their sizes, whether any camera has lens distortion, the bytes its uint8 pixels take (and what float32 would
take), the space, the ray bounds, the capture -> scene similarity, the per-frame bounds' range, and the rays/s
of the training pipeline (one host making `--batch_size`-ray batches, rays through distorted pixels
included), and the process's peak memory. `--out FILE` also writes it there.
"""
import json
import resource
import time

from absl import app, flags
from ml_collections import config_flags


def report(config, batch_size: int = 4096, batches: int = 20) -> dict:
  import numpy as np
  from nerfpod import data, scenes
  start = time.perf_counter()
  scene = scenes.load(config.data)
  load_s = time.perf_counter() - start
  splits = {}
  for name, split in scene.splits.items():
    cams = split.cameras
    splits[name] = {
        "frames": len(split), "pixels": split.num_pixels,
        "sizes": sorted({f"{w}x{h}" for w, h in zip(cams.width.tolist(), cams.height.tolist())}),
        "focal_px": [float(cams.fx.min()), float(cams.fx.max())], "distorted": cams.is_distorted,
        "image_mib": split.pixels.nbytes / 2**20, "as_float32_mib": split.pixels.size * 4 / 2**20,
        "bounds": None if split.bounds is None else [float(split.bounds.min()), float(split.bounds.max())]}
  train = scene.split("train")
  batch = data.LocalRayBatch(train, 0, batch_size, slice(0, batch_size), config.data.pixel_center)
  batch.map(0)
  start = time.perf_counter()
  for step in range(1, batches + 1):
    batch.map(step)
  rays_per_s = batch_size * batches / (time.perf_counter() - start)
  return {"name": scene.name, "kind": scene.kind, "space": scene.space, "near": scene.near, "far": scene.far,
          "load_s": load_s, "splits": splits, "capture_to_scene": np.round(scene.transform, 6).tolist(),
          "pipeline_rays_per_s": rays_per_s, "batch_size": batch_size,
          "host_peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def run() -> None:
  """The command line. Its flags are defined here, not on import, so that this module and the other tools
  (which define --config and --out too) can be imported into one process, e.g. by the tests."""
  config = config_flags.DEFINE_config_file("config", None, "Config file whose data.* names the scene.",
                                           lock_config=True)
  batch_size = flags.DEFINE_integer("batch_size", 4096, "Rays per batch for the pipeline's throughput.")
  batches = flags.DEFINE_integer("batches", 20, "Timed batches.")
  out = flags.DEFINE_string("out", None, "Also write the JSON report to this file.")

  def main(argv):
    del argv
    text = json.dumps(report(config.value, batch_size.value, batches.value), indent=1)
    print(text)
    if out.value:
      with open(out.value, "w") as f:
        f.write(text + "\n")

  app.run(main)


if __name__ == "__main__":
  run()
