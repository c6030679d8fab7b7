#!/usr/bin/env bash
# A walk through vsmd's HTTP API with curl (and jq for reading JSON), against a running daemon:
#
#   client-examples/curl.sh [MODEL [DETAIL]]
#
#   VSM_URL    the daemon (default http://127.0.0.1:8080)
#   VSM_TOKEN  the bearer token for writes (vsmd --token); only the merge step needs it
#   MODEL      the model to read (default: the first one listed); with DETAIL, the merge target
#   DETAIL     a second model to merge into MODEL as a job (no merge step without it)
#
# Every step prints the request it makes and what came back. Exits non-zero at the first answer
# that is not what the API promises (see proto/openapi.yaml).
set -euo pipefail

URL=${VSM_URL:-http://127.0.0.1:8080}
TOKEN=${VSM_TOKEN:-}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT

step() { printf '\n== %s\n' "$*"; }
show() { printf '$ %s\n' "$*" >&2; }  # to stderr: stdout may be piped into jq
# GET a JSON resource, fail on a non-2xx status (curl prints the JSON error body).
get() {
  show "curl -sS --fail-with-body $URL$1"
  curl -sS --fail-with-body "$URL$1"
}

step "liveness and readiness"
get /healthz | jq -c .
get /readyz | jq -c .

step "the open models"
get /v1/models | jq -c '.models[] | {id, version, grid_size, depth, patches, leaves}'
MODEL=${1:-$(curl -sS --fail-with-body "$URL/v1/models" | jq -r '.models[0].id // empty')}
DETAIL=${2:-}
if [[ -z $MODEL ]]; then
  echo "no model is open: start vsmd with --data-root holding an OPC directory" >&2
  exit 1
fi

step "summary of '$MODEL' (bounds in ECEF metres, one line per level)"
get "/v1/models/$MODEL" >"$WORK/summary.json"
jq -c '{id, version, depth, patches, leaves, resolution}' "$WORK/summary.json"
jq -c '.levels[] | {depth, patches, leaves, resolution}' "$WORK/summary.json"

step "the hierarchy: the root and its children"
get "/v1/models/$MODEL/hierarchy?depth=1" |
  jq -c '.root | {key, leaf, child_count, children: [.children[]?.key]}'

step "a leaf patch: the middle one of the whole tree"
get "/v1/models/$MODEL/hierarchy" >"$WORK/tree.json"
LEAF=$(jq -r '[.root | recurse(.children[]?) | select(.leaf)] | .[length / 2 | floor].key' \
  "$WORK/tree.json")
echo "leaf: $LEAF"

step "its metadata (the ETag names the patch version)"
show "curl -sS -D headers $URL/v1/models/$MODEL/patches/$LEAF"
curl -sS --fail-with-body -D "$WORK/meta.headers" "$URL/v1/models/$MODEL/patches/$LEAF" |
  jq -c '{key, depth, version, grid_size, resolution, parent, children}'
ETAG=$(tr -d '\r' <"$WORK/meta.headers" | sed -n 's/^[Ee][Tt][Aa][Gg]: //p')
echo "etag: $ETAG"

step "its positions: .aara bytes (13-byte header: 0x03 'V3f' 0x02, int32 columns, int32 rows)"
show "curl -sS -D headers -o positions.aara $URL/v1/models/$MODEL/patches/$LEAF/positions"
curl -sS --fail-with-body -D "$WORK/pos.headers" -o "$WORK/positions.aara" \
  "$URL/v1/models/$MODEL/patches/$LEAF/positions"
tr -d '\r' <"$WORK/pos.headers" | grep -i -E '^(content-type|content-length|etag|cache-control|x-vsm-)'
BYTES=$(stat -c %s "$WORK/positions.aara")
TYPE=$(dd if="$WORK/positions.aara" bs=1 skip=1 count=3 status=none)
read -r COLS ROWS < <(od -A n -t d4 -j 5 -N 8 --endian=little "$WORK/positions.aara")
echo "positions: $BYTES bytes, type $TYPE, $COLS x $ROWS vertices"
if [[ $TYPE != V3f || $BYTES -ne $((13 + COLS * ROWS * 12)) ]]; then
  echo "positions: not a V3f grid of $COLS x $ROWS" >&2
  exit 1
fi

step "the same again with If-None-Match: 304, no body"
show "curl -sS -H 'If-None-Match: $ETAG' $URL/v1/models/$MODEL/patches/$LEAF/positions"
read -r STATUS SIZE < <(curl -sS -o /dev/null -w '%{http_code} %{size_download}\n' \
  -H "If-None-Match: $ETAG" "$URL/v1/models/$MODEL/patches/$LEAF/positions")
echo "conditional GET: $STATUS, $SIZE body bytes"
[[ $STATUS == 304 ]] || exit 1

LAYER=$(curl -sS --fail-with-body "$URL/v1/models/$MODEL/patches/$LEAF" |
  jq -r '.texture.layer // empty')
if [[ -n $LAYER ]]; then
  step "its texture ($LAYER layer) as PNG, and its texture coordinates as .aara (V2f per vertex)"
  show "curl -sS -o texture.png $URL/v1/models/$MODEL/patches/$LEAF/texture"
  curl -sS --fail-with-body -o "$WORK/texture.png" "$URL/v1/models/$MODEL/patches/$LEAF/texture"
  curl -sS --fail-with-body -o "$WORK/coordinates.aara" \
    "$URL/v1/models/$MODEL/patches/$LEAF/coordinates"
  echo "texture: $(stat -c %s "$WORK/texture.png") bytes of PNG;" \
    "coordinates: $(dd if="$WORK/coordinates.aara" bs=1 skip=1 count=3 status=none)"
else
  echo "(the model has no texture; 'vsm import <dem> <out> --texture <image>' drapes one)"
fi

step "level of detail: the cut of the tree over the whole model at 4x the finest resolution"
BOX=$(jq -r '.bounds | (.min + .max) | map(tostring) | join(",")' "$WORK/summary.json")
RES=$(jq -r '.resolution.finest * 4' "$WORK/summary.json")
get "/v1/models/$MODEL/lod?box=$BOX&resolution=$RES" >"$WORK/lod.json"
jq -c '{model, version, resolution, patches: (.patches | length),
        depths: ([.patches[].key | split("_")[0] | tonumber] | unique)}' "$WORK/lod.json"

if [[ -n $DETAIL ]]; then
  step "merge '$DETAIL' into '$MODEL' as a job (writes need the token)"
  AUTH=()
  [[ -n $TOKEN ]] && AUTH=(-H "Authorization: Bearer $TOKEN")
  show "curl -sS -X POST -H 'Authorization: Bearer ...' -H 'Content-Type: application/json'" \
    "-d '{\"type\": \"merge\", \"target\": \"$MODEL\", \"source\": \"$DETAIL\"}' $URL/v1/jobs"
  curl -sS --fail-with-body -X POST "${AUTH[@]}" -H 'Content-Type: application/json' \
    -d "{\"type\": \"merge\", \"target\": \"$MODEL\", \"source\": \"$DETAIL\"}" \
    "$URL/v1/jobs" >"$WORK/job.json"
  JOB=$(jq -r .id "$WORK/job.json")
  echo "job $JOB: $(jq -r .state "$WORK/job.json")"
  show "curl -sS $URL/v1/jobs/$JOB   (every 0.2 s until final)"
  LAST=""
  while :; do
    curl -sS --fail-with-body "$URL/v1/jobs/$JOB" >"$WORK/job.json"
    LINE=$(jq -r '"\(.state) \(.stage) \(.progress * 100 | floor)%"' "$WORK/job.json")
    [[ $LINE != "$LAST" ]] && echo "  $LINE"
    LAST=$LINE
    case $(jq -r .state "$WORK/job.json") in
      succeeded | failed | cancelled) break ;;
    esac
    sleep 0.2
  done
  jq -c '{state, error, result}' "$WORK/job.json"
  STATE=$(jq -r .state "$WORK/job.json")
  echo "job $JOB $STATE"
  [[ $STATE == succeeded ]] || exit 1
  get "/v1/models/$MODEL" | jq -c '{id, version, depth, patches}'

  step "the revisions of '$MODEL': the merge made a new one; the one before can still be read"
  get "/v1/models/$MODEL/revisions" >"$WORK/revisions.json"
  jq -c '.revisions[] | {revision, parent, job, changed_patches, latest}' "$WORK/revisions.json"
  FIRST=$(jq -r '.revisions[0].revision' "$WORK/revisions.json")
  get "/v1/models/$MODEL?rev=$FIRST" | jq -c '{id, version, depth, patches}'

  LATEST=$(jq -r '.revisions[-1].revision' "$WORK/revisions.json")
  step "what the merge changed: revision $FIRST to $LATEST (metres along the surface normal)"
  get "/v1/models/$MODEL/diff?from=$FIRST&to=$LATEST" >"$WORK/diff.json"
  jq -c '.totals | {changed_patches, shared_patches, changed_area, min, max, rms}' \
    "$WORK/diff.json"
  show "curl -sS -o diff.png '$URL/v1/models/$MODEL/diff.png?from=$FIRST&to=$LATEST&size=512'"
  curl -sS --fail-with-body -D "$WORK/diff-headers.txt" -o "$WORK/diff.png" \
    "$URL/v1/models/$MODEL/diff.png?from=$FIRST&to=$LATEST&size=512"
  echo "$WORK/diff.png: $(wc -c <"$WORK/diff.png") bytes, $(grep -i '^x-vsm-diff-legend' \
    "$WORK/diff-headers.txt" | cut -d' ' -f2- | tr -d '\r')"
fi

step "memory and cache statistics"
get /v1/stats | jq -c '{budget_bytes: .memory.budget_bytes, resident_bytes: .memory.resident_bytes,
                        hits: .cache.hits, misses: .cache.misses}'
echo
echo "walk-through done"
