#!/usr/bin/env bash
# The demo's set-up, everything deploy/demo.sh does before it starts vsmd: install and build
# (Release), import the bundled real DEMs into OPC models (once each) and build the browser
# viewer. tests/integration/demo_viewer_test.py runs exactly this into a temporary directory with
# --no-build (its build directory is the tests' own) and starts vsmd on it as demo.sh does.
#
#   <demo>/models/PRISMelevation       PRISM's coarse DEM of the US with the NASA image draped over it
#   <demo>/models/jacksboro_fault_dem  the detail DEM of the Jacksboro fault (Tennessee), no image
#   <demo>/viewer                      the viewer (client-examples/web/build.sh) for --viewer-dir
#
# A model is imported only when missing: a merge from the viewer changes PRISMelevation in place,
# and stays (rm -rf <demo>/models to start again). The viewer's npm packages are installed once
# into <build>/viewer.npm and never fetched again while there (the demo runs offline after its
# first run).
#
#   --no-build     use the binaries in VSM_BUILD_DIR as they are (no install, no cmake)
#   VSM_DATA       the shared data (default ../shared/data beside the checkout)
#   VSM_BUILD_DIR  the build directory (default build/)
#   VSM_DEMO_DIR   where models and viewer go (default demo/ in the checkout)
#   VSM_NPM_PREFIX the npm packages of the viewer (default <build>/viewer.npm)
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
DATA=${VSM_DATA:-$ROOT/../shared/data}
BUILD=${VSM_BUILD_DIR:-build}
DEMO=${VSM_DEMO_DIR:-$ROOT/demo}
NPM_PREFIX=${VSM_NPM_PREFIX:-$BUILD/viewer.npm}
case ${1:-} in
  "") build=true ;;
  --no-build) build=false ;;
  *) echo "demo-setup.sh: unknown argument '$1' (--no-build)" >&2; exit 2 ;;
esac

if $build; then
  deploy/install-deps.sh
  # Warnings are not errors here (the test command turns them on): a build directory configured
  # by it must not make the demo fail on a compiler false positive of -O3.
  VSM_BUILD_DIR=$BUILD deploy/build.sh -DCMAKE_BUILD_TYPE=Release -DVSM_WERROR=OFF
fi
VSM=$BUILD/server/cli/vsm

mkdir -p "$DEMO/models"
import_once() {  # name, extra import arguments
  local name=$1
  shift
  if [[ ! -d $DEMO/models/$name ]]; then
    "$VSM" import "$DATA/$name.tif" "$DEMO/models/$name" "$@"
    "$VSM" validate "$DEMO/models/$name"
  fi
  "$VSM" info "$DEMO/models/$name"
  echo
}
import_once PRISMelevation --texture "$DATA/conus_visible_earth.tif"
import_once jacksboro_fault_dem

client-examples/web/build.sh "$DEMO/viewer" --npm-prefix "$NPM_PREFIX"
