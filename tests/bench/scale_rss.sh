#!/bin/bash
# Benchmark probe (not a test): where vsmd's RSS outside the budget comes from (issue 31). Run in a
# directory whose root/ holds m8 (scale_gen depth 8) and detail (scale_gen's detail, see
# scale_bench.sh): vsmd (--memory-budget 64MiB) opens them, three merge jobs run, VmRSS is printed
# after the open and after each merge. Extra arguments are the environment of vsmd, e.g. glibc's
# malloc tunables, to tell memory in use from memory the allocator keeps:
#   tests/bench/scale_rss.sh default
#   tests/bench/scale_rss.sh arena1 MALLOC_ARENA_MAX=1
#   tests/bench/scale_rss.sh trim GLIBC_TUNABLES=glibc.malloc.arena_max=1:glibc.malloc.trim_threshold=0:glibc.malloc.mmap_threshold=65536
# VSMD=path/to/vsmd picks the binary (default: vsmd on PATH).
tag=$1; shift
rm -f $tag.port
env "$@" "${VSMD:-vsmd}" --listen 127.0.0.1:0 --data-root root --port-file $tag.port --token bench --memory-budget 64MiB --log-level warn > $tag.log 2>&1 &
pid=$!
while [[ ! -s $tag.port ]]; do sleep 0.05; done
url=http://127.0.0.1:$(cat $tag.port)
echo -n "$tag open $(awk '/VmRSS/{print int($2/1024)}' /proc/$pid/status) MB;"
for i in 1 2 3; do
  id=$(curl -sf -X POST -H "Authorization: Bearer bench" -H 'Content-Type: application/json' -d '{"type":"merge","target":"m8","source":"detail"}' $url/v1/jobs | python3 -c 'import json,sys; print(json.load(sys.stdin)["id"])')
  while :; do s=$(curl -sf -H "Authorization: Bearer bench" $url/v1/jobs/$id | python3 -c 'import json,sys; print(json.load(sys.stdin)["state"])'); [[ $s == queued || $s == running ]] || break; sleep 0.1; done
  echo -n " merge$i $s $(awk '/VmRSS/{print int($2/1024)}' /proc/$pid/status) MB;"
done
echo
kill $pid; wait $pid
