#!/usr/bin/env bash
# Builds the interop parsers' libFuzzer fuzzers with Debian's clang in their own tree and runs
# each for SECONDS (default 60) from a small seed corpus. Exits non-zero if any fuzzer found a
# crash, leak or sanitizer error; the reproducer is left in the fuzzer's artifact folder.
#   bash bench/fuzz/run.sh [SECONDS]
set -euo pipefail
seconds=${1:-60}
root=$(cd "$(dirname "$0")/../.." && pwd)
build=${HOLOCAP_FUZZ_BUILD:-$root/build-fuzz}
work=$build/fuzz-runs
command -v clang++ >/dev/null || { echo "run.sh: clang++ is missing (apt-get install clang)" >&2; exit 1; }

# The parsers need core alone: no hardware driver is configured (-DHOLOCAP_DRIVERS=).
cmake -S "$root" -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release \
  -DCMAKE_C_COMPILER=clang -DCMAKE_CXX_COMPILER=clang++ \
  -DHOLOCAP_BUILD_TESTS=OFF -DHOLOCAP_BUILD_BENCH=ON -DHOLOCAP_BUILD_FUZZERS=ON \
  -DHOLOCAP_DRIVERS= >/dev/null
fuzzers=(middlebury krt panoptic colmap nerf cameramodel)
cmake --build "$build" -j 2 --target "${fuzzers[@]/#/fuzz_}"

# Seeds: one small valid file per format (the COLMAP fuzzer's first byte picks the file).
rm -rf "$work" && mkdir -p "$work"
seed() { mkdir -p "$work/seeds-$1"; cat > "$work/seeds-$1/$2"; }
data=$root/tests/data
mkdir -p "$work/seeds-middlebury"
cp "$data/middlebury/dinoSparseRing/dinoSR_par.txt" "$work/seeds-middlebury/" 2>/dev/null || true
seed middlebury small <<'X'
1
a.png 500 0 320 0 500 240 0 0 1 1 0 0 0 1 0 0 0 1 0 0 2
X
seed krt two <<'X'
400001
500 0 31.5
0 505 23.5
0 0 1
-0.1 0.02 0.001 0.0005 0.004
1 0 0 0
0 1 0 0
0 0 1 2

400002
480 0 32
0 480 24
0 0 1
0 0 0 0 0
0 1 0 0.1
-1 0 0 0
0 0 1 2.5
X
seed panoptic one <<'X'
{"calibDataSource": "x", "cameras": [{"name": "00_00", "type": "hd", "resolution": [1920, 1080],
 "panel": 0, "node": 0, "K": [[1400.5, 0, 950.2], [0, 1401.2, 550.9], [0, 0, 1]],
 "distCoef": [-0.21, 0.15, 0.0004, -0.0003, -0.02],
 "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [[10.5], [-20], [300]]}]}
X
printf '\0# cameras\n1 PINHOLE 160 120 300 305 80 60\n2 OPENCV 160 120 300 302 80.7 59.2 -0.2 0.05 0.001 -0.002\n3 FULL_OPENCV 160 120 298 299 80.1 60.3 -0.2 0.05 0.0005 -0.001 0.01 0.02 -0.01 0.003\n4 OPENCV_FISHEYE 100 80 90 90 50 40 0.1 0.01 0 0\n' | seed colmap cameras
printf '\001# images\n1 1 0 0 0 0.1 0.2 3 1 a.png\n10.5 20.25 1 30 40 -1\n2 0.7071067811865476 0 0.7071067811865476 0 0 0 1 2 b/c.png\n\n' | seed colmap images
printf '\002# points\n1 0.1 0.2 0.3 128 64 32 0.25 1 0 2 1\n2 1 2 3 0 0 0 0\n' | seed colmap points
seed nerf blender <<'X'
{"camera_angle_x": 0.6911112070083618, "frames": [{"file_path": "./train/r_0", "rotation": 0.0,
 "transform_matrix": [[-0.9999, 0.0042, -0.0133, -0.0538], [-0.0140, -0.2997, 0.9539, 3.8455],
 [0.0, 0.9540, 0.2997, 1.2081], [0.0, 0.0, 0.0, 1.0]]}]}
X
seed nerf nerfstudio <<'X'
{"camera_model": "OPENCV", "fl_x": 300, "fl_y": 301, "cx": 80, "cy": 60, "w": 160, "h": 120,
 "k1": -0.1, "k2": 0.01, "p1": 0.001, "p2": -0.001, "frames": [{"file_path": "images/a.png",
 "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "k3": 0.002}]}
X
mkdir -p "$work/seeds-cameramodel"
cp "$data/lenses/"*.cameramodel "$work/seeds-cameramodel/" 2>/dev/null || true
seed cameramodel pinhole <<'X'
{ 'lensmodel': 'LENSMODEL_PINHOLE', 'intrinsics': [500, 500, 319.5, 239.5],
  'extrinsics': [0, 0, 0, 0, 0, 0], 'imagersize': [640, 480] }
X

status=0
printf '%-12s %8s %10s %s\n' fuzzer seconds runs result
for name in "${fuzzers[@]}"; do
  mkdir -p "$work/corpus-$name" "$work/artifacts-$name"
  log=$work/$name.log
  if "$build/bench/fuzz/fuzz_$name" "$work/corpus-$name" "$work/seeds-$name" -max_total_time="$seconds" \
       -max_len=16384 -artifact_prefix="$work/artifacts-$name/" -print_final_stats=1 >"$log" 2>&1; then
    result=ok
  else
    result="FAILED (see $log and $work/artifacts-$name/)"
    status=1
  fi
  runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo '?')
  printf '%-12s %8s %10s %s\n' "$name" "$seconds" "$runs" "$result"
done
exit $status
