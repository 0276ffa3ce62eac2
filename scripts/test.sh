#!/usr/bin/env bash
# The whole test suite, set-up included: Python package with test extras, the Khronos glTF
# validator (npm, from the committed lockfile), then pytest. Used by .ci/run and README.
set -euo pipefail
cd "$(dirname "$0")/.."

python -m pip install --quiet --disable-pip-version-check -e ".[test,dev]"
if [ ! -d tools/gltf-validator/node_modules ]; then
  npm ci --silent --no-audit --no-fund --prefix tools/gltf-validator
fi
ruff check .
python -m pytest "$@"
