#!/usr/bin/env bash
# Benchmark (not a test): how the costs of issue 31 grow with the number of patches. Models of
# ~10^3 and ~10^5 (and, with VSM_BENCH_DEPTHS, more) patches in the same run.
#
# The models are SYNTHETIC, written by scale_gen (tests/bench/scale_gen.cpp): full quadtrees of
# 17 x 17 patches, no textures, 3" spacing, one analytic surface; depth 5 is 1,365 patches, 8 is
# 87,381 (the issue's 4097^2 model), 10 is 1,398,101. The detail merged is scale_gen's depth 2 at
# 0.75" from a corner inside both (21 patches, two levels finer): a small merge.
#
# For each model, all on this machine (2 shared cores: the load average is printed):
#   info-full   `vsm info` without the index (Patches/patchhierarchy.vsmidx moved away): the full
#               read of every Patch.xml, as before the index; median of 3 runs;
#   info        `vsm info` with the index (scale_gen writes it, as a publish does); median of 5;
#   ready-full, ready   vsmd started on a data root holding the model (and the detail), without
#               and with the index: seconds from exec to the port file (it opens the models before
#               it listens), and VmRSS then (empty cache; --memory-budget 64MiB up to depth 8,
#               1GiB beyond: the budget holds the models' metadata, ~200 bytes a patch, and 64 MiB
#               leaves no room beside 1.4 million patches); "RSS settled", printed below the row,
#               is the writer's a second after its replica started (the image codec it loads just
#               after ready is in then);
#   merge1..N   a merge job (POST /v1/jobs, detail into the model) end to end, by the daemon's
#               clock: from its created_at (the POST's arrival) to its finished_at, then VmRSS;
#               N = VSM_BENCH_MERGES (3). The bench polls the job every 20 ms with curl and grep
#               (a Python per poll would add 0.3 s); the time from the POST to the poll that saw
#               it succeed is printed below the row ("as polled"): it adds one curl and a sleep,
#               30-80 ms where starting a process is slow;
#   follow      a second vsmd on the same data root (read-only: the first holds the writer lock)
#               follows each publish; seconds from the job's finished_at to the replica answering the new
#               version (polled every 20 ms; the replica looks every 500 ms, so this includes up
#               to 0.5 s of waiting: the reopen itself is in the replica's log line, printed below the row);
#   layer, tileset   the first GET of the last merge's version's terrain layer.json and 3D Tiles
#               tileset.json (curl's total time). As a viewer following the model does, the bench
#               GETs both after opening and after each merge, so each new version's are made
#               knowing the previous version's; the first version's (made from nothing) are
#               printed below the row;
#   medians     of the merges, follows, layers and tilesets over the N merges, below the row;
#   restart     the writer started again after the merges: its first layer.json and tileset.json,
#               the layer from the footprints the first process saved (Patches/
#               vsm-terrain-footprints.bin) and the patches changed since, printed below the row.
#
#   tests/bench/scale_bench.sh [build-dir] [work-dir]
# Defaults: build/ and a temporary directory (removed afterwards; ~1.3 GB at depth 8).
# VSM_BENCH_DEPTHS (default "5 8") picks the models; VSM_BENCH_FULL=0 skips info-full and
# ready-full.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
BUILD=$(cd "${1:-$ROOT/build}" && pwd)
DEPTHS=${VSM_BENCH_DEPTHS:-5 8}
MERGES=${VSM_BENCH_MERGES:-3}
VSM=$BUILD/server/cli/vsm
VSMD=$BUILD/server/vsmd
GEN=$BUILD/tests/bench/scale_gen
for b in "$VSM" "$VSMD" "$GEN"; do
  [[ -x $b ]] || { echo "build first: $b" >&2; exit 2; }
done
if [[ -n "${2:-}" ]]; then
  WORK=$2
  mkdir -p "$WORK"
else
  WORK=$(mktemp -d)
  REMOVE_WORK=1
fi
TOKEN=bench
PIDS=()
cleanup_daemons() {
  for pid in "${PIDS[@]+"${PIDS[@]}"}"; do
    kill "$pid" 2>/dev/null || true
    wait "$pid" 2>/dev/null || true
  done
  PIDS=()
  [[ -z ${REMOVE_WORK:-} ]] || rm -rf "$WORK"
}
trap 'cleanup_daemons' ERR EXIT

now() { date +%s.%N; }
elapsed() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.3f", b - a }'; }
rss_mb() { awk '/VmRSS/ { printf "%.0f", $2 / 1024 }' "/proc/$1/status"; }
median() { sort -n | awk '{ v[NR] = $1 } END { print v[int((NR + 1) / 2)] }'; }

time_info() {  # time_info <opc> <runs>: median seconds of `vsm info`
  for _ in $(seq "$2"); do
    local t0 t1
    t0=$(now)
    "$VSM" info "$1" >/dev/null
    t1=$(now)
    elapsed "$t0" "$t1"
    echo
  done | median
}

start_vsmd() {  # start_vsmd <data-root> <tag> <budget>: sets DPID, DURL and READY (s to ready)
  local port=$WORK/$2.port
  rm -f "$port"
  local t0 t1
  t0=$(now)
  "$VSMD" --listen 127.0.0.1:0 --data-root "$1" --port-file "$port" --token "$TOKEN" \
    --memory-budget "$3" --keep-revisions 8 --log-level info >"$WORK/$2.log" 2>&1 &
  DPID=$!
  PIDS+=("$DPID")
  while [[ ! -s $port ]]; do
    kill -0 "$DPID" 2>/dev/null || { echo "vsmd died: $(tail -3 "$WORK/$2.log")" >&2; exit 1; }
    sleep 0.01
  done
  t1=$(now)
  DURL=http://127.0.0.1:$(cat "$port")
  READY=$(elapsed "$t0" "$t1")
}

stop_vsmd() {  # stop_vsmd <pid>: SIGTERM, then waits until it is gone (it holds the writer lock)
  kill "$1" 2>/dev/null || true
  wait "$1" 2>/dev/null || true
  local kept=()
  for pid in "${PIDS[@]}"; do [[ $pid == "$1" ]] || kept+=("$pid"); done
  PIDS=("${kept[@]+"${kept[@]}"}")
}

api() {  # api <url> <method> <path> [json]
  if [[ -n "${4:-}" ]]; then
    curl -sf -X "$2" -H "Authorization: Bearer $TOKEN" -H 'Content-Type: application/json' \
      -d "$4" "$1$3"
  else
    curl -sf -X "$2" -H "Authorization: Bearer $TOKEN" "$1$3"
  fi
}

# The first value of a top-level member of a compact JSON answer, without starting a Python (whose
# 0.3 s start would be most of a small merge's measured time): field <name> < json.
field() { grep -o "\"$1\":\"\?[a-z0-9]*" | head -1 | sed 's/.*:"\?//'; }
stamp() { grep -o "\"$1\":\"[0-9T:.Z-]*\"" | head -1 | cut -d'"' -f4; }  # a job's time

version_of() {  # version_of <url> <model>
  api "$1" GET "/v1/models/$2" | field version
}

derived() {  # sets layer and tileset: curl's total time for the writer's layer.json, tileset.json
  layer=$(curl -sf -o /dev/null -w '%{time_total}' -H "Authorization: Bearer $TOKEN" \
    "$wurl/v1/models/$name/terrain/layer.json" || echo failed)
  tileset=$(curl -sf -o /dev/null -w '%{time_total}' -H "Authorization: Bearer $TOKEN" \
    "$wurl/v1/models/$name/3dtiles/tileset.json" || echo failed)
}

echo "scale bench: $(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg), $(date -u +%FT%TZ)"
# The deployed units set GLIBC_TUNABLES (deploy/systemd/vsmd.service); vsmd inherits it from here.
[[ -z ${GLIBC_TUNABLES:-} ]] || echo "GLIBC_TUNABLES=$GLIBC_TUNABLES"
"$GEN" "$WORK/detail" 2 17 -98.49 33.49 0.75 >/dev/null
printf '%-8s %9s %9s %7s %9s %9s %7s %s\n' patches info-full info ready-full rss-full ready rss \
  "merges (s, RSS MB after) / follow (s) / layer, tileset (s)"
for depth in $DEPTHS; do
  name=m$depth
  budget=64MiB
  ((depth <= 8)) || budget=1GiB
  data=$WORK/data-$depth
  rm -rf "$data"
  mkdir -p "$data"
  t0=$(now)
  patches=$("$GEN" "$data/$name" "$depth" 17 -98.5 33.5 3 | cut -d' ' -f1)
  gen_s=$(elapsed "$t0" "$(now)")
  cp -r "$WORK/detail" "$data/detail"
  # The generator's writes flushed before anything is timed: else the first merge's syncfs
  # (core/durable FileSystemSync) writes back its gigabyte and is timed with it.
  sync
  idx=$data/$name/Patches/patchhierarchy.vsmidx
  # Before the index: the full read (VSM_BENCH_FULL=0 skips it: ~10 min at 10^6 patches).
  info_full=- ready_full=- rss_full=-
  if [[ ${VSM_BENCH_FULL:-1} != 0 ]]; then
    mv "$idx" "$WORK/saved.vsmidx"
    info_full=$(time_info "$data/$name" 3)
    start_vsmd "$data" full-$depth "$budget"
    ready_full=$READY
    rss_full=$(rss_mb "$DPID")
    stop_vsmd "$DPID"
    mv "$WORK/saved.vsmidx" "$idx"
  fi
  info_idx=$(time_info "$data/$name" 5)
  # With the index: the writer, then its replica.
  start_vsmd "$data" writer-$depth "$budget"
  ready=$READY
  wpid=$DPID
  wurl=$DURL
  rss=$(rss_mb "$wpid")
  start_vsmd "$data" replica-$depth "$budget"
  rpid=$DPID
  rurl=$DURL
  # Once settled: the image codec (~80 MB of OpenImageIO and what it loads) comes in on a handler
  # thread just after ready, and the writer's leftover sweep runs.
  sleep 1
  rss_settled=$(rss_mb "$wpid")
  # A viewer following the model: the first version's documents, then each new version's.
  derived
  first_docs="$layer, $tileset"
  merges=""
  polled=""
  follows=""
  merge_s=() follow_s=() layer_s=() tileset_s=()
  for i in $(seq "$MERGES"); do
    t0=$(now)
    job=$(api "$wurl" POST /v1/jobs "{\"type\":\"merge\",\"target\":\"$name\",\"source\":\"detail\"}" |
      field id)
    while :; do
      state=$(api "$wurl" GET "/v1/jobs/$job" | field state)
      [[ $state == succeeded ]] && break
      [[ $state == queued || $state == running ]] || { api "$wurl" GET "/v1/jobs/$job" >&2; exit 1; }
      sleep 0.02
    done
    t1=$(now)
    v=$(version_of "$wurl" "$name")
    while [[ $(version_of "$rurl" "$name") != "$v" ]]; do sleep 0.02; done
    t2=$(now)
    status=$(api "$wurl" GET "/v1/jobs/$job")
    created=$(date -d "$(stamp created_at <<<"$status")" +%s.%N)
    finished=$(date -d "$(stamp finished_at <<<"$status")" +%s.%N)
    merge_s+=("$(elapsed "$created" "$finished")")
    follow_s+=("$(elapsed "$finished" "$t2")")
    merges+="${merge_s[-1]}/$(rss_mb "$wpid") "
    polled+="$(elapsed "$t0" "$t1") "
    follows+="${follow_s[-1]} "
    derived
    layer_s+=("$layer")
    tileset_s+=("$tileset")
  done
  printf '%-8s %9s %9s %7s %9s %9s %7s %s/ %s/ %s, %s\n' "$patches" "$info_full" "$info_idx" \
    "$ready_full" "$rss_full" "$ready" "$rss" "$merges" "$follows" "$layer" "$tileset"
  echo "         (medians over the $MERGES merges: merge $(printf '%s\n' "${merge_s[@]}" | median) s," \
    "follow $(printf '%s\n' "${follow_s[@]}" | median) s, layer $(printf '%s\n' "${layer_s[@]}" |
    median) s, tileset $(printf '%s\n' "${tileset_s[@]}" | median) s)"
  echo "         (the first version's layer, tileset: $first_docs s; writer RSS settled: $rss_settled MB)"
  echo "         (merges as polled: $polled)"
  echo "         (generated in ${gen_s} s; the replica's reopen: $(grep -o \
    'another writer published: version [0-9]* ([0-9]* ms)' "$WORK/replica-$depth.log" |
    grep -o '[0-9]* ms' | tr '\n' ' '))"
  stop_vsmd "$rpid"
  stop_vsmd "$wpid"
  # A restart: the first layer of a new process, from the footprints the first one saved.
  start_vsmd "$data" restart-$depth "$budget"
  wurl=$DURL
  derived
  echo "         (after a restart: ready $READY s; layer, tileset: $layer, $tileset s; $(grep -o \
    'read [0-9]* of [0-9]* patches' "$WORK/restart-$depth.log" | head -1))"
  stop_vsmd "$DPID"
  [[ -n "${2:-}" ]] || rm -rf "$data"
done
