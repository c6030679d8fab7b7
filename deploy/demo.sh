#!/usr/bin/env bash
# The main job on a fresh Debian 12 machine: install, build (Release), import the bundled real DEMs
# into OPC models under demo/ (once), then serve them with vsmd on 127.0.0.1:8080 in the
# foreground (Ctrl-C or SIGTERM stops it cleanly).
#
#   VSM_DATA    the shared data (default ../shared/data beside the checkout)
#   VSM_LISTEN  where vsmd listens (default 127.0.0.1:8080)
#   VSM_TOKEN   bearer token for writes (default none: writes are open, on loopback only)
#   VSM_BUILD_DIR  the build directory (default build/)
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
DATA=${VSM_DATA:-$ROOT/../shared/data}
LISTEN=${VSM_LISTEN:-127.0.0.1:8080}
TOKEN=${VSM_TOKEN:-}
cd "$ROOT"

deploy/install-deps.sh
# Warnings are not errors here (the test command turns them on): a build directory configured by
# it must not make the demo fail on a compiler false positive of -O3.
deploy/build.sh -DCMAKE_BUILD_TYPE=Release -DVSM_WERROR=OFF
BUILD=${VSM_BUILD_DIR:-build}
VSM=$BUILD/server/cli/vsm
VSMD=$BUILD/server/vsmd

mkdir -p demo
for name in PRISMelevation jacksboro_fault_dem; do
  if [[ ! -d demo/$name ]]; then
    "$VSM" import "$DATA/$name.tif" "demo/$name"
    "$VSM" validate "demo/$name"
  fi
  "$VSM" info "demo/$name"
  echo
done

URL=http://$LISTEN
AUTH=""
[[ -n $TOKEN ]] && AUTH=" -H 'Authorization: Bearer $TOKEN'"
cat <<EOF
vsmd will serve demo/ on $URL. Try, from another shell:

  curl $URL/v1/models
  curl $URL/v1/models/PRISMelevation
  curl '$URL/v1/models/PRISMelevation/hierarchy?depth=1'
  curl $URL/v1/models/PRISMelevation/patches/0_0_0
  curl -o root.aara $URL/v1/models/PRISMelevation/patches/0_0_0/positions
  curl -X POST$AUTH -H 'Content-Type: application/json' \\
       -d '{"type": "merge", "target": "PRISMelevation", "source": "jacksboro_fault_dem"}' \\
       $URL/v1/jobs
  curl $URL/v1/jobs
  curl $URL/metrics

  VSM_URL=$URL${TOKEN:+ VSM_TOKEN=$TOKEN} client-examples/curl.sh
  python3 client-examples/python/vsm_client.py --url $URL tour
  $BUILD/client-examples/cpp/vsm_client_example --port ${LISTEN##*:}

Stop it with Ctrl-C.

EOF
FLAGS=(--listen "$LISTEN" --data-root "$ROOT/demo")
[[ -n $TOKEN ]] && FLAGS+=(--token "$TOKEN")
exec "$VSMD" "${FLAGS[@]}"
