"""The viewer's start-up time and frame times, and a screenshot of its page, in one command.

    python -m tools.view_benchmark --workdir=DIR [--size=256] [--frames=10] [--screenshot=docs/viewer.png]

Measures, on this machine's JAX devices, with the viewer of nerfpod/view.py:
- start-up: from this process's start (before JAX is imported) to the viewer serving its page (config,
  scene, model, the checkpoint restored read-only), and to its first frame of --size x --size pixels
  rendered (the renderer's compilation included);
- a frame's render time at --size x --size (and at the viewer's coarse preview size, 64), the median of
  --frames renders from the first held-out camera, after the first;
- with --screenshot: a headless chromium (Debian's, through selenium) opens the page at a 900x640
  window; the time until the page holds its first full-resolution frame is reported and the page is saved
  as a PNG there.
Prints one JSON object.
"""
import time

_STARTED = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402


def _screenshot(viewer, path: str) -> tuple[float, str]:
  """Opens the page in headless chromium, waits for its first full frame, saves the page; returns the time
  from opening the page to that frame, and the frame's size."""
  from selenium import webdriver
  from selenium.webdriver.chrome.service import Service
  options = webdriver.ChromeOptions()
  options.binary_location = shutil.which("chromium") or shutil.which("chromium-browser")
  for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=900,640",
                   "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--force-device-scale-factor=1"):
    options.add_argument(argument)
  driver = webdriver.Chrome(options=options, service=Service(shutil.which("chromedriver")))
  viewer._max_resolution.value = 512  # the page's own default, for the picture
  try:
    opened = time.perf_counter()
    driver.get(viewer.url)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
      browsers = list(viewer.browsers().values())
      if browsers and browsers[0].last is not None and browsers[0].last.full:
        break
      time.sleep(0.02)
    else:
      raise RuntimeError("the page got no full-resolution frame within 300 s")
    to_frame = time.perf_counter() - opened
    size = f"{browsers[0].last.intrinsics.width}x{browsers[0].last.intrinsics.height}"
    time.sleep(2.0)  # the frustums' images and the panel settle
    from selenium.webdriver.common.by import By
    for button in driver.find_elements(By.CSS_SELECTOR, "button[class*='closeButton']"):
      button.click()  # the note that WebGL runs in software (headless chromium has no GPU)
    time.sleep(0.5)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    driver.save_screenshot(path)
    return to_frame, size
  finally:
    driver.quit()


def main():
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--workdir", required=True)
  parser.add_argument("--size", type=int, default=256, help="frame width and height, pixels")
  parser.add_argument("--frames", type=int, default=10, help="frames timed (after the first)")
  parser.add_argument("--screenshot", default="", help="also open the page in headless chromium, save it here")
  args = parser.parse_args()

  import jax
  import numpy as np
  from nerfpod import view
  from nerfpod.nerf import cameras
  viewer = view.Viewer(args.workdir, port=0, max_resolution=max(args.size, 64))
  serving = time.perf_counter() - _STARTED
  try:
    split = viewer.comps.scene.split(viewer.config.eval.split)
    fov = cameras.fov_y(split.intrinsics)
    pose = split.poses[0]

    def timed(size):
      start = time.perf_counter()
      image = viewer.render(pose, cameras.intrinsics_from_fov(fov, size, size), "rgb")
      return time.perf_counter() - start, image
    first, image = timed(args.size)
    first_frame = time.perf_counter() - _STARTED
    frame_s = float(np.median([timed(args.size)[0] for _ in range(args.frames)]))
    timed(viewer.coarse_resolution)
    coarse_s = float(np.median([timed(viewer.coarse_resolution)[0] for _ in range(args.frames)]))
    result = {
        "workdir": args.workdir, "step": viewer.step, "scene": viewer.comps.scene.name,
        "field": viewer.config.model.field, "samples_per_ray": viewer.config.render.num_samples,
        "devices": f"{jax.device_count()} x {jax.devices()[0].platform}",
        "start_to_serving_s": round(serving, 2), "start_to_first_frame_s": round(first_frame, 2),
        "first_frame_s (compile included)": round(first, 2),
        f"frame_{args.size}x{args.size}_s": round(frame_s, 3), "rays_per_s": round(args.size ** 2 / frame_s),
        f"coarse_frame_{viewer.coarse_resolution}x{viewer.coarse_resolution}_s": round(coarse_s, 3),
        "load_average": os.getloadavg()[0],
    }
    assert image.std() > 0, "the frame is blank"
    if args.screenshot:
      seconds, size = _screenshot(viewer, args.screenshot)
      result[f"page_open_to_first_full_frame_{size}_s"] = round(seconds, 2)
      result["screenshot"] = args.screenshot
    print(json.dumps(result, indent=1))
  finally:
    viewer.close()


if __name__ == "__main__":
  main()
