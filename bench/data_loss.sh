#!/bin/bash
# The five ways a command once lost what was there, each run again: a tree hash of what was
# there before and after the command (sha256 of the sorted sha256sum list of its files, the lock
# and a report.failed.json left out), the exit status and the last line printed.
#   1 sim --overwrite into a folder whose take.json is any JSON (a source tree beside it)
#   2 a calibrate that fails, over a take's good calib/report.json
#   3 calibrate through a calib/ that links into another take
#   4 reconstruct A --out B/recon, B's own results there
#   5 two train splat into one --out outside a take, the second 1.5 s after the first
# Usage: bench/data_loss.sh [HOLOCAP] (default build/app/holocap). Equal hashes: nothing lost.
# The small simulated takes run on their true cameras (--ground-truth-cameras): what is measured
# is what the commands keep and write, not their accuracy.
set -uo pipefail
H=$(realpath "${1:-build/app/holocap}")
W=$(mktemp -d /tmp/holocap-data-loss.XXXXXX)
trap 'rm -rf "$W"' EXIT
export HOLOCAP_NO_PROGRESS=1
cd "$W"
tree() { (cd "$1" && find . -type f ! -name .holocap.lock ! -name report.failed.json -print0 | sort -z | xargs -0 sha256sum) | sha256sum | cut -c1-16; }
$H sim --rig single-rgbd --frames 2 --size 96x72 --no-noise --out base >/dev/null 2>&1
echo "case | before | after | exit | last line"
# 1
mkdir -p proj/src; echo x > proj/src/main.c; echo '{"name":"cfg"}' > proj/take.json
b=$(tree proj); out=$($H sim --rig studio8 --frames 2 --size 160 --out proj --overwrite 2>&1); rc=$?
echo "1 sim --overwrite into a folder with take.json | $b | $(tree proj) | $rc | $(echo "$out" | tail -1 | cut -c1-110)"
# 2
cp -a base t2; mkdir -p t2/calib; echo '{"command":"calibrate","summary":{"termination":"SUCCESS"}}' > t2/calib/report.json
b=$(tree t2/calib); out=$($H calibrate t2 2>&1); rc=$?
echo "2 failed calibrate, calib/ without report.failed.json | $b | $(tree t2/calib) (report.failed.json beside: $(test -f t2/calib/report.failed.json && echo yes)) | $rc | $(echo "$out" | tail -1 | cut -c1-110)"
# 3
cp -a base a3; cp -a base b3; mkdir -p b3/calib; echo '{}' > b3/calib/report.json; ln -s "$W/b3/calib" a3/calib
b=$(tree b3); out=$($H calibrate a3 2>&1); rc=$?
echo "3 calibrate through a linked calib/, other take | $b | $(tree b3) | $rc | $(echo "$out" | tail -1 | cut -c1-110)"
# 4
cp -a base b4; $H reconstruct b4 --ground-truth-cameras >/dev/null 2>&1
b=$(tree b4/recon); out=$($H reconstruct base --ground-truth-cameras --out b4/recon 2>&1); rc=$?
echo "4 reconstruct A --out B/recon | $b | $(tree b4/recon) | $rc | $(echo "$out" | tail -1 | cut -c1-110)"
# 5
$H sim --rig studio8 --frames 2 --clean-plate 1 --size 64 --out s5 >/dev/null 2>&1; $H reconstruct s5 --ground-truth-cameras --voxel 20mm --no-sweep >/dev/null 2>&1
$H train splat s5 --ground-truth-cameras --iterations 200 --threads 1 --out m5 > o1.txt 2>&1 & p1=$!
sleep 1.5; $H train splat s5 --ground-truth-cameras --iterations 30 --threads 1 --out m5 > o2.txt 2>&1; rc2=$?; wait $p1; rc1=$?
echo "5 two train splat into one --out | first exit $rc1 ($(grep -o '^[A-Z_]*:' o1.txt | tail -1)) | second exit $rc2 | $(tail -1 o2.txt | cut -c1-110)"
