#!/bin/sh
# Installs npm packages at pinned versions into <prefix>/node_modules, once: a package already
# present at its pinned version is not fetched again, so later runs need no network. What the
# test tools' installers share (tests/contract/install-contract-tools.sh,
# tests/integration/install-web-tools.sh); their messages start with <label>.
# Needs node and npm (Debian 12: apt-get install nodejs npm).
# Usage: install-npm-pinned.sh <label> <prefix> <project name> <name@version>...
set -eu
label=$1
prefix=$2
project=$3
shift 3
for tool in node npm; do
  if ! command -v "$tool" >/dev/null 2>&1; then
    echo "$label: '$tool' not found (Debian: apt-get install nodejs npm)" >&2
    exit 1
  fi
done
missing=""
for p in "$@"; do
  name=${p%@*}
  version=${p##*@}
  if [ -f "$prefix/node_modules/$name/package.json" ] &&
    [ "$(node -p "require('$prefix/node_modules/$name/package.json').version")" = "$version" ]; then
    echo "$label: $p present in $prefix"
  else
    missing="$missing $p"
  fi
done
if [ -n "$missing" ]; then
  mkdir -p "$prefix"
  # A package.json of our own keeps npm from walking up into a parent project.
  [ -f "$prefix/package.json" ] || printf '{"name": "%s", "private": true}\n' "$project" >"$prefix/package.json"
  # shellcheck disable=SC2086
  npm install --prefix "$prefix" --no-audit --no-fund --loglevel=error $missing
  echo "$label: installed$missing in $prefix"
fi
