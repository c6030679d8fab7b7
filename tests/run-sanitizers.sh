#!/usr/bin/env bash
# Builds and runs the tests under sanitizers: every test under AddressSanitizer +
# UndefinedBehaviorSanitizer (build-asan/), the concurrency tests under ThreadSanitizer
# (build-tsan/). Usage: tests/run-sanitizers.sh [address|thread]  (default: both)
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
deploy/install-deps.sh
which=${1:-both}
if [[ $which == address || $which == both ]]; then
  VSM_BUILD_DIR=build-asan deploy/build.sh -DCMAKE_BUILD_TYPE=Debug -DVSM_SANITIZE=address
  ASAN_OPTIONS=detect_leaks=0 UBSAN_OPTIONS=print_stacktrace=1 \
    ctest --test-dir build-asan --output-on-failure --parallel "$(nproc)" --timeout 1800
fi
if [[ $which == thread || $which == both ]]; then
  # Also for the build: test discovery runs the test binaries.
  export TSAN_OPTIONS="halt_on_error=1 suppressions=$ROOT/tests/tsan.supp"
  VSM_BUILD_DIR=build-tsan deploy/build.sh -DCMAKE_BUILD_TYPE=RelWithDebInfo -DVSM_SANITIZE=thread
  ctest --test-dir build-tsan --output-on-failure -R 'Cache|Concurrent'
fi
