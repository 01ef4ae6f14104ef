#!/usr/bin/env bash
# clang-tidy (.clang-tidy: bugprone, performance, naming, override) on the C++ sources that
# changed, every finding an error. A whole-tree run takes about half a minute a file on two
# cores (an hour and more), so CI checks what a change touched:
#
#   scripts/check-tidy.sh [BASE]     sources changed between BASE and the working tree
#                                    (default: HEAD~1, the last commit)
#   scripts/check-tidy.sh --all      every source
#
# Needs the compile database of a configured build (HOLOCAP_BUILD_DIR, default build/).
set -euo pipefail
cd "$(dirname "$0")/.."
build_dir=${HOLOCAP_BUILD_DIR:-build}
[ -f "$build_dir/compile_commands.json" ] ||
  { echo "check-tidy: no $build_dir/compile_commands.json (configure a build first)" >&2; exit 1; }
command -v clang-tidy >/dev/null 2>&1 ||
  { echo "check-tidy: clang-tidy is not installed (scripts/setup.sh --tests installs it)" >&2; exit 1; }

if [ "${1:-}" = "--all" ]; then
  mapfile -t files < <(git ls-files '*.cpp' '*.cc' | grep -v '^bench/fuzz/')
else
  base=${1:-HEAD~1}
  if ! git rev-parse --verify --quiet "$base^{commit}" >/dev/null; then
    echo "check-tidy: $base is not a commit here (a shallow clone?): nothing to compare with"
    exit 0
  fi
  mapfile -t files < <(git diff --name-only --diff-filter=AMR "$base" -- '*.cpp' '*.cc' |
                       grep -v '^bench/fuzz/' || true)
fi
# Only what this build compiles (a driver left out has no compile command).
checked=()
for file in "${files[@]}"; do
  grep -q "\"file\": \"$PWD/$file\"" "$build_dir/compile_commands.json" && checked+=("$file")
done
if [ "${#checked[@]}" -eq 0 ]; then
  echo "check-tidy: no compiled C++ source changed"
  exit 0
fi
echo "check-tidy: ${#checked[@]} file(s): ${checked[*]}"
log=$(mktemp)
trap 'rm -f "$log"' EXIT
status=0
printf '%s\n' "${checked[@]}" |
  xargs -P "$(nproc)" -n 1 clang-tidy -p "$build_dir" --quiet --warnings-as-errors='*' \
    >"$log" 2>&1 || status=$?
# Findings are those in the repository's files. clang 14 cannot compile LibTorch 1.13's headers
# in C++20 (c10::IValue is incomplete where std::vector<IValue> is destroyed), so every file
# that includes them (neural/) also reports errors inside /usr/include: those are not findings,
# and they alone do not fail the check; what clang-tidy finds in the file itself still does.
findings=$(grep -E '(warning|error): ' "$log" | grep -v '^[0-9]* warnings generated' |
           grep "^$PWD/" | sort -u || true)
outside=$(grep -E '(warning|error): ' "$log" | grep -v "^$PWD/" | grep -c 'error: ' || true)
[ -n "$findings" ] && printf '%s\n' "$findings"
if [ -n "$findings" ] || { [ "$status" -ne 0 ] && [ "$outside" -eq 0 ]; }; then
  echo "check-tidy: findings above (fix them, or say why with NOLINT(check) on the line)" >&2
  [ -z "$findings" ] && tail -n 20 "$log" >&2
  exit 1
fi
[ "$outside" -gt 0 ] &&
  echo "check-tidy: $outside error(s) inside system headers (LibTorch's, which clang 14 cannot compile in C++20) left aside"
echo "check-tidy: ${#checked[@]} file(s) clean"
