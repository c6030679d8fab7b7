#!/bin/sh
# Lints the API contract with Redocly CLI's recommended rules (redocly.yaml beside this script)
# and fails on any problem, warnings included (redocly itself fails on errors only).
# Offline: no telemetry, no update check. The tools come from install-contract-tools.sh.
# Usage: lint.sh <contract-tools prefix> <openapi.yaml>
set -eu
tools=${1:?usage: lint.sh <tools> <openapi.yaml>}
contract=${2:?usage: lint.sh <tools> <openapi.yaml>}
here=$(cd "$(dirname "$0")" && pwd)
redocly="$tools/node_modules/.bin/redocly"
if [ ! -x "$redocly" ]; then
  echo "lint: $redocly missing (run install-contract-tools.sh $tools)" >&2
  exit 1
fi
export REDOCLY_TELEMETRY=off REDOCLY_SUPPRESS_UPDATE_NOTICE=true NO_COLOR=1
# The findings for people, then the totals for the verdict. Node 20's deprecation banner goes to
# stderr: dropped.
"$redocly" lint --config "$here/redocly.yaml" --format stylish --max-problems 1000 "$contract" 2>/dev/null || true
totals=$("$redocly" lint --config "$here/redocly.yaml" --format json --max-problems 1000 "$contract" 2>/dev/null |
  node -e 'let s="";process.stdin.on("data",d=>s+=d).on("end",()=>{const t=JSON.parse(s).totals;
    console.log(t.errors+" "+t.warnings)})') || {
  echo "lint: redocly gave no result" >&2
  exit 1
}
# shellcheck disable=SC2086  # two numbers, split on purpose
set -- $totals
echo "lint: $1 errors, $2 warnings (Redocly CLI $("$redocly" --version 2>/dev/null), recommended rules)"
[ "$1" = 0 ] && [ "$2" = 0 ]
