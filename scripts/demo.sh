#!/usr/bin/env bash
# Installs what is missing, builds, and runs `holocap demo` on the simulated rig (out/demo/).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
"${HOLOCAP_BUILD_DIR:-build}/app/holocap" demo "$@"
