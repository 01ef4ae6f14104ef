#!/usr/bin/env bash
# Installs what is missing (test packages included), builds, and runs every test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --tests
# The browser tests skip where chromium or puppeteer-core is missing; here set-up has just
# installed both, so their absence is a failed set-up, not a reason to skip.
command -v chromium >/dev/null || { echo "test.sh: chromium is not installed after set-up" >&2; exit 1; }
[ -d tests/playback/browser/node_modules/puppeteer-core ] ||
  { echo "test.sh: puppeteer-core is not installed after set-up" >&2; exit 1; }
build_dir=${HOLOCAP_BUILD_DIR:-build}
ctest --test-dir "$build_dir" --output-on-failure -j "$(nproc)" --timeout 600
