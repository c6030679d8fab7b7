#!/bin/sh
# Installs the npm tools of the contract checks into <prefix>/node_modules, once, at pinned
# versions: Redocly CLI (lints proto/openapi.yaml, ctest contract.lint), Ajv with ajv-formats (the
# JSON Schema 2020-12 validator that checks vsmd's live answers against the contract's schemas,
# ctest contract.live) and yaml (reads the contract as YAML 1.2, as Redocly does). A package
# already present at its pinned version is not fetched again, so later runs need no network.
# Needs node and npm (Debian 12: apt-get install nodejs npm).
# Usage: install-contract-tools.sh <prefix>    (e.g. <build>/contract-tools)
set -eu
prefix=${1:?usage: install-contract-tools.sh <prefix>}
PACKAGES="@redocly/cli@2.77.0 ajv@8.20.0 ajv-formats@3.0.1 yaml@2.9.1"
for tool in node npm; do
  if ! command -v "$tool" >/dev/null 2>&1; then
    echo "install-contract-tools: '$tool' not found (Debian: apt-get install nodejs npm)" >&2
    exit 1
  fi
done
missing=""
for p in $PACKAGES; do
  name=${p%@*}
  version=${p##*@}
  if [ -f "$prefix/node_modules/$name/package.json" ] &&
    [ "$(node -p "require('$prefix/node_modules/$name/package.json').version")" = "$version" ]; then
    echo "install-contract-tools: $p present in $prefix"
  else
    missing="$missing $p"
  fi
done
if [ -n "$missing" ]; then
  mkdir -p "$prefix"
  # A package.json of our own keeps npm from walking up into a parent project.
  [ -f "$prefix/package.json" ] ||
    printf '{"name": "vsm-contract-tools", "private": true}\n' >"$prefix/package.json"
  # shellcheck disable=SC2086
  npm install --prefix "$prefix" --no-audit --no-fund --loglevel=error $missing
  echo "install-contract-tools: installed$missing in $prefix"
fi
