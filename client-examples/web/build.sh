#!/bin/sh
# Builds the browser viewer (index.html, main.js and the modules it imports from js/,
# maplibre.html with MapLibre GL JS, and, with --cesium, cesium.html and terrain.html) into
# <out-dir>, with the modules they import vendored from npm into <out-dir>/vendor, so that vsmd
# serves it with no network access at runtime (vsmd --viewer-dir <out-dir>, then open
# /viewer/?model=ID).
# No bundler: index.html maps the bare imports ("three", "3d-tiles-renderer") to the vendored files
# with an import map.
#
# The npm packages are installed (pinned versions, once) into an npm prefix of the build, never
# into the source tree: <out-dir>.npm unless --npm-prefix DIR names another (the tests share one).
# Needs node and npm (Debian 12: apt-get install nodejs npm).
#
# Usage: build.sh <out-dir> [--npm-prefix DIR] [--cesium]
#        build.sh --packages         (prints the pinned npm packages)
set -eu

THREE=three@0.187.0
TILES=3d-tiles-renderer@0.5.3
CESIUM=cesium@1.140.0
# The last major version with a UMD build that carries its worker (6.x ships ES modules only).
MAPLIBRE=maplibre-gl@5.24.1

if [ "${1:-}" = "--packages" ]; then
  echo "$THREE $TILES $CESIUM $MAPLIBRE"
  exit 0
fi
out=${1:?usage: build.sh <out-dir> [--npm-prefix DIR] [--cesium]}
shift
prefix=$out.npm
cesium=false
while [ $# -gt 0 ]; do
  case $1 in
    --npm-prefix) prefix=${2:?--npm-prefix needs a directory}; shift 2 ;;
    --cesium) cesium=true; shift ;;
    *) echo "build.sh: unknown argument '$1'" >&2; exit 2 ;;
  esac
done
src=$(cd "$(dirname "$0")" && pwd)
for tool in node npm; do
  if ! command -v "$tool" >/dev/null 2>&1; then
    echo "build.sh: '$tool' not found (Debian: apt-get install nodejs npm)" >&2
    exit 1
  fi
done

# "name@version" -> installed in $prefix at that version?
present() {
  name=${1%@*}
  version=${1##*@}
  [ -f "$prefix/node_modules/$name/package.json" ] &&
    [ "$(node -p "require('$prefix/node_modules/$name/package.json').version")" = "$version" ]
}
wanted="$THREE $TILES $MAPLIBRE"
if $cesium; then wanted="$wanted $CESIUM"; fi
missing=""
for p in $wanted; do
  present "$p" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  mkdir -p "$prefix"
  # A package.json of our own keeps npm from walking up into a parent project.
  [ -f "$prefix/package.json" ] || printf '{"name": "vsm-viewer-build", "private": true}\n' >"$prefix/package.json"
  # shellcheck disable=SC2086
  npm install --prefix "$prefix" --no-audit --no-fund --loglevel=error $missing
fi
nm=$prefix/node_modules

# A fresh tree next to the old one, swapped in at the end: a running vsmd never sees half a build.
mkdir -p "$(dirname "$out")"
tmp=$out.tmp.$$
rm -rf "$tmp"
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$tmp/vendor/three/build" "$tmp/vendor/three/examples/jsm/loaders" \
  "$tmp/vendor/three/examples/jsm/controls" "$tmp/vendor/three/examples/jsm/utils" \
  "$tmp/vendor/three/examples/jsm/libs" \
  "$tmp/vendor/3d-tiles-renderer/build"
cp "$src/index.html" "$src/main.js" "$tmp/"
mkdir -p "$tmp/js"
cp "$src"/js/*.js "$tmp/js/"
cp "$nm/three/LICENSE" "$tmp/vendor/three/"
cp "$nm/three/build/three.module.js" "$nm/three/build/three.core.js" "$tmp/vendor/three/build/"
for f in loaders/GLTFLoader.js controls/OrbitControls.js controls/FlyControls.js \
  utils/BufferGeometryUtils.js \
  utils/SkeletonUtils.js libs/meshopt_decoder.module.js; do
  cp "$nm/three/examples/jsm/$f" "$tmp/vendor/three/examples/jsm/$f"
done
cp "$nm/3d-tiles-renderer/LICENSE" "$tmp/vendor/3d-tiles-renderer/"
# The three.js entry point and the chunks it imports (their names carry a content hash).
cp "$nm/3d-tiles-renderer/build/index.three.js" "$tmp/vendor/3d-tiles-renderer/build/"
for f in "$nm"/3d-tiles-renderer/build/renderer-*.js; do
  cp "$f" "$tmp/vendor/3d-tiles-renderer/build/"
done
cp "$src/maplibre.html" "$tmp/"
mkdir -p "$tmp/vendor/maplibre-gl"
cp "$nm/maplibre-gl/LICENSE.txt" "$nm/maplibre-gl/dist/maplibre-gl.js" \
  "$nm/maplibre-gl/dist/maplibre-gl.css" "$tmp/vendor/maplibre-gl/"
if $cesium; then
  cp "$src/cesium.html" "$src/terrain.html" "$tmp/"
  mkdir -p "$tmp/vendor/cesium"
  cp "$nm/cesium/LICENSE.md" "$tmp/vendor/cesium/" 2>/dev/null || true
  cp -R "$nm/cesium/Build/Cesium" "$tmp/vendor/cesium/Build"
fi
rm -rf "$out"
mv "$tmp" "$out"
trap - EXIT
echo "build.sh: viewer built in $out ($wanted)"
