#!/bin/bash
# Calibration from photographs and videos against the take's own: a simulated 2-camera 640x480
# board take of 24 frame sets is calibrated directly, then written as JPEG folders (quality 95,
# one right frame deleted) and as MP4s (H.264, crf 18), imported with `holocap import images`
# and calibrated again (LENSMODEL_OPENCV5 throughout). Per figure (fx fy cx cy of each camera, the
# baseline): its value, its difference to the direct solve and to the truth, the direct solve's
# 1-sigma, the route's own 1-sigma, and |difference to direct| / direct 1-sigma.
# It is the test ImportImages.BoardTakeCalibratesFromJpegFoldersAndMp4sAsFromTheTake
# (tests/interop/images_test.cc), whose table this keeps.
# Usage: bash bench/images_calibration.sh [BUILD] (default build) > bench/images_calibration_results.txt
set -euo pipefail
build=${1:-build}
echo "# bash bench/images_calibration.sh $build ($(date -u '+%Y-%m-%d %H:%M UTC'), at $(git rev-parse --short HEAD), $(nproc) cores, shared)"
echo "# $(uptime)"
HOLOCAP_NO_PROGRESS=1 "$build/tests/interop_tests" \
  --gtest_filter=ImportImages.BoardTakeCalibratesFromJpegFoldersAndMp4sAsFromTheTake |
  awk '/^route /{on=1} on && /^(route|take|jpeg|mp4) /{print} /^\[       OK|^\[  FAILED/{print "# " $0}'
