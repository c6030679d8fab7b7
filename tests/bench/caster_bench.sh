#!/usr/bin/env bash
# Benchmark (not a test): SurfaceCaster's construction and rays per second on one core for a
# 10^6-triangle B (tests/bench/caster_bench.cpp says what is measured), medians of 3, with the
# machine's load before and after. Writes tests/bench/results/caster.txt.
#   tests/bench/caster_bench.sh [build-dir]
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
BUILD=${1:-$ROOT/build}
OUT=$ROOT/tests/bench/results/caster.txt
{
  echo "# tests/bench/caster_bench.sh on $(date -u +%Y-%m-%dT%H:%MZ), $(nproc) cores, one used"
  echo "# $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//')"
  echo "# load before: $(uptime | sed 's/.*load average: //')"
  taskset -c 0 "$BUILD/tests/bench/caster_bench" --repeat 3
  echo "# load after: $(uptime | sed 's/.*load average: //')"
} | tee "$OUT"
