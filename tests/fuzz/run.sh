#!/usr/bin/env bash
# Builds the fuzz targets (clang-14, libFuzzer + ASan + UBSan, into $VSM_FUZZ_BUILD_DIR, default
# build-fuzz/) and runs each for SECONDS seconds, one after the other:
#
#   tests/fuzz/run.sh SECONDS [TARGET...]     targets: aara opc_xml opc_index texture http json_body
#                                             lod_query config (default: all)
#
# Each target first replays tests/fuzz/regressions/<target>/ (inputs that once crashed it) and
# its seed corpus tests/fuzz/corpus/<target>/ (real files and requests); SECONDS=0 stops there.
# Then it fuzzes from the seeds plus what earlier runs in the same build dir found (kept in
# <build>/corpus/<target>/, never written back to the source tree). A crash stops the script
# with exit status 1, naming the input libFuzzer saved: make it a regression test by copying it
# into tests/fuzz/regressions/<target>/ with the fix.
#
# Environment: VSM_FUZZ_BUILD_DIR; VSM_FUZZ_NICE=19 runs the fuzzers at low priority;
# VSM_FUZZ_RUNS=N also stops a target after N executions (the long run: SECONDS=3600 and
# VSM_FUZZ_RUNS=10000000, whichever comes first); VSM_FUZZ_TIMEOUT=S (default 10) is the wall time
# one input may take: raise it for low-priority runs on a busy machine, where a fuzzer waiting for
# a core looks like a slow input.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
HERE="$ROOT/tests/fuzz"
SECONDS_EACH=${1:?usage: tests/fuzz/run.sh SECONDS [TARGET...]}
shift
ALL=(aara opc_xml opc_index texture http json_body lod_query config)
TARGETS=("${@:-${ALL[@]}}")
BUILD=${VSM_FUZZ_BUILD_DIR:-$ROOT/build-fuzz}
CXX=${VSM_FUZZ_CXX:-clang++-14}

if ! command -v "$CXX" >/dev/null; then
  echo "fuzz: $CXX is missing (deploy/install-deps.sh installs clang-14)" >&2
  exit 1
fi
start=$(date +%s)
if [[ ! -f "$BUILD/build.ninja" ]]; then
  cmake -S "$ROOT" -B "$BUILD" -G Ninja -DVSM_FUZZ=ON -DCMAKE_BUILD_TYPE=Debug \
    -DCMAKE_CXX_COMPILER="$CXX" >/dev/null
fi
cmake --build "$BUILD" --parallel "$(nproc)"
echo "fuzz: build $(($(date +%s) - start)) s"

status=0
for target in "${TARGETS[@]}"; do
  binary="$BUILD/tests/fuzz/fuzz_$target"
  if [[ ! -x "$binary" ]]; then
    echo "fuzz: no target '$target' (one of: ${ALL[*]})" >&2
    exit 2
  fi
  # Every input that once crashed a target, and every seed, must pass.
  replay=()
  for dir in "$HERE/regressions/$target" "$HERE/corpus/$target"; do
    if [[ -d "$dir" ]]; then
      mapfile -t -O "${#replay[@]}" replay < <(find "$dir" -type f | sort)
    fi
  done
  export LSAN_OPTIONS="suppressions=$HERE/lsan.supp:print_suppressions=0"
  if ((${#replay[@]})) && ! "$binary" -runs=1 "${replay[@]}" >"$BUILD/replay-$target.log" 2>&1; then
    echo "fuzz: $target: a regression or seed input fails (see $BUILD/replay-$target.log):" >&2
    grep -E "Running:|SUMMARY|property|what\(\)" "$BUILD/replay-$target.log" | tail -5 >&2
    status=1
    continue
  fi
  echo "fuzz: $target: ${#replay[@]} regression and seed inputs pass"
  if ((SECONDS_EACH == 0)); then
    continue
  fi
  work="$BUILD/corpus/$target"
  artifacts="$BUILD/artifacts/$target"
  mkdir -p "$work" "$artifacts"
  log="$BUILD/fuzz-$target.log"
  target_start=$(date +%s)
  # -malloc_limit_mb: one allocation above 512 MiB is a bug (an unbounded size from input).
  if ! nice -n "${VSM_FUZZ_NICE:-0}" "$binary" "$work" "$HERE/corpus/$target" \
    -max_total_time="$SECONDS_EACH" -runs="${VSM_FUZZ_RUNS:--1}" \
    -timeout="${VSM_FUZZ_TIMEOUT:-10}" \
    -rss_limit_mb=2048 -malloc_limit_mb=512 -max_len=65536 -print_final_stats=1 \
    -print_funcs=0 -print_pcs=0 \
    -artifact_prefix="$artifacts/" >"$log" 2>&1; then
    echo "fuzz: $target: CRASH (log $log):" >&2
    grep -E "SUMMARY|property|what\(\)|Test unit written" "$log" | tail -5 >&2
    status=1
    continue
  fi
  runs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log")
  rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log")
  cov=$(grep -oE "cov: [0-9]+ ft: [0-9]+" "$log" | tail -1)
  echo "fuzz: $target: ${runs:-?} executions in $(($(date +%s) - target_start)) s" \
    "(${rate:-?}/s), ${cov:-cov: ?}, corpus $(find "$work" -type f | wc -l) inputs, no crash"
done
echo "fuzz: total $(($(date +%s) - start)) s"
exit "$status"
