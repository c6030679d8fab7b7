#!/bin/sh
# Installs the npm packages the browser check (viewer_test.py) uses into <prefix>/node_modules,
# once: playwright-core (drives Debian's /usr/bin/chromium; it downloads no browser) and the
# viewer's packages at the versions client-examples/web/build.sh pins (three, 3d-tiles-renderer,
# cesium), so that build.sh --npm-prefix <prefix> finds them.
# Needs node and npm (Debian 12: apt-get install nodejs npm).
# Usage: install-web-tools.sh <prefix> <client-examples/web/build.sh>   (e.g. <build>/web-tools)
set -eu
prefix=${1:?usage: install-web-tools.sh <prefix> <build.sh>}
build=${2:?usage: install-web-tools.sh <prefix> <build.sh>}
PLAYWRIGHT=playwright-core@1.65.1
for tool in node npm; do
  if ! command -v "$tool" >/dev/null 2>&1; then
    echo "install-web-tools: '$tool' not found (Debian: apt-get install nodejs npm)" >&2
    exit 1
  fi
done
missing=""
for p in $PLAYWRIGHT $(sh "$build" --packages); do
  name=${p%@*}
  version=${p##*@}
  if [ -f "$prefix/node_modules/$name/package.json" ] &&
    [ "$(node -p "require('$prefix/node_modules/$name/package.json').version")" = "$version" ]; then
    echo "install-web-tools: $p present in $prefix"
  else
    missing="$missing $p"
  fi
done
if [ -n "$missing" ]; then
  mkdir -p "$prefix"
  # A package.json of our own keeps npm from walking up into a parent project.
  [ -f "$prefix/package.json" ] || printf '{"name": "vsm-web-tools", "private": true}\n' >"$prefix/package.json"
  # shellcheck disable=SC2086
  npm install --prefix "$prefix" --no-audit --no-fund --loglevel=error $missing
  echo "install-web-tools: installed$missing in $prefix"
fi
