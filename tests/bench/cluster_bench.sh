#!/usr/bin/env bash
# Reads per second through the nginx front of a loopback cluster (deploy/local-cluster.sh) with 1,
# 2 and 3 vsmd nodes, and nginx's cache hit ratio. A benchmark, not a test.
#
#   tests/bench/cluster_bench.sh [WORK_DIR]      (default /tmp/vsm-cluster-bench)
#
# Models: PRISM and Jacksboro imported at 65 x 65 (357 patches). wrk (-t2 -c32, keep-alive) reads
# the positions of every patch round robin, for BENCH_DURATION (default 10s) after a 2 s warm-up:
#   cached:    the URLs as clients send them; nginx serves them from its cache once it has them
#              (vsmd allows a minute), so this measures the front;
#   misses:    each URL with a query nginx has not seen (?b=<run>-<n>), so every read misses the
#              front's cache and goes to a node (nginx stores each answer, as for any miss): this
#              measures the front's misses (proxying and storing);
#   bypass:    ?nocache=1 on every URL: nginx passes each read to a node and stores nothing
#              (deploy/nginx/vsm.conf), so this measures the nodes behind the front;
#   direct:    (1 node only) the same reads from the node, without nginx.
# Environment: VSMD, VSM (built binaries; default build/), BENCH_DURATION.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
WORK=$(realpath -m "${1:-/tmp/vsm-cluster-bench}")
DURATION=${BENCH_DURATION:-10s}
VSM=${VSM:-$ROOT/build/server/cli/vsm}
export VSMD=${VSMD:-$ROOT/build/server/vsmd}
DATA=$ROOT/../shared/data
command -v wrk >/dev/null || { apt-get install -y -q wrk >/dev/null; }

CLUSTER=$WORK/cluster
if [[ -f "$CLUSTER/cluster.env" ]]; then "$ROOT/deploy/local-cluster.sh" down "$CLUSTER"; fi
rm -rf "$WORK"
mkdir -p "$CLUSTER/data"
"$VSM" import "$DATA/PRISMelevation.tif" "$CLUSTER/data/prism" --patch-size 65 >/dev/null 2>&1
"$VSM" import "$DATA/jacksboro_fault_dem.tif" "$CLUSTER/data/jacksboro" --patch-size 65 >/dev/null 2>&1

# Round robin over the paths in $WORK/paths; BENCH_MODE misses: a query of its own per request,
# bypass: ?nocache=1. Counts
# the X-Cache-Status of each answer.
cat >"$WORK/paths.lua" <<'LUA'
local paths, threads = {}, {}
for line in io.lines(os.getenv("BENCH_PATHS")) do paths[#paths + 1] = line end
local mode = os.getenv("BENCH_MODE")
function setup(thread)
  thread:set("id", #threads)
  threads[#threads + 1] = thread
end
function init(args)
  math.randomseed(os.time() * 1000 + id)
  nonce = math.random(1, 1000000000)
  i = id * 97
  n = 0
  hits = 0
  answers = 0
end
function request()
  i = i + 1
  n = n + 1
  local path = paths[(i % #paths) + 1]
  if mode == "misses" then
    path = path .. "?b=" .. nonce .. "-" .. id .. "-" .. n
  elseif mode == "bypass" then
    path = path .. "?nocache=1"
  end
  return wrk.format("GET", path)
end
function response(status, headers, body)
  answers = answers + 1
  if headers["X-Cache-Status"] == "HIT" then hits = hits + 1 end
end
function done(summary, latency, requests)
  local h, a = 0, 0
  for _, t in ipairs(threads) do
    h = h + t:get("hits")
    a = a + t:get("answers")
  end
  io.write(string.format("cache-hits %d of %d\n", h, a))
end
LUA

# Prints "<requests/s> <cache hit %> <p99>" of one run against URL $1.
run() {
  BENCH_PATHS=$WORK/paths wrk -t2 -c32 -d2s -s "$WORK/paths.lua" "$1" >/dev/null
  BENCH_PATHS=$WORK/paths wrk -t2 -c32 -d"$DURATION" --latency -s "$WORK/paths.lua" "$1" \
    >"$WORK/wrk.out"
  if grep -q "Non-2xx\|Socket errors" "$WORK/wrk.out"; then
    cat "$WORK/wrk.out" >&2
    echo "cluster_bench: errors in the run" >&2
    exit 1
  fi
  local rps hits p99
  rps=$(sed -n 's/^Requests\/sec: *//p' "$WORK/wrk.out")
  hits=$(awk '/^cache-hits/ {printf "%.0f", ($4 ? 100 * $2 / $4 : 0)}' "$WORK/wrk.out")
  p99=$(sed -n 's/^ *99% *//p' "$WORK/wrk.out")
  echo "$rps $hits $p99"
}

echo "cluster_bench: $(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg), wrk -t2 -c32" \
  "-d$DURATION, models prism + jacksboro at 65 x 65"
printf "%-6s %-9s %12s %8s %10s\n" nodes reads "requests/s" "hits %" "p99"
for nodes in 1 2 3; do
  VSM_NODES=$nodes VSM_MEMORY_BUDGET=256MiB "$ROOT/deploy/local-cluster.sh" up "$CLUSTER" \
    >/dev/null
  # shellcheck disable=SC1091
  source "$CLUSTER/cluster.env"
  python3 - "$FRONT" >"$WORK/paths" <<'PY'
import json, sys, urllib.request
front = sys.argv[1]
def walk(node):
    yield node["key"]
    for child in node.get("children", []):
        yield from walk(child)
for model in ("prism", "jacksboro"):
    with urllib.request.urlopen("%s/v1/models/%s/hierarchy" % (front, model)) as r:
        for key in walk(json.load(r)["root"]):
            print("/v1/models/%s/patches/%s/positions" % (model, key))
PY
  for mode in cached misses bypass; do
    out=$(BENCH_MODE=$mode run "$FRONT")
    read -r rps hits p99 <<<"$out"
    printf "%-6s %-9s %12s %8s %10s\n" "$nodes" "$mode" "$rps" "$hits" "$p99"
  done
  if ((nodes == 1)); then
    out=$(BENCH_MODE=bypass run "$N1")
    read -r rps hits p99 <<<"$out"
    printf "%-6s %-9s %12s %8s %10s\n" "$nodes" direct "$rps" "-" "$p99"
  fi
  "$ROOT/deploy/local-cluster.sh" down "$CLUSTER" >/dev/null
done
echo "paths: $(wc -l <"$WORK/paths") patches of 2 models"
