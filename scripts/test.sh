#!/usr/bin/env bash
# The whole test suite, set-up included: Python package with test extras, the Khronos glTF
# validator, axe-core and the web page's three.js modules (npm, from the committed lockfiles), Debian's
# Chromium for the browser tests (installed with apt when missing and running as root), then
# pytest. Used by .ci/run and README.
set -euo pipefail
cd "$(dirname "$0")/.."

python -m pip install --quiet --disable-pip-version-check -e ".[test,dev]"
if [ ! -d tools/gltf-validator/node_modules ]; then
  npm ci --silent --no-audit --no-fund --prefix tools/gltf-validator
fi
# axe-core for the accessibility browser test (tests/web/test_accessibility.py).
if [ ! -d tools/axe-core/node_modules ]; then
  npm ci --silent --no-audit --no-fund --prefix tools/axe-core
fi
# The page's three.js modules: `npm ci` installs the pinned package and its postinstall
# (web/build.mjs) copies the modules into service/static/vendor/ (git-ignored).
if [ ! -f web/node_modules/.package-lock.json ] || [ web/package-lock.json -nt web/node_modules/.package-lock.json ]; then
  npm ci --silent --no-audit --no-fund --prefix web
else
  node web/build.mjs > /dev/null
fi
# Browser tests (tests/web) drive Debian's Chromium headless; Playwright's own browser
# download is never used. Without root, install it yourself: apt-get install -y chromium.
if ! command -v chromium > /dev/null && [ "$(id -u)" = 0 ]; then
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium
fi
ruff check .
# The slowest tests are listed at the end: the suite plus the Docker smoke test should stay
# under 20 minutes on a 2-core machine. Two pytest-xdist workers (one per core, at most two),
# each taking whole test files (module fixtures such as a uvicorn start once per file): 16.9
# instead of 27.7 minutes on a 2-core machine (load ~1 on its own: the suite waits on servers,
# browsers and subprocesses). `bash scripts/test.sh -n 0` runs it in one process.
python -m pytest -n auto --maxprocesses 2 --dist loadfile --durations=25 "$@"
