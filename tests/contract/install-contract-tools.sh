#!/bin/sh
# Installs the npm tools of the contract checks into <prefix>/node_modules, once, at pinned
# versions: Redocly CLI (lints proto/openapi.yaml, ctest contract.lint), Ajv with ajv-formats (the
# JSON Schema 2020-12 validator that checks vsmd's live answers against the contract's schemas,
# ctest contract.live) and yaml (reads the contract as YAML 1.2, as Redocly does), through
# tests/install-npm-pinned.sh: a package already present at its pinned version is not fetched
# again, so later runs need no network.
# Needs node and npm (Debian 12: apt-get install nodejs npm).
# Usage: install-contract-tools.sh <prefix>    (e.g. <build>/contract-tools)
set -eu
prefix=${1:?usage: install-contract-tools.sh <prefix>}
PACKAGES="@redocly/cli@2.77.0 ajv@8.20.0 ajv-formats@3.0.1 yaml@2.9.1"
# shellcheck disable=SC2086
exec sh "$(dirname "$0")/../install-npm-pinned.sh" install-contract-tools "$prefix" vsm-contract-tools \
  $PACKAGES
