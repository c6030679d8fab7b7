#!/usr/bin/env bash
# Benchmark (not a test): the cache's default policy against the thesis' FIFO-second-chance
# baseline on one Zipf trace over the real DEM models (imported with 65 x 65 patches so that there
# are a few hundred patches), at several budgets.
#   tests/bench/cache_bench.sh [build-dir]
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
BUILD=${1:-$ROOT/build}
DATA=${VSM_DATA:-$ROOT/../shared/data}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
for dem in PRISMelevation jacksboro_fault_dem; do
  "$BUILD/server/cli/vsm" import "$DATA/$dem.tif" "$WORK/$dem" --patch-size 65 >/dev/null 2>&1
done
for fraction in 0.1 0.25 0.5; do
  "$BUILD/tests/bench/cache_bench" "$WORK/PRISMelevation" "$WORK/jacksboro_fault_dem" \
    --budget-fraction "$fraction" --accesses 200000 --zipf 1.0
  echo
done
