#!/bin/sh
# Installs the npm packages the browser check (viewer_test.py) uses into <prefix>/node_modules,
# once: playwright-core (drives Debian's /usr/bin/chromium; it downloads no browser) and the
# viewer's packages at the versions client-examples/web/build.sh pins (three, 3d-tiles-renderer,
# cesium), so that build.sh --npm-prefix <prefix> finds them (tests/install-npm-pinned.sh).
# Needs node and npm (Debian 12: apt-get install nodejs npm).
# Usage: install-web-tools.sh <prefix> <client-examples/web/build.sh>   (e.g. <build>/web-tools)
set -eu
prefix=${1:?usage: install-web-tools.sh <prefix> <build.sh>}
build=${2:?usage: install-web-tools.sh <prefix> <build.sh>}
PLAYWRIGHT=playwright-core@1.65.1
# shellcheck disable=SC2046
exec sh "$(dirname "$0")/../install-npm-pinned.sh" install-web-tools "$prefix" vsm-web-tools \
  "$PLAYWRIGHT" $(sh "$build" --packages)
