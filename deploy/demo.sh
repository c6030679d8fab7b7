#!/usr/bin/env bash
# The main job on a fresh Debian 12 machine: install, build (Release), import the bundled real
# DEMs (PRISM with the NASA image, Jacksboro) and build the browser viewer (deploy/demo-setup.sh),
# then serve them and the viewer with vsmd on 127.0.0.1:8080 in the foreground (Ctrl-C or SIGTERM
# stops it cleanly). Prints the one URL to open: the viewer on the textured PRISM, whose merge
# button merges Jacksboro into it (POST /v1/jobs) while the page follows along.
#
#   VSM_DATA    the shared data (default ../shared/data beside the checkout)
#   VSM_LISTEN  where vsmd listens (default 127.0.0.1:8080)
#   VSM_TOKEN   bearer token for writes (default none: writes are open, on loopback only); the
#               viewer's merge button asks for it
#   VSM_BUILD_DIR  the build directory (default build/)
#   VSM_DEMO_DIR   models and viewer (default demo/)
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
LISTEN=${VSM_LISTEN:-127.0.0.1:8080}
TOKEN=${VSM_TOKEN:-}
BUILD=${VSM_BUILD_DIR:-build}
DEMO=${VSM_DEMO_DIR:-$ROOT/demo}
cd "$ROOT"

VSM_BUILD_DIR=$BUILD VSM_DEMO_DIR=$DEMO deploy/demo-setup.sh

URL=http://$LISTEN
AUTH=""
[[ -n $TOKEN ]] && AUTH=" -H 'Authorization: Bearer $TOKEN'"
cat <<EOF2
vsmd will serve $DEMO/models on $URL. From another shell:

  curl $URL/v1/models
  curl $URL/v1/models/PRISMelevation
  curl '$URL/v1/models/PRISMelevation/hierarchy?depth=1'
  curl $URL/v1/models/PRISMelevation/patches/0_0_0
  curl -N $URL/v1/events                    # job progress and publications as they happen
  curl $URL/v1/jobs
  curl $URL/metrics

  VSM_URL=$URL${TOKEN:+ VSM_TOKEN=$TOKEN} client-examples/curl.sh
  python3 client-examples/python/vsm_client.py --url $URL tour
  $BUILD/client-examples/cpp/vsm_client_example --port ${LISTEN##*:}

Merge Jacksboro into PRISM with the viewer's merge button${TOKEN:+ (it asks for the token)}, or:

  curl -X POST$AUTH -H 'Content-Type: application/json' \\
       -d '{"type": "merge", "target": "PRISMelevation", "source": "jacksboro_fault_dem"}' \\
       $URL/v1/jobs

Stop it with Ctrl-C.
EOF2
# vsmd in the background only until it listens, so that the viewer's URL is the last thing
# printed; then the script waits for it and passes SIGTERM and Ctrl-C on.
PORT_FILE=$DEMO/vsmd.port
rm -f "$PORT_FILE"
FLAGS=(--listen "$LISTEN" --data-root "$DEMO/models" --viewer-dir "$DEMO/viewer"
       --port-file "$PORT_FILE")
[[ -n $TOKEN ]] && FLAGS+=(--token "$TOKEN")
"$BUILD/server/vsmd" "${FLAGS[@]}" &
VSMD_PID=$!
trap 'kill -TERM "$VSMD_PID" 2>/dev/null || true' TERM INT
while [[ ! -s $PORT_FILE ]]; do
  kill -0 "$VSMD_PID" 2>/dev/null || { wait "$VSMD_PID"; exit $?; }
  sleep 0.1
done
cat <<EOF2

Open the viewer: PRISM with the NASA image; relief, level of detail, height, fly to Jacksboro,
and the button that merges Jacksboro into it:

  $URL/viewer/?model=PRISMelevation&mode=texture&merge=jacksboro_fault_dem

EOF2
# wait returns early when a trapped signal arrives: wait again until vsmd has exited.
status=0
while kill -0 "$VSMD_PID" 2>/dev/null; do
  wait "$VSMD_PID" || status=$?
done
exit "$status"
