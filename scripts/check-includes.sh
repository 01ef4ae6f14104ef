#!/usr/bin/env bash
# Fails when a source file includes what its folder may not (the table ALLOWED below, the
# folders each library links), when a file includes another folder's private header, or when a
# private header sits outside an `internal/` folder.
#
#   private headers   <folder>/internal/*.h: included only by <folder>/ itself, by its own
#                     tests (tests/<folder>/) and by benchmarks (bench/), which measure a
#                     folder's parts as its tests check them
#   public headers    every other header: included by the folders ALLOWED names
#
# `scripts/check-includes.sh [ROOT]` checks the tracked files of ROOT (default: this checkout).
set -euo pipefail
root=${1:-$(cd "$(dirname "$0")/.." && pwd)}
cd "$root"

# The folders each library folder may include (besides itself); tests/, bench/ and app/ may
# include every folder's public headers.
declare -A ALLOWED=(
  [core]=""
  [capture]="core"
  [interop]="core"
  [sim]="core capture"
  [calibration]="core"
  [reconstruction]="core"
  [scan]="core reconstruction"
  [live]="core reconstruction scan"
  [avatar]="core reconstruction"
  [neural]="core reconstruction scan live avatar"
  [splat]="core reconstruction avatar"
  [playback]="core avatar splat"
  [distributed]="core capture"
)

problems=0
say() {
  echo "check-includes: $*" >&2
  problems=$((problems + 1))
}

# One convention for private headers: internal/, never a suffix or a bare internal.h.
while IFS= read -r header; do
  case "$header" in
    */internal/*) ;;
    *internal*.h) say "$header: a private header belongs in its folder's internal/ (one convention)" ;;
  esac
done < <(git ls-files '*.h')

while IFS= read -r file; do
  folder=${file%%/*}
  owner=$folder
  [ "$folder" = tests ] && { rest=${file#tests/}; owner=tests/${rest%%/*}; }
  while IFS= read -r line; do
    included=$(sed -E 's/^[[:space:]]*#[[:space:]]*include[[:space:]]+"([^"]+)".*/\1/' <<<"$line")
    target=${included%%/*}
    [ "$target" = "$included" ] && continue  # a file beside it, or a generated header
    [ "$target" = "$folder" ] && continue
    case "$included" in
      */internal/*)
        if [ "$owner" != "tests/$target" ] && [ "$folder" != bench ]; then
          say "$file includes $included, a private header of $target/"
        fi
        continue
        ;;
    esac
    case "$folder" in
      tests | bench | app | scripts | docs) continue ;;
    esac
    if [ -z "${ALLOWED[$folder]+set}" ]; then
      say "$file: folder $folder/ is not in this script's ALLOWED table"
      continue
    fi
    # shellcheck disable=SC2076
    if [[ ! " ${ALLOWED[$folder]} " =~ " $target " ]]; then
      say "$file includes $included: $folder/ may include only: ${ALLOWED[$folder]:-nothing else}"
    fi
  done < <(grep -E '^[[:space:]]*#[[:space:]]*include[[:space:]]+"' "$file" || true)
done < <(git ls-files '*.cpp' '*.cc' '*.h' | grep -v '^bench/fuzz/corpus/')

if [ "$problems" -gt 0 ]; then
  echo "check-includes: $problems problem(s)" >&2
  exit 1
fi
echo "check-includes: $(git ls-files '*.cpp' '*.cc' '*.h' | wc -l) files keep the folders' include rules"
