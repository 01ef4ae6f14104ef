#!/bin/bash
# Chessboard finders against each other and the truth: a simulated studio8 take (colour cameras
# only, 48 frame sets at 640 px) of a square chessboard (7 x 7 inner corners, 0.1 m squares) is
# calibrated with `--compare-detectors`: holocap's finder, OpenCV's recipe
# (findChessboardCorners + cornerSubPix, 11 x 11 half window or half the corner spacing where
# smaller) and mrgingham, per pair and against the true corners (gt/cameras, gt/board.json);
# then calibrated with each `--detector`, the focal error against the truth.
# Usage: bash bench/chessboard_detectors.sh [BUILD] (default build) > bench/chessboard_detectors_results.txt
set -euo pipefail
build=${1:-build}
holocap=$(realpath "$build/app/holocap")
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
echo "# bash bench/chessboard_detectors.sh $build ($(date -u '+%Y-%m-%d %H:%M UTC'), at $(git rev-parse --short HEAD), $(nproc) cores, shared)"
echo "# $(uptime)"
export HOLOCAP_NO_PROGRESS=1
printf 'type: chessboard\nchessboard_width_n: 7\nchessboard_height_n: 7\nspacing: 0.1\nmargin: 0.2\n' >"$dir/square.yaml"
"$holocap" sim --rig studio8 --board --board-layout "$dir/square.yaml" --color-only --frames 48 \
  --size 640 --out "$dir/take" >/dev/null
for detector in holocap mrgingham; do
  out=$("$holocap" calibrate "$dir/take" --no-pictures --detector "$detector" \
    $([ "$detector" = holocap ] && echo --compare-detectors) 2>&1 || true)
  if [ "$detector" = holocap ]; then
    echo "$out" | awk '/^chessboard corners/{on=1} on && !/^report:/{print}'
  fi
  echo "--detector $detector: $(echo "$out" | grep -E '^(CONVERGENCE|NO_CONVERGENCE|DEGENERATE|FAILURE|SUCCESS):' | cut -c1-60)"
  echo "--detector $detector: $(echo "$out" | grep '^vs truth:')"
done
