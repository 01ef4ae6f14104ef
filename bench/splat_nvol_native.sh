#!/bin/bash
# Splats against Neural Volumes on object captures at the images' native resolution, the same
# inputs and the same process CPU time (loading and seeding inside it), each trainer enforcing
# the budget itself: `holocap train splat` and `holocap train nvol` with no flag but the budget
# and the held-out cameras, on
#   - Middlebury dinoSparseRing (real, 16 views at 640x480, its own calibration; one camera
#     held out, as `--heldout 1` picks it for both), and
#   - the simulator's alpha object (100 colour cameras on a sphere at 800x800, the silhouette in
#     alpha, calibrated from a board take of the same rig as bench/mvs_many_views.sh does; the
#     same three cameras held out from both), scored on white too, as alpha datasets publish.
# Neural Volumes train at the width their plan picks (160 px on both) unless told: the rows
# `*-nvol-native` give them `--width` of the images' own, so that both models are scored on the
# same, native pixels. ROWS="name ..." runs only those rows (default: all six).
# All runs go at once (the budgets are CPU seconds, so load moves wall time only). Prints one
# row per run: held-out PSNR whole / inside the subject's silhouette / on white, iterations,
# CPU seconds spent (loading and seeding + training; scoring apart) and the ending.
# Usage: bash bench/splat_nvol_native.sh BUILD WORK MINUTES DINO_TAKE OBJECT_TAKE
#          > bench/splat_nvol_native_results.txt
#   DINO_TAKE: `holocap import middlebury tests/data/middlebury/dinoSparseRing --out DIR`
#   OBJECT_TAKE: bench/mvs_many_views.sh's calibrated knot100 take
set -euo pipefail
build=$1 work=$2 minutes=$3 dino=$4 object=$5
holocap="$build/app/holocap"
echo "# bash bench/splat_nvol_native.sh $*"
echo "# $(date -u '+%Y-%m-%d %H:%M UTC'), at $(git rev-parse --short HEAD), $(nproc) cores, shared:" \
  "$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //')"
echo "# load at start: $(uptime)"
mkdir -p "$work"
export HOLOCAP_NO_PROGRESS=1 OMP_WAIT_POLICY=PASSIVE
pids=()
train() {  # name kind take flags...
  local name=$1 kind=$2 take=$3
  shift 3
  echo "\$ $holocap train $kind $take $* --cpu-minutes $minutes --out $work/$name --overwrite"
  "$holocap" train "$kind" "$take" "$@" --cpu-minutes "$minutes" --out "$work/$name" \
    --overwrite > "$work/$name.log" 2>&1 &
  pids+=($!)
}
native_width() {  # a take's first colour stream's width
  /usr/bin/python3 -c 'import json, sys
print(next(s["width"] for s in json.load(open(sys.argv[1]))["streams"] if s["role"] == "color"))' \
    "$1/take.json"
}
rows=${ROWS:-dino-nvol dino-nvol-native dino-splat object-nvol object-nvol-native object-splat}
for row in $rows; do
  case $row in
    dino-nvol) train "$row" nvol "$dino" --heldout 1 ;;
    dino-nvol-native) train "$row" nvol "$dino" --heldout 1 --width "$(native_width "$dino")" ;;
    dino-splat) train "$row" splat "$dino" --heldout 1 ;;
    object-nvol) train "$row" nvol "$object" --heldout-names cam10,cam50,cam90 ;;
    object-nvol-native)
      train "$row" nvol "$object" --heldout-names cam10,cam50,cam90 \
        --width "$(native_width "$object")" ;;
    object-splat) train "$row" splat "$object" --heldout-names cam10,cam50,cam90 ;;
    *) echo "unknown row $row" >&2; exit 2 ;;
  esac
done
for pid in "${pids[@]}"; do wait "$pid" || true; done
echo "# load at end: $(uptime)"
echo "# psnr: held-out, dB; subject: inside the held-out silhouettes grown 3 px; white: composited"
echo "# on white by the frames' own alpha; cpu_s: loading and seeding + training (the budget's);"
echo "# width: the scored images' width (the plan's image_size)"
echo "run            width  psnr  subject  white  iterations   cpu_s  termination"
for name in $rows; do
  /usr/bin/python3 - "$name" "$work/$name/report.json" << 'PY'
import json, math, sys
name, path = sys.argv[1:]
try:
    report = json.load(open(path))
except OSError:
    print(f"{name:14s} no report.json")
    sys.exit(0)
m = report.get("metrics", {})
plan = report.get("plan", {})
width = plan.get("image_size", ["?"])[0]
cpu = m.get("cpu_s_seed", m.get("cpu_s_loading", 0)) + m.get("cpu_s_training", 0)
white = m.get("heldout_psnr_white_db", float("nan"))
print(f"{name:14s} {str(width):>5s} {m.get('heldout_psnr_db', float('nan')):5.2f}  "
      f"{m.get('heldout_psnr_fg_db', float('nan')):7.2f} {white:6.2f} {m.get('iterations', 0):11d} "
      f"{cpu:7.1f}  {report['summary']['termination']}")
PY
done
