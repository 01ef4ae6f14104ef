#!/usr/bin/env bash
# Builds holocap's parser fuzzers (bench/fuzz alone, with clang and libFuzzer) and runs each for
# SECONDS (default 60) from its seed corpus bench/fuzz/corpus/<target>/, then prints per target
# the inputs run, the edges and features covered, and the crashes found. Exits 1 if any target
# crashed (the reproducer is left in the printed folder: add it to the corpus once fixed), 77
# if clang's libFuzzer is missing. The ctest test fuzz.parsers runs it with 3 seconds.
#   bash bench/fuzz/run.sh [SECONDS] [TARGET...]
#   HOLOCAP_FUZZ_BUILD=DIR  where to build and run (default build-fuzz)
set -euo pipefail
seconds=${1:-60}
shift $(($# > 0 ? 1 : 0))
root=$(cd "$(dirname "$0")/../.." && pwd)
build=${HOLOCAP_FUZZ_BUILD:-$root/build-fuzz}
work=$build/runs

skip() {
  echo "run.sh: skipped: $1 (scripts/setup.sh --tests installs clang, libclang-rt-14-dev and libomp-14-dev)"
  exit 77
}
command -v clang++ >/dev/null || skip "clang++ is missing"
probe=$(mktemp -d)
trap 'rm -rf "$probe"' EXIT
echo 'extern "C" int LLVMFuzzerTestOneInput(const char*, unsigned long) { return 0; }' \
  >"$probe/probe.cpp"
clang++ -fsanitize=fuzzer,address,undefined "$probe/probe.cpp" -o "$probe/probe" 2>/dev/null ||
  skip "clang++ cannot link libFuzzer with ASan and UBSan"
printf '#include <omp.h>\nint main() { return omp_get_max_threads() > 0 ? 0 : 1; }\n' >"$probe/omp.cpp"
clang++ -fopenmp "$probe/omp.cpp" -o "$probe/omp" 2>/dev/null ||
  skip "clang++ has no OpenMP (the splat kernels the splat readers use need it)"

launcher=()
command -v ccache >/dev/null && launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
mkdir -p "$build"
started=$SECONDS
if ! { cmake -S "$root/bench/fuzz" -B "$build" -G Ninja -DCMAKE_CXX_COMPILER=clang++ \
  "${launcher[@]}" && cmake --build "$build" -j "$(nproc)"; } >"$build/build.log" 2>&1; then
  tail -n 40 "$build/build.log"
  echo "run.sh: building the fuzzers failed (the whole log: $build/build.log)" >&2
  exit 1
fi
echo "run.sh: fuzzers built in $((SECONDS - started)) s ($build)"
if [ $# -gt 0 ]; then
  targets=("$@")
else
  read -ra targets <"$build/targets.txt"
fi

status=0
rm -rf "$work"
printf '%-15s %7s %10s %8s %7s %9s %7s  %s\n' target seconds runs exec/s edges features crashes \
  result
for target in "${targets[@]}"; do
  seeds=$root/bench/fuzz/corpus/$target
  corpus=$work/corpus/$target
  artifacts=$work/artifacts/$target
  log=$work/$target.log
  mkdir -p "$corpus" "$artifacts"
  # New inputs go to the first folder (in the build); the repository's seeds are only read.
  # The parsers' own stderr (libmrcal's messages) is closed: libFuzzer keeps its reports.
  if "$build/fuzz_$target" "$corpus" "$seeds" -max_total_time="$seconds" -timeout=25 \
    -rss_limit_mb=2048 -max_len=16384 -close_fd_mask=3 -print_final_stats=1 \
    -artifact_prefix="$artifacts/" >"$log" 2>&1; then
    result=ok
  else
    result="FAILED: $log, $artifacts/"
    status=1
  fi
  final_stat() { grep -o "stat::$1: *[0-9]*" "$log" | grep -o '[0-9]*$' || echo '?'; }
  last=$(grep -E '^#[0-9]+' "$log" | grep 'cov:' | tail -n 1)
  edges=$(grep -o 'cov: [0-9]*' <<<"$last" | grep -o '[0-9]*' || echo '?')
  features=$(grep -o 'ft: [0-9]*' <<<"$last" | grep -o '[0-9]*' || echo '?')
  crashes=$(find "$artifacts" -type f | wc -l)
  printf '%-15s %7s %10s %8s %7s %9s %7s  %s\n' "$target" "$seconds" "$(final_stat number_of_executed_units)" \
    "$(final_stat average_exec_per_sec)" "$edges" "$features" "$crashes" "$result"
done
exit $status
