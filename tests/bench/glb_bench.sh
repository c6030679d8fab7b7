#!/usr/bin/env bash
# Benchmark (not a test): 3D Tiles GLB bytes per tile, uncompressed (float32, ?compress=none)
# against compressed (KHR_mesh_quantization + EXT_meshopt_compression, vsmd's default), total and
# geometry only (without the embedded PNG texture), and encodeGlb's time per tile, over every tile
# of real models: PRISM with the NASA image as the tests import it (65 x 65 patches, the
# tiles.prepare fixture), PRISM with Jacksboro merged into it, and PRISM at vsm's default patch
# size. Writes tests/bench/results/glb.txt.
#   tests/bench/glb_bench.sh [build-dir]
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
BUILD=${1:-$ROOT/build}
DATA=${VSM_DATA:-$ROOT/../shared/data}
OUT=$ROOT/tests/bench/results/glb.txt
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
VSM="$BUILD/server/cli/vsm"
texture=(--texture "$DATA/conus_visible_earth.tif")
"$VSM" import "$DATA/PRISMelevation.tif" "$WORK/prism" --patch-size 65 "${texture[@]}" >/dev/null 2>&1
"$VSM" import "$DATA/jacksboro_fault_dem.tif" "$WORK/jack" --patch-size 65 "${texture[@]}" \
  >/dev/null 2>&1
"$VSM" merge "$WORK/prism" "$WORK/jack" --out "$WORK/merged" >/dev/null 2>&1
"$VSM" import "$DATA/PRISMelevation.tif" "$WORK/prism-default" "${texture[@]}" >/dev/null 2>&1
{
  echo "# tests/bench/glb_bench.sh on $(date -u +%Y-%m-%dT%H:%MZ), $(nproc) cores"
  echo "# $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//'), meshoptimizer $(dpkg-query -W -f='${Version}' libmeshoptimizer-dev 2>/dev/null || echo '?')"
  echo "# geometry = GLB bytes without the embedded PNG texture (JSON chunk, vertex and index data)"
  "$BUILD/tests/bench/glb_bench" "$WORK/prism" "$WORK/merged" "$WORK/prism-default" --repeat 15 |
    sed "s|$WORK/||"
} | tee "$OUT"
