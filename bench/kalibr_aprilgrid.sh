#!/bin/bash
# What Kalibr's aprilgrid costs the solve: its tag corners lie on no uniform grid, so holocap
# solves mrcal's uniform board with the step tagSize / tag_steps and observes only the corners
# (docs/calibration.md "Kalibr aprilgrid"). A simulated 2-camera 640x480 ring (the ring of
# tests/calibration/cli_test.cc) films each board in 16 frame sets, then `holocap calibrate
# --board` solves it. Per board: grid points per view (observed), views, the solve's and the
# uncertainty's seconds as calibrate prints them, calibrate's wall time and peak memory, and its
# distance to the truth, the mean distance of the corners it used from the true grid's
# projection (corners_px) and the tag border they were found with. holocap's own 6 x 6 board
# (the same tags, one tag apart) is the peer measured in the same run; kalibr_4x3_kprint is the
# 4 x 3 board filmed as Kalibr's kalibr_create_target_pdf prints it (sim --board-print kalibr:
# two-bit tag borders, black squares at the tags' corners), read with the same YAML. Then
# whether holocap's detector finds a board printed as Kalibr prints it, drawn here independently
# of holocap (OpenCV's DICT_APRILTAG_36h11 bits, which OpenCV draws turned 180 degrees against
# libapriltag's and Kalibr's tags, turned back; two-bit borders, with and without the black
# squares at the tags' corners) beside holocap's own print of the same layout (3 x 2 tags): each
# image imported as a one-camera take of two frames and calibrated, which detects first (two
# views of one camera solve nothing: only the detection line counts). Last the tests
# CalibrateCli.CalibratesAKalibrAprilgridTake and CalibrateCli.CalibratesAKalibrPrintedAprilgridTake
# (tests/calibration/cli_test.cc, 4 x 3 tags of 15 cm at 0.3), whose figures this keeps: their
# corners against the true grid and each camera's intrinsics against the truth and the solve's
# 1-sigma.
# Usage: bash bench/kalibr_aprilgrid.sh [BUILD] (default build) > bench/kalibr_aprilgrid_results.txt
set -euo pipefail
build=${1:-build}
holocap=$(realpath "$build/app/holocap")
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
echo "# bash bench/kalibr_aprilgrid.sh $build ($(date -u '+%Y-%m-%d %H:%M UTC'), at $(git rev-parse --short HEAD), $(nproc) cores, shared)"
echo "# $(uptime)"
cat > "$work/ring2.yaml" <<'RIG'
name: ring
fps: 30
sensors:
  - name: cam0
    uri: sim:ring#cam0
    role: color
    options:
      lens: LENSMODEL_OPENCV4
      intrinsics: [520.3, 519.1, 322.4, 236.9, -0.082, 0.031, 0.0006, -0.0004]
      size: [640, 480]
      position: [2.77164, 1.14805, 1.45]
      look_at: [0, 0, 1.0]
  - name: cam1
    uri: sim:ring#cam1
    role: color
    options:
      lens: LENSMODEL_OPENCV5
      intrinsics: [561.7, 560.2, 316.8, 243.5, -0.121, 0.094, -0.0003, 0.0007, -0.021]
      size: [640, 480]
      position: [1.19067, 2.87450, 2.1]
      look_at: [0, 0, 0.9]
RIG
printf 'type: apriltag\nfamily: tag36h11\ntags_across: 6\ntags_down: 6\nspacing: 0.088\nmargin: 0.088\n' > "$work/holocap_6x6.yaml"
printf "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0.25\n" > "$work/kalibr_6x6_g0.25.yaml"
printf "target_type: 'aprilgrid'\ntagCols: 4\ntagRows: 3\ntagSize: 0.15\ntagSpacing: 0.3\n" > "$work/kalibr_4x3_g0.3.yaml"
printf "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0.3\n" > "$work/kalibr_6x6_g0.3.yaml"
cp "$work/kalibr_4x3_g0.3.yaml" "$work/kalibr_4x3_kprint.yaml"
printf '%-18s %10s %9s %6s %8s %8s %8s %8s %10s %9s %10s %6s\n' board grid observed views solve_s \
  uncert_s wall_s rss_mb focal_err principal corners_px border
for board in holocap_6x6 kalibr_6x6_g0.25 kalibr_4x3_g0.3 kalibr_4x3_kprint kalibr_6x6_g0.3; do
  take="$work/$board"
  print=holocap
  [ "$board" = kalibr_4x3_kprint ] && print=kalibr
  (cd "$work" && HOLOCAP_NO_PROGRESS=1 "$holocap" sim --rig ring2.yaml --board \
    --board-layout "$board.yaml" --board-print $print --frames 16 --size 640 --out "$take" \
    > /dev/null)
  out=$( { HOLOCAP_NO_PROGRESS=1 /usr/bin/time -f 'TIME %e %M' "$holocap" calibrate "$take" \
    --no-pictures --board "$work/$board.yaml" --write-corners "$take/corners.vnl"; } 2>&1)
  /usr/bin/python3 - "$take" "$board" "$out" <<'PY'
import json, re, sys
import mrcal
import numpy as np
take = sys.argv[1]
report = json.load(open(take + "/calib/report.json"))
out = sys.argv[3]
board = report["options"]["board"]
m = report["metrics"]
solve = re.search(r"solve ([0-9.]+) s, uncertainty ([0-9.]+) s", out)
wall, rss = re.search(r"TIME ([0-9.]+) ([0-9]+)", out).groups()
views = sum(c["views"] for c in m["cameras"].values())
observed = 4 * (board["tags_across"] * board["tags_down"])
# The corners used against the true grid, projected by the true cameras and board poses.
truth = json.load(open(take + "/gt/board.json"))
board_rt = {e["set"]: np.array(e["rt"]) for e in truth["world_from_board"]}
models, rows, errors = {}, {}, []
for line in open(take + "/corners.vnl"):
    if line.startswith("#"):
        continue
    name, x, y, _ = line.split()
    row = rows[name] = rows.get(name, -1) + 1
    if x == "-":
        continue
    camera, frame = name.split("/")
    model = models.setdefault(camera, mrcal.cameramodel(f"{take}/gt/cameras/{camera}.cameramodel"))
    point = np.array([row % board["width_n"], row // board["width_n"], 0.0]) * board["spacing"]
    world = mrcal.transform_point_rt(board_rt[int(frame.split(".")[0])], point)
    pixel = mrcal.project(mrcal.transform_point_rt(model.extrinsics_rt_fromref(), world),
                          *model.intrinsics())
    errors.append(np.linalg.norm(pixel - [float(x), float(y)]))
borders = ",".join("%s-bit" % k for k in m["detection"]["views_per_tag_border_bits"])
print("%-18s %10s %9d %6d %8s %8s %8s %8.0f %9.4f%% %7.3fpx %8.4fpx %6s  %s" % (
    sys.argv[2], "%dx%d" % (board["width_n"], board["height_n"]), observed, views,
    solve.group(1), solve.group(2), wall, int(rss) / 1024, 100 * m["gt"]["focal_rel_err_max"],
    m["gt"]["principal_point_err_px_max"], np.mean(errors), borders,
    report["summary"]["termination"]))
PY
done

echo "# a printed 3 x 2 aprilgrid (tagSize 0.1, tagSpacing 0.3) seen square-on, two frames each"
printf "target_type: 'aprilgrid'\ntagCols: 3\ntagRows: 2\ntagSize: 0.1\ntagSpacing: 0.3\n" > "$work/k32.yaml"
HOLOCAP_NO_PROGRESS=1 "$holocap" board "$work/k32.yaml" --out "$work/holocap_print.png" --dpi 120 > /dev/null
/usr/bin/python3 - "$work" <<'PY'
import sys
import cv2
import numpy as np
tags = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
cols, rows, side, gap, margin = 3, 2, 200, 60, 120
pitch = side + gap
width, height = cols * pitch - gap + 2 * margin, rows * pitch - gap + 2 * margin
for squares in (False, True):
    image = np.full((height, width), 255, np.uint8)
    for r in range(rows):
        for c in range(cols):
            x, y = margin + c * pitch, height - margin - r * pitch - side  # row 0 at the bottom
            image[y:y + side, x:x + side] = np.rot90(
                cv2.aruco.drawMarker(tags, r * cols + c, side, borderBits=2), 2)
            if squares:
                for sx, sy in ((x - gap, y - gap), (x + side, y - gap), (x - gap, y + side),
                               (x + side, y + side)):
                    image[sy:sy + gap, sx:sx + gap] = 0
    image = cv2.resize(cv2.GaussianBlur(image, (0, 0), 1.0), (width // 2, height // 2),
                       interpolation=cv2.INTER_AREA)
    name = "kalibr_print" if squares else "kalibr_borders_only"
    cv2.imwrite(f"{sys.argv[1]}/{name}.png", image)
PY
for print in holocap_print kalibr_borders_only kalibr_print; do
  mkdir -p "$work/src_$print"
  cp "$work/$print.png" "$work/src_$print/0.png"
  cp "$work/$print.png" "$work/src_$print/1.png"
  HOLOCAP_NO_PROGRESS=1 "$holocap" import images --camera "a=$work/src_$print/*.png" \
    --out "$work/t_$print" > /dev/null
  result=$(HOLOCAP_NO_PROGRESS=1 "$holocap" calibrate "$work/t_$print" --board "$work/k32.yaml" \
    --no-pictures 2>&1 | grep -E '^detected|error' | head -1 || true)
  printf '%-20s %s\n' "$print" "$result"
done
for test in CalibratesAKalibrAprilgridTake CalibratesAKalibrPrintedAprilgridTake; do
  echo "# the test CalibrateCli.$test"
  HOLOCAP_NO_PROGRESS=1 "$build/tests/calibration_tests" --gtest_filter=CalibrateCli.$test |
    awk '/aprilgrid take:|^residuals |^cam[0-9]+: focal/{print} /^\[       OK|^\[  FAILED/{print "# " $0}'
done
echo "# $(uptime)"
