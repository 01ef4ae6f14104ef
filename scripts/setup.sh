#!/usr/bin/env bash
# Installs the Debian packages holocap needs (only the missing ones), then configures and
# builds it with every core. Idempotent; works as root or through sudo.
#   scripts/setup.sh            build dependencies + the holocap CLI alone
#   scripts/setup.sh --tests    also the packages the tests and peer checks use (clang, its
#                               libFuzzer and OpenMP for the fuzz.parsers test, clang-tidy for
#                               scripts/check-tidy.sh), and every test suite and benchmark
set -euo pipefail
cd "$(dirname "$0")/.."

want_tests=0
for arg in "$@"; do
  case "$arg" in
    --tests) want_tests=1 ;;
    *) echo "setup.sh: unknown option '$arg'" >&2; exit 2 ;;
  esac
done

packages=(
  build-essential cmake ninja-build pkg-config git
  libeigen3-dev libopencv-dev libopencv-contrib-dev libopenexr-dev libzstd-dev
  libmrcal-dev mrgingham libapriltag-dev libceres-dev
  libcamera-dev libaravis-dev aravis-tools libusb-1.0-0-dev libv4l-dev
  libtorch-dev
  nlohmann-json3-dev libcli11-dev libyaml-cpp-dev
  libzmq3-dev cppzmq-dev
  ffmpeg libcpp-httplib-dev zlib1g-dev libwebp-dev libmeshoptimizer-dev
)
if [ "$want_tests" = 1 ]; then
  packages+=(googletest libgtest-dev clang-format clang-tidy clang libclang-rt-14-dev libomp-14-dev python3-mrcal mrcal python3-numpy python3-opencv python3-open3d iproute2 chromium slurm-wlm munge)
  # Node.js and npm only where no npm runs yet: a machine with NodeSource's nodejs has its
  # own npm, and Debian's npm package conflicts with it.
  command -v npm >/dev/null 2>&1 || packages+=(nodejs npm)
fi

missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  sudo_cmd=()
  [ "$(id -u)" -ne 0 ] && sudo_cmd=(sudo)
  echo "setup.sh: installing ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  "${sudo_cmd[@]}" apt-get update -qq
  "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# The browser tests drive chromium through puppeteer-core, pinned in package-lock.json.
if [ "$want_tests" = 1 ]; then
  (cd tests/playback/browser && npm ci --no-audit --no-fund >/dev/null)
fi

build_dir=${HOLOCAP_BUILD_DIR:-build}
# Every hardware driver, its libraries installed above (named, so that a cached
# -DHOLOCAP_DRIVERS= from an earlier configure does not leave them out).
drivers="-DHOLOCAP_DRIVERS=aravis;v4l2;libcamera"
if [ "$want_tests" = 1 ]; then
  cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=Release "$drivers" \
    -DHOLOCAP_BUILD_TESTS=ON -DHOLOCAP_BUILD_BENCH=ON >/dev/null
  cmake --build "$build_dir" -j "$(nproc)"
else
  # The demo needs the CLI alone: no test suites, no benchmarks (nor GoogleTest to find them).
  cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=Release "$drivers" \
    -DHOLOCAP_BUILD_TESTS=OFF -DHOLOCAP_BUILD_BENCH=OFF >/dev/null
  cmake --build "$build_dir" -j "$(nproc)" --target holocap
fi
