#!/bin/bash
# export web as shards against one process on a simulated take (12 frame sets at 128 px, the
# meshes and a dynamic splat model at medium,high, --key-every 3: 4 groups), two interleaved
# repeats: the wall time of one process, of 3 shards one after another, and of 2 shards at
# once; each site compared byte for byte with one process's (records and reports aside).
# Usage: bench/web_shard_bench.sh [HOLOCAP] (default build/app/holocap). Note `uptime`: the
# timings mean something only against each other in the same run. The simulated take runs on its
# true cameras (--ground-truth-cameras): the sites are compared with each other, not scored.
set -euo pipefail
H=$(realpath "${1:-build/app/holocap}")
D=$(mktemp -d /tmp/holocap-web-shard-bench.XXXXXX)
trap 'rm -rf "$D"' EXIT
export HOLOCAP_NO_PROGRESS=1
"$H" sim --rig studio8 --frames 13 --clean-plate 1 --size 128 --seed 3 --threads 2 --out "$D/take" >/dev/null
"$H" reconstruct "$D/take" --ground-truth-cameras --voxel 8mm --no-sweep --threads 2 >/dev/null
"$H" train splat "$D/take" --ground-truth-cameras --recon "$D/take/recon" --iterations 60 --frame-iterations 10 --width 64 \
  --seed-points 3000 --heldout 1 --threads 2 --out "$D/splat" >/dev/null
args=(export web "$D/take" --model "$D/splat" --quality medium,high --key-every 3 --ground-truth)
seconds() { local start; start=$(date +%s.%N); "$@" >/dev/null; echo "$(date +%s.%N) - $start" | bc; }
uptime
for repeat in 1 2; do
  rm -rf "$D/whole" "$D/turn" "$D/once"
  whole=$(seconds "$H" "${args[@]}" --out "$D/whole")
  turn=0
  for k in 0 1 2; do turn=$(echo "$turn + $(seconds "$H" "${args[@]}" --out "$D/turn" --shard $k/3)" | bc); done
  start=$(date +%s.%N)
  "$H" "${args[@]}" --out "$D/once" --shard 0/2 >/dev/null &
  first=$!
  "$H" "${args[@]}" --out "$D/once" --shard 1/2 >/dev/null
  wait $first
  once=$(echo "$(date +%s.%N) - $start" | bc)
  printf "repeat %d: one process %6.1f s | 3 shards in turn %6.1f s | 2 shards at once %6.1f s\n" \
    "$repeat" "$whole" "$turn" "$once"
  for site in turn once; do
    diff -r -q -x report.json -x run.json -x frame-reports -x plan -x tasks -x .holocap-output \
      "$D/whole" "$D/$site" >/dev/null && echo "  $site: the same bytes as one process's site"
  done
done
python3 -c "
import json
plan = json.load(open('$D/whole/plan/plan.json'))
report = json.load(open('$D/whole/report.json'))
print('plan made in %.3f CPU s; %d frames, %d groups, %d bytes' % (plan['made_cpu_s'],
      report['metrics']['frames'], len(json.load(open('$D/whole/run.json'))['sets']),
      report['metrics']['bytes']))
for name, s in report['metrics']['streams'].items():
    print('  %-13s %.4f MB/frame  PSNR %.1f dB' % (name, s['mb_per_frame'], s['psnr_db']))"
uptime
