#!/bin/bash
# Why a simulated studio8 board take at 320 px ends DEGENERATE while the same take at 640 px
# converges, and what a user at 320 px can do: for each run, a 40-set board take (`holocap sim
# --rig studio8 --board --frames 40`), `holocap calibrate` with no flag, the ending, the board
# views found, and how many pixels a tag spans in the views where the board was found and in
# those where its centre was in the image but nothing was found (from the truth: the tag side
# times the focal length over the distance, shrunk by the square root of the cosine of the
# board's tilt to the ray; the truth only measures). Runs: the default 5x4 AprilTag board
# (10 cm tags) at 320 and 640 px, and at 320 px a 4x3 board of 30 cm tags.
# Usage: bash bench/board_resolution.sh [BUILD] [WORK] > bench/board_resolution_results.txt
set -euo pipefail
build=${1:-build}
work=${2:-/tmp/board_resolution}
holocap="$build/app/holocap"
echo "# bash bench/board_resolution.sh $build $work"
echo "# $(date -u '+%Y-%m-%d %H:%M UTC'), at $(git rev-parse --short HEAD), $(nproc) cores, shared:" \
  "$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //')"
echo "# load at start: $(uptime)"
mkdir -p "$work"
printf 'type: apriltag\nfamily: tag36h11\ntags_across: 4\ntags_down: 3\nspacing: 0.3\nmargin: 0.1\n' \
  > "$work/large-tags.yaml"
export HOLOCAP_NO_PROGRESS=1
run() {  # name size [sim flags...]
  local name=$1 size=$2 take="$work/$1"
  shift 2
  if [ ! -f "$take/take.json" ]; then
    "$holocap" sim --rig studio8 --board --frames 40 --size "$size" "$@" --out "$take" \
      --overwrite > "$work/$name.sim.log"
  fi
  "$holocap" calibrate "$take" --no-pictures > "$work/$name.calibrate.log" 2>&1 || true
  /usr/bin/python3 - "$name" "$take" << 'PY'
import glob, json, sys
import mrcal
import numpy as np
name, take = sys.argv[1:]
board = json.load(open(f"{take}/gt/board.json"))
layout = board["layout"]
side = layout["spacing"]
centre = np.array([(layout["width_n"] - 1) * side / 2, (layout["height_n"] - 1) * side / 2, 0, 1])
poses = [np.array(p["matrix"]) for p in board["world_from_board"]]
report = json.load(open(f"{take}/calib/report.json"))
rejected = {(r["frame_set"], r["sensor"]) for r in report["metrics"]["detection"]["rejected"]}
found, missed = [], []
for path in sorted(glob.glob(f"{take}/gt/cameras/cam*.cameramodel")):
    sensor = path.split("/")[-1].split(".")[0]
    model = mrcal.cameramodel(path)
    width, height = model.imagersize()
    focal = model.intrinsics()[1][0]
    rt = model.extrinsics_Rt_fromref()
    eye = -rt[:3, :3].T @ rt[3]
    for s, pose in enumerate(poses):
        point = (pose @ centre)[:3]
        in_camera = mrcal.transform_point_Rt(rt, point)
        if in_camera[2] <= 0:
            continue
        q = mrcal.project(in_camera, *model.intrinsics())
        if not (0 <= q[0] < width and 0 <= q[1] < height):
            continue
        ray = point - eye
        cosine = abs(pose[:3, 2] @ ray) / np.linalg.norm(ray)
        px = focal * side / in_camera[2] * np.sqrt(cosine)
        (missed if (s, sensor) in rejected else found).append((px, in_camera[2]))
summary = report["summary"]
def stats(rows):
    if not rows:
        return "   -      -      -"
    px = np.array([r[0] for r in rows]); z = np.array([r[1] for r in rows])
    return f"{np.min(px):5.1f} {np.median(px):6.1f} {np.median(z):6.2f}"
print(f"{name:16s} {width:4d} {side * 100:5.0f} {len(found):5d} {stats(found)} {len(missed):6d} {stats(missed)}  "
      f"{summary['termination']}: {summary['message']}")
PY
}
echo "# width: px; tag: cm; found / missed: board views detected / with the board's centre in the"
echo "# image but not detected; then the tag's pixels (min, median) and the median distance, m"
echo "run              width  tag found  min_px med_px  dist missed min_px med_px  dist  ending"
run default-320 320
run default-640 640
run large-tags-320 320 --board-layout "$work/large-tags.yaml"
echo "# load at end: $(uptime)"
