#!/usr/bin/env bash
# The main job on a fresh Debian 12 machine: install, build, import the bundled real DEMs into OPC
# models under demo/ (once) and describe them.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
DATA=${VSM_DATA:-$ROOT/../shared/data}
cd "$ROOT"

deploy/install-deps.sh
deploy/build.sh -DCMAKE_BUILD_TYPE=Release
VSM=build/server/cli/vsm

mkdir -p demo
for name in PRISMelevation jacksboro_fault_dem; do
  if [[ ! -d demo/$name ]]; then
    "$VSM" import "$DATA/$name.tif" "demo/$name"
  fi
  "$VSM" validate "demo/$name"
  "$VSM" info "demo/$name"
  echo
done
