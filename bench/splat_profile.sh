#!/usr/bin/env bash
# One splat training iteration by stage, two builds interleaved row by row (the same load falls
# on both): bench/splat_profile_bench of BEFORE and of AFTER on each scene and width, ROW lines
# gathered into one table. Usage (rows: scene:width[:iterations], default below):
#   bench/splat_profile.sh BEFORE_BENCH AFTER_BENCH [rows...]
set -euo pipefail
before=$1 after=$2
shift 2
rows=("$@")
[ ${#rows[@]} -gt 0 ] || rows=(synthetic:640:10 synthetic:1280:5 dino:640:10 studio8:640:10 object-ring:640:10)
work=${WORK:-/tmp/splat-profile}
holocap=${HOLOCAP:-build/app/holocap}
echo "# bench/splat_profile.sh $before $after ${rows[*]}"
echo "# commit $(git rev-parse --short HEAD), $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2)"
echo "# load at start: $(uptime)"
echo "# columns: build scene size gaussians it/s then ms per iteration: projection sort binning forward loss_ssim backward reduction project_backward statistic adam densification other"
for row in "${rows[@]}"; do
  IFS=: read -r scene width iterations <<<"$row"
  for build in before after; do
    bin=$before
    [ $build = after ] && bin=$after
    line=$("$bin" --scene "$scene" --width "$width" --iterations "${iterations:-10}" --threads 2 \
      --work "$work" --holocap "$holocap" --sim-size 640 2>/dev/null | grep '^ROW' || echo "ROW $scene failed")
    echo "$build ${line#ROW }"
  done
done
echo "# load at end: $(uptime)"
