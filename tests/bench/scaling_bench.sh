#!/usr/bin/env bash
# Benchmark (not a test): how the cost of `vsm import` and `vsm merge` grows with the work.
#
# The inputs are SYNTHETIC: GeoTIFFs (EPSG:4326, float32) of merge_terrain.py's analytic surface.
#   import: rasters of 2049^2, 4097^2, 8193^2 and 16385^2 at 1" (257 x 257 patches: depth 3 to
#           6), each imported into a fresh directory;
#   merge:  one detail model (1921^2 at 0.8", about 105 MB of OPC, merge_bench.sh's (b)) merged in
#           place into fresh copies of targets at 3" whose OPCs take about 20, 200 and 2000 MB
#           (833^2, 2635^2 and 8333^2 samples; the detail lies inside each). The merge's work is
#           the same in all three: its time should not grow with the target.
# Each row: wall seconds and peak RSS (/usr/bin/time) of one run, and the size of what it wrote.
# Import's working set is bounded by its budget (the pyramid builder holds a few rows of patches
# per level, not the raster), merge's by --memory-budget (1 GiB default) plus what
# core/merge/merge.hpp states: peak RSS should stay flat in the raster and target size.
#
#   tests/bench/scaling_bench.sh [path/to/vsm] [work-dir]
# Defaults: build/server/cli/vsm and a temporary directory (removed afterwards; needs ~12 GB).
# VSM_BENCH_PARTS (default "im") picks import (i) and/or merge (m).
set -euo pipefail
source "$(dirname "$0")/bench_lib.sh"
PARTS=${VSM_BENCH_PARTS:-im}
bench_vsm_and_work "$@"

raster() {  # raster <name> <west> <north> <spacing"> <size>: the GeoTIFF, once
  [[ -f "$WORK/$1.tif" ]] || "$PYTHON" "$HERE/merge_terrain.py" "$WORK/$1.tif" "$2" "$3" "$4" "$5"
}

measure() {  # measure <command...>: prints "<wall s> <peak RSS MiB>" of one run
  /usr/bin/time -f '%e %M' -o "$WORK/last.time" "$@" >/dev/null 2>&1
  awk '{ printf "%.2f %.0f\n", $1, $2 / 1024 }' "$WORK/last.time"
}

if [[ $PARTS == *i* ]]; then
  echo "import (1\" spacing, 257 x 257 patches, fresh output directory):"
  printf '  %-8s %9s %10s %12s %10s\n' size raster wall "peak RSS" OPC
  for size in 2049 4097 8193 16385; do
    raster "import-$size" 10 47.5 1 "$size"
    rm -rf "$WORK/import-$size.opc"
    sync
    read -r wall rss < <(measure "$VSM" import "$WORK/import-$size.tif" "$WORK/import-$size.opc" \
      --patch-size 257)
    printf '  %-8s %6d MB %8s s %8s MiB %7d MB\n' "${size}^2" \
      "$(megabytes "$WORK/import-$size.tif")" "$wall" "$rss" "$(megabytes "$WORK/import-$size.opc")"
    rm -rf "$WORK/import-$size.opc"
  done
fi

if [[ $PARTS == *m* ]]; then
  raster detail -100.3 36.3 0.8 1921
  [[ -d "$WORK/detail.opc" ]] ||
    "$VSM" import "$WORK/detail.tif" "$WORK/detail.opc" --patch-size 257 >/dev/null 2>&1
  echo "merge of the same detail (1921^2 at 0.8\", $(megabytes "$WORK/detail.opc") MB of OPC)" \
    "in place into a fresh copy of each target (3\"):"
  printf '  %-8s %9s %10s %12s\n' target OPC wall "peak RSS"
  for size in 833 2635 8333; do
    raster "target-$size" -100.5 36.5 3 "$size"
    [[ -d "$WORK/target-$size.opc" ]] ||
      "$VSM" import "$WORK/target-$size.tif" "$WORK/target-$size.opc" --patch-size 257 \
        >/dev/null 2>&1
    rm -rf "$WORK/copy"
    cp -a "$WORK/target-$size.opc" "$WORK/copy"
    sync
    read -r wall rss < <(measure "$VSM" merge "$WORK/copy" "$WORK/detail.opc")
    printf '  %-8s %6d MB %8s s %8s MiB\n' "${size}^2" "$(megabytes "$WORK/target-$size.opc")" \
      "$wall" "$rss"
  done
  rm -rf "$WORK/copy"
fi
