#!/usr/bin/env bash
# Installs the Debian 12 packages VSM needs to build, run and test. Idempotent; run as root or with
# sudo available.
set -euo pipefail

SUDO=""
if [[ $(id -u) -ne 0 ]]; then
  SUDO="sudo"
fi

PACKAGES=(
  build-essential cmake ninja-build pkg-config git
  libboost-dev libeigen3-dev libpcl-dev libpugixml-dev libopenimageio-dev nlohmann-json3-dev
  libgtest-dev libgdal-dev zlib1g-dev libtiff-dev
  # the 3D Tiles GLBs' EXT_meshopt_compression codecs (encoder in vsmd, decoder in the unit tests)
  libmeshoptimizer-dev
  # tests: gdaladdo (benchmark), GDAL's Python bindings for the independent import checker,
  # a comma-decimal locale (numbers in XML must not follow the locale), clang-format
  gdal-bin python3 python3-gdal python3-numpy locales clang-format
  # the fuzz targets (tests/fuzz): clang 14 and its libFuzzer runtime (libclang_rt.fuzzer)
  clang-14 libclang-rt-14-dev
  # the curl walk-through of the daemon's API (client-examples/curl.sh, run by the tests)
  curl jq
  # the browser check of the viewer and CesiumJS in headless Chromium (viewer_test.py,
  # demo_viewer_test.py); node and npm for the viewer's build follow below
  chromium
  # the consistency check of the deploy files (tests/deploy/deploy_files_test.py) parses YAML
  python3-yaml
  # the cluster on loopback (deploy/local-cluster.sh, tests/integration/cluster_test.py): etcd for
  # the writer leases, nginx (with SSL and HTTP/2) in front, openssl for its certificate
  etcd-server nginx-light openssl
)

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "installing: ${missing[*]}"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

# node and npm for the viewer's build (client-examples/web/build.sh, deploy/demo-setup.sh) and the
# tests' npm tools (tests/integration/install-node-tools.sh: gltf-validator). Debian's packages
# only when no node is installed: NodeSource's nodejs bundles npm and conflicts
# with Debian's npm package.
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
  echo "installing: nodejs npm"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends nodejs npm
fi

if ! locale -a 2>/dev/null | grep -qi '^de_DE\.utf-\?8$'; then
  $SUDO sed -i 's/^# *de_DE.UTF-8 UTF-8/de_DE.UTF-8 UTF-8/' /etc/locale.gen
  $SUDO locale-gen >/dev/null
fi
