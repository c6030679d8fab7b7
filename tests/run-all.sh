#!/usr/bin/env bash
# Installs what is needed, builds with warnings as errors and runs the whole test suite.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"

deploy/install-deps.sh
VSM_BUILD_DIR=${VSM_BUILD_DIR:-build} deploy/build.sh -DCMAKE_BUILD_TYPE=RelWithDebInfo -DVSM_WERROR=ON
tests/check-format.sh
ctest --test-dir "${VSM_BUILD_DIR:-build}" --output-on-failure --parallel "$(nproc)" --timeout 900
