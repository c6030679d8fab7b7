#!/usr/bin/env bash
# Benchmark (not a test): a merge of models ten times larger than the memory budget stays inside
# the budget. Peak RSS is measured from outside with /usr/bin/time -v, and compared with the same
# merge under a budget larger than both models (what the process needs besides patch data:
# code, GDAL/PCL, metadata, one merge's working set).
#
# Data: the real DEMs in ../shared/data (PRISM as target, Jacksboro as detail), imported with
# 65 x 65 patches.
#
#   tests/bench/merge_budget.sh [path/to/vsm] [work-dir]
set -euo pipefail
source "$(dirname "$0")/bench_lib.sh"
DATA=${VSM_SHARED_DATA:-$ROOT/../shared/data}
bench_vsm_and_work "$@"

rm -rf "$WORK/prism" "$WORK/jack"
"$VSM" import "$DATA/PRISMelevation.tif" "$WORK/prism" --patch-size 65 >/dev/null 2>&1
"$VSM" import "$DATA/jacksboro_fault_dem.tif" "$WORK/jack" --patch-size 65 >/dev/null 2>&1
models=$(( $(du -sb "$WORK/prism" | cut -f1) + $(du -sb "$WORK/jack" | cut -f1) ))
budget=$(( models / 10 ))

run() {  # run <label> <budget-bytes>: one merge into a fresh copy, prints its figures
  local out="$WORK/merged-$1"
  rm -rf "$out"
  /usr/bin/time -v "$VSM" merge "$WORK/prism" "$WORK/jack" --out "$out" --memory-budget "$2" \
    >"$WORK/$1.out" 2>"$WORK/$1.time"
  local rss peak
  rss=$(awk -F: '/Maximum resident set size/ {gsub(/ /, "", $2); print $2}' "$WORK/$1.time")
  peak=$(sed -n 's/^memory: budget .*, peak resident \(.*\), \(.*\) evictions, \(.*\) write-backs$/\1 (\2 evictions, \3 write-backs)/p' "$WORK/$1.out")
  "$VSM" validate "$out" >/dev/null
  printf '%-10s budget %9d B  peak RSS %7d KiB  cache peak %s\n' "$1" "$2" "$rss" "$peak"
  echo "$rss" >"$WORK/$1.rss"
}

echo "models on disk: $models bytes (target + detail); budget = models / 10 = $budget bytes"
run tight "$budget"
run roomy $(( 1 << 30 ))
# The process without any patch data: the same binary and libraries reading the target's metadata.
/usr/bin/time -v "$VSM" info "$WORK/prism" >/dev/null 2>"$WORK/info.time"
base=$(awk -F: '/Maximum resident set size/ {gsub(/ /, "", $2); print $2}' "$WORK/info.time")
echo "peak RSS of 'vsm info' (code, libraries, metadata; no patch data): $base KiB"
tight=$(cat "$WORK/tight.rss")
roomy=$(cat "$WORK/roomy.rss")
echo "peak RSS under the tight budget: $tight KiB ($(( tight - base )) KiB above 'vsm info');" \
  "under 1 GiB: $roomy KiB ($(( roomy - base )) KiB above)"
