#!/bin/bash
# Multi-view stereo over many views: `holocap reconstruct` with no hand-set flags on the
# simulator's alpha object seen by 100 colour cameras on a sphere at 800x800 (one frame set),
# calibrated as a user calibrates a rig: a board take of the same rig (100 frame sets at 320 px,
# the lens scaled from there), `holocap calibrate BOARD`, `holocap calibrate TAKE --from BOARD`.
# Three cameras are held out to score the mesh (heldout_iou in the report: the mesh's silhouette
# against each one's alpha); the truth only scores.
# Per run: wall and CPU seconds (/usr/bin/time), the held-out IoU, the plan's stereo estimate and
# the stereo's own split of its seconds. BEFORE=path/to/an/older/holocap runs that binary on the
# same take first (the same flags), for a before-and-after table; FLAGS="..." adds flags to
# both (none by default).
# Usage: bash bench/mvs_many_views.sh [BUILD] [WORK] (default build, /tmp/mvs_many_views)
#          > bench/mvs_many_views_results.txt
set -euo pipefail
build=${1:-build}
work=${2:-/tmp/mvs_many_views}
holocap="$build/app/holocap"
echo "# bash bench/mvs_many_views.sh $build $work${BEFORE:+ (BEFORE=$BEFORE)}${FLAGS:+ (FLAGS=$FLAGS)}"
echo "# $(date -u '+%Y-%m-%d %H:%M UTC'), at $(git rev-parse --short HEAD), $(nproc) cores, shared:" \
  "$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //')"
echo "# $(uptime)"
mkdir -p "$work"
take="$work/knot100"
board="$work/knot100-board"
export HOLOCAP_NO_PROGRESS=1
if [ ! -f "$take/take.json" ]; then
  "$holocap" sim --rig sphere100 --scene object --alpha --color-only --frames 1 \
    --out "$take" --overwrite > "$work/sim.log"
fi
if [ ! -f "$board/calib/report.json" ]; then
  if [ ! -f "$board/take.json" ]; then
    "$holocap" sim --rig sphere100 --board --color-only --frames 100 --size 320 \
      --out "$board" --overwrite > "$work/board.log"
  fi
  "$holocap" calibrate "$board" --no-pictures > "$work/calibrate.log" || true
fi
if [ ! -f "$take/calib/cam0.cameramodel" ]; then
  "$holocap" calibrate "$take" --from "$board" > "$work/adopt.log"
fi
/usr/bin/python3 - "$board/calib/report.json" << 'EOF'
import json, sys
summary = json.load(open(sys.argv[1]))["summary"]
print(f"# the board take's calibration: {summary['termination']}: {summary['message']}")
EOF

# One reconstruction with `binary`, named `name`: its row of the table.
run() {
  local name=$1 binary=$2 out="$work/recon-$1"
  rm -rf "$out"
  /usr/bin/time -f '%e %U %S' -o "$work/time-$name" \
    "$binary" reconstruct "$take" --heldout-names cam10,cam50,cam90 --out "$out" ${FLAGS:-} \
    > "$work/recon-$name.log" 2>&1 || true
  read -r wall user sys < "$work/time-$name"
  /usr/bin/python3 - "$name" "$wall" "$user" "$sys" "$out/report.json" << 'EOF'
import json, sys
name, wall, user, system, path = sys.argv[1:]
report = json.load(open(path))
frame = report["metrics"]["frames"][0]
mvs = frame["metrics"].get("mvs", {})
estimate = report["plan"].get("stereo_estimate", {}).get("seconds")
views = report["plan"].get("stereo_views", {}).get("references")
print(f"{name:7s} {float(wall):8.1f} {float(user) + float(system):8.1f} "
      f"{report['metrics'].get('heldout_iou_mean', float('nan')):8.4f} "
      f"{len(views) if views else 99:6d} "
      f"{estimate if estimate is not None else float('nan'):8.1f} "
      f"{mvs.get('sweep_seconds', float('nan')):8.1f} {mvs.get('seconds', float('nan')):8.1f} "
      f"{frame['seconds']:8.1f}  {report['summary']['termination']}")
EOF
}
echo "# wall_s, cpu_s (user + system): the whole command; iou: held-out mean (cam10, cam50, cam90);"
echo "# views: reference views searched; estimate_s: the plan's estimate of the sweeps;"
echo "# sweep_s: the sweeps' seconds summed over views (one thread each); mvs_s: stereo's wall clock;"
echo "# frame_s: the frame set's (hull, stereo, fusion, texture)"
echo "run       wall_s    cpu_s      iou  views estimate  sweep_s    mvs_s  frame_s  termination"
if [ -n "${BEFORE:-}" ]; then run before "$BEFORE"; fi
run after "$holocap"
