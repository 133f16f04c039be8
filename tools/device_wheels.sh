#!/usr/bin/env bash
# Fills .whl/ with the wheels an accelerator machine without a network lacks, and .devdata/ with the lego scene
# and the cup, for tools/device_check.sh (both folders are git-ignored; carry them with the call). The machine this was
# written for (an NVIDIA image with CUDA, Python 3.12, JAX 0.11.2, flax, optax, orbax-checkpoint, tensorstore)
# lacks grain, ml-collections and tensorboardX; flax, optax and orbax-checkpoint travel too, at this project's
# pinned versions, so that the check runs the versions the tests passed with. imageio-ffmpeg's wheel (68 MB)
# is over the call's size limit: without it the orbit's mp4s are left out and the check says so.
#
#   bash tools/device_wheels.sh [PYTHON_VERSION=3.12] [DATA=../shared/data]
set -euo pipefail
cd "$(dirname "$0")/.."
python_version="${1:-3.12}"
data="${2:-../shared/data}"
pin() {  # NAME==VERSION from constraints.txt for the target Python (of two marked lines, the one that applies)
  python3 - "$python_version" "$1" <<'PY'
import sys
from packaging.requirements import Requirement
version, name = sys.argv[1], sys.argv[2].lower().replace("_", "-")
for line in open("constraints.txt"):
  line = line.strip()
  if line and not line.startswith("#"):
    req = Requirement(line)
    if req.name.lower().replace("_", "-") == name and (req.marker is None or req.marker.evaluate(
        {"python_version": version, "python_full_version": f"{version}.0"})):
      print(f"{req.name}{req.specifier}")
PY
}
rm -rf .whl && mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$python_version" --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 -d .whl \
  "$(pin grain)" "$(pin array_record)" "$(pin ml_collections)" "$(pin tensorboardX)" "$(pin portpicker)" \
  "$(pin flax)" "$(pin optax)" "$(pin orbax-checkpoint)"
if [ -d "$data/lego_400" ]; then
  rm -rf .devdata && mkdir -p .devdata && cp -r "$data/lego_400" .devdata/
else
  echo "device_wheels: $data/lego_400 not found: the check's lego stages will be skipped" >&2
fi
# The cup for the check's capture stage, as a transforms.json of its images at 200 x 150 (2.5 MB; no pycolmap
# needed there): one step of the smoke config loads it here, `nerfpod export cameras` writes it out.
if [ -d "$data/colmap_cup" ]; then
  work=$(mktemp -d)
  python3 -m nerfpod.main --config="configs/capture.py:path=$data/colmap_cup,smoke" --workdir="$work/run" \
    --config.train.num_steps=1 --config.orbit.render_after_training=False --config.eval.lpips_net=none >/dev/null
  rm -rf .devdata/cup && python3 -m nerfpod.export cameras --workdir="$work/run" --out=.devdata/cup/transforms.json
  rm -rf "$work"
else
  echo "device_wheels: $data/colmap_cup not found: the check's capture stage will be skipped" >&2
fi
du -sh .whl .devdata 2>/dev/null || true
