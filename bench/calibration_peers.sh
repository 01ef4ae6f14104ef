#!/bin/bash
# holocap calibrate beside mrcal's own tool and OpenCV on the same images: a simulated take of
# three 640x480 cameras (bench/calibration_peers_rig.yaml, OPENCV5 lenses) filming a square
# chessboard (10 x 10 inner corners, 0.06 m squares) in 40 frame sets is written as PNG folders
# (`export images --format png`) and calibrated in LENSMODEL_OPENCV5 (OpenCV's standard
# 5-coefficient model) by holocap, by mrgingham + mrcal-calibrate-cameras and by OpenCV
# (findChessboardCorners + cornerSubPix, calibrateCamera, stereoCalibrate), each on its own
# corners and again on holocap's (`calibrate --write-corners`); then mrcal's recommended path,
# its splined model, on mrgingham's corners. Scored against the take's gt/ (which only scores):
# bench/calibration_peers.py says how.
# With --real DIR, real photographs instead (no truth): DIR's left*.jpg and right*.jpg, paired by
# number, and its board.yaml (a chessboard) go through `holocap import images` and `holocap
# calibrate` as a user runs them, and holocap, mrcal-calibrate-cameras (on holocap's corners;
# mrgingham reads N x N grids only) and OpenCV (its own corners and holocap's) are tabulated
# beside holocap's 1-sigma: `calibration_peers.py real` says how.
# Usage: bash bench/calibration_peers.sh [BUILD] (default build) > bench/calibration_peers_results.txt
#        bash bench/calibration_peers.sh build --real tests/data/opencv-stereo \
#          > bench/calibration_peers_real_results.txt
set -euo pipefail
build=${1:-build}
holocap=$(realpath "$build/app/holocap")
here=$(dirname "$(realpath "$0")")
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
echo "# bash bench/calibration_peers.sh $* ($(date -u '+%Y-%m-%d %H:%M UTC'), at $(git rev-parse --short HEAD), $(nproc) cores, shared: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'))"
echo "# $(uptime)"
export HOLOCAP_NO_PROGRESS=1
if [ "${2:-}" = "--real" ]; then
  [ -n "${3:-}" ] || { echo "calibration_peers.sh: --real needs a folder" >&2; exit 2; }
  /usr/bin/python3 "$here/calibration_peers.py" real --holocap "$holocap" --data "$(realpath "$3")" \
    --work "$dir/work"
  echo "# $(uptime)"
  exit 0
fi
printf 'type: chessboard\nchessboard_width_n: 10\nchessboard_height_n: 10\nspacing: 0.06\nmargin: 0.2\n' >"$dir/square.yaml"
"$holocap" sim --rig "$here/calibration_peers_rig.yaml" --board --board-layout "$dir/square.yaml" \
  --frames 40 --out "$dir/take" >/dev/null
/usr/bin/python3 "$here/calibration_peers.py" run --holocap "$holocap" --take "$dir/take" \
  --work "$dir/work" --lensmodel LENSMODEL_OPENCV5 \
  --splined LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=70
echo "# $(uptime)"
