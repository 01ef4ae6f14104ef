#!/bin/bash
# A ChArUco board take calibrated: a simulated 2-camera 640x480 ring filming a 6 x 5 ChArUco
# board (16 cm squares, 12 cm DICT_4X4_50 markers) in 16 frame sets, `holocap calibrate --board`
# on it. Per take: the corners the solve used against the true grid projected by the true
# cameras (mean and max px, views with part of the board out of sight), the solve's residuals
# beside the corners' RMS error per coordinate, the solved projection's RMS distance to the
# truth's where the board was seen; per camera: the focal length's and principal point's distance
# to the truth beside the solve's own 1-sigma (at its residuals' noise, and scaled to the
# corners' RMS error, the test's bound being 4 times that).
# It is the test CalibrateCli.CalibratesAChArUcoBoardTake (tests/calibration/cli_test.cc), whose
# figures this keeps.
# Usage: bash bench/charuco_calibration.sh [BUILD] (default build) > bench/charuco_calibration_results.txt
set -euo pipefail
build=${1:-build}
echo "# bash bench/charuco_calibration.sh $build ($(date -u '+%Y-%m-%d %H:%M UTC'), at $(git rev-parse --short HEAD), $(nproc) cores, shared)"
echo "# $(uptime)"
HOLOCAP_NO_PROGRESS=1 "$build/tests/calibration_tests" \
  --gtest_filter=CalibrateCli.CalibratesAChArUcoBoardTake |
  awk '/^ChArUco take:|^residuals |^cam[0-9]+: focal/{print} /^\[       OK|^\[  FAILED/{print "# " $0}'
