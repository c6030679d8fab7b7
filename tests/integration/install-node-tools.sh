#!/bin/sh
# Installs the npm tools the integration tests use into <prefix>/node_modules, once: Khronos'
# glTF validator (npm `gltf-validator`, pinned: every release is a 2.0.0-dev prerelease) and
# meshoptimizer's JavaScript decoder (npm `meshoptimizer`, the version of Debian's
# libmeshoptimizer-dev), with which validate_gltf.js decodes EXT_meshopt_compression GLBs so that
# the validator sees their data.
# Needs node and npm (Debian 12: apt-get install nodejs npm).
# Usage: install-node-tools.sh <prefix>    (e.g. <build>/node-tools)
set -eu
prefix=${1:?usage: install-node-tools.sh <prefix>}
for tool in node npm; do
  if ! command -v "$tool" >/dev/null 2>&1; then
    echo "install-node-tools: '$tool' not found (Debian: apt-get install nodejs npm)" >&2
    exit 1
  fi
done
if [ -f "$prefix/node_modules/gltf-validator/package.json" ] &&
  [ -f "$prefix/node_modules/meshoptimizer/package.json" ]; then
  echo "install-node-tools: gltf-validator $(node -p "require('$prefix/node_modules/gltf-validator/package.json').version") present in $prefix"
  exit 0
fi
mkdir -p "$prefix"
# A package.json of our own keeps npm from walking up into a parent project.
[ -f "$prefix/package.json" ] || printf '{"name": "vsm-node-tools", "private": true}\n' >"$prefix/package.json"
npm install --prefix "$prefix" --no-audit --no-fund --loglevel=error gltf-validator@2.0.0-dev.3.10 \
  meshoptimizer@0.18.1
echo "install-node-tools: gltf-validator $(node -p "require('$prefix/node_modules/gltf-validator/package.json').version") installed in $prefix"
