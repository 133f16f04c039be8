#!/usr/bin/env bash
# The device check: one call on a machine with an accelerator (and JAX for it already installed) measures what
# nerfpod does there; tools/device_check.py says what and writes the report (JSON and markdown) to $OUT or --out.
#
#   bash tools/device_wheels.sh          # here, with a network: fills .whl/ and .devdata/
#   bash tools/device_check.sh           # there, without one: installs .whl/ into /tmp, then measures
#   bash tools/device_check.sh --tiny    # anywhere: the same stages on the CPU in about a minute (the tests)
#
# The wheels go to /tmp/nerfpod-site ahead of the machine's own packages; nothing is installed system-wide.
set -euo pipefail
cd "$(dirname "$0")/.."
tiny=0
for arg in "$@"; do [ "$arg" = "--tiny" ] && tiny=1; done
if [ "$tiny" = 0 ] && compgen -G ".whl/*.whl" >/dev/null; then
  "${PYTHON:-python3}" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/nerfpod-site \
    .whl/*.whl
  export PYTHONPATH="/tmp/nerfpod-site${PYTHONPATH:+:$PYTHONPATH}"
fi
exec "${PYTHON:-python3}" tools/device_check.py "$@"
