#!/usr/bin/env bash
# Benchmark (not a test): `vsm merge` times against the targets of the merge issue.
#
# The inputs are SYNTHETIC: GeoTIFFs (EPSG:4326, float32) sampling one analytic terrain function
# (merge_terrain.py beside this file: sinusoids from 60 km to 120 m wavelength), so a coarse target
# and a fine detail model inside it describe the same surface. Quote the figures as synthetic.
# All models are imported with 257 x 257 patches (vsm's default). The target spacing is 3", the
# detail spacing 0.8" (ratio 3.75: two new levels).
#
#   (a) the same detail model (513 x 513 at 0.8") merged into a target of 1025 x 1025 at 3" and
#       into one of 3241 x 3241 at 3" (ten times the vertices, same spacing, containing the first,
#       its origin 4 bottom patches (4 x 256 x 3") north-west of the first so the detail model
#       meets the same bottom patches in both: the same merge work); target: at most 1.2x the time;
#   (b) a ~60 MB detail model (1921 x 1921 at 0.8", OPC on disk) into a ~200 MB model (3585 x 3585
#       at 3"); target: under 3 s (issue 17; the first target was 10 s);
#   (c) the extra time --register adds: the small detail model's surface shifted 4 m east and
#       1.5 m up (so ICP has something to find), merged into the small target with and without
#       --register; target: at most 25 %.
#
# Every figure is the median of $VSM_BENCH_REPEAT (default 3) in-place merges, each into a fresh
# copy of the target (the copy is made before the clock starts, then `sync`), wall time of the
# whole `vsm merge` process (opening, merging, fsynced publish); in (c) the plain and the
# --register merges alternate, so that the load of a shared machine falls on both alike (the run
# times are printed too). `--out` would add a copy of the whole target to every figure (it copies
# A before merging), so it is not used here.
#
#   tests/bench/merge_bench.sh [path/to/vsm] [work-dir]
# Defaults: build/server/cli/vsm and a temporary directory (removed afterwards; needs ~2 GB).
# VSM_BENCH_CASES (default "abc") picks the cases, e.g. VSM_BENCH_CASES=c for --register only
# (its inputs take ~25 MB).
set -euo pipefail
source "$(dirname "$0")/bench_lib.sh"
REPEAT=${VSM_BENCH_REPEAT:-3}
CASES=${VSM_BENCH_CASES:-abc}
bench_vsm_and_work "$@"

gen() {  # gen <name> <west> <north> <spacing"> <size> [shift options]: raster + OPC, once
  local name=$1
  shift
  if [[ ! -d "$WORK/$name" ]]; then
    "$PYTHON" "$HERE/merge_terrain.py" "$WORK/$name.tif" "$@"
    "$VSM" import "$WORK/$name.tif" "$WORK/$name.partial" --patch-size 257 >/dev/null 2>&1
    mv "$WORK/$name.partial" "$WORK/$name"
  fi
  printf '  %-14s %5d x %-5d at %s"  OPC %4d MB\n' "$name" "$4" "$4" "$3" \
    "$(megabytes "$WORK/$name")"
}

has() { [[ $CASES == *$1* ]]; }

echo "synthetic inputs in $WORK (generated and imported once):"
if has a || has c; then gen target-small -100.5 36.5 3 1025; fi
if has a; then gen target-large -101.3533333333333 37.3533333333333 3 3241; fi
if has b; then gen target-200mb -101.5 37.5 3 3585; fi
if has a; then gen detail-small -100.1 36.1 0.8 513; fi
if has b; then gen detail-60mb  -100.3 36.3 0.8 1921; fi
if has c; then gen detail-shift -100.1 36.1 0.8 513 --shift-east 4 --up 1.5; fi

# merge_once <target> <detail> [options]: wall seconds of one in-place merge into a fresh copy.
merge_once() {
  local target=$1 detail=$2 start end
  shift 2
  rm -rf "$WORK/copy"
  cp -a "$WORK/$target" "$WORK/copy"
  sync
  start=$(now)
  /usr/bin/time -f '%e s wall, %U s user, %S s system' -o "$WORK/last.time" \
    "$VSM" merge "$WORK/copy" "$WORK/$detail" "$@" >"$WORK/last.out" 2>"$WORK/last.err"
  end=$(now)
  printf '%.3f\n' "$(echo "$end - $start" | bc -l)"
}

# The last merge's result must validate.
check_last() {
  "$VSM" validate "$WORK/copy" >/dev/null 2>&1 || { echo "merged model does not validate" >&2; exit 1; }
}

# merge_time <target> <detail> [options]: median wall seconds of $REPEAT in-place merges.
merge_time() {
  local times=() i
  for (( i = 0; i < REPEAT; i++ )); do
    times+=("$(merge_once "$@")")
  done
  check_last
  median "${times[@]}"
}

# The last run's own report and its CPU time.
summary() {
  grep -h '^merged\|^registration\|^memory' "$WORK/last.out" | sed 's/^/    /'
  sed 's/^/    last run: /' "$WORK/last.time"
}

if has a; then
echo
echo "(a) the same detail model into a target and into one ten times larger"
small=$(merge_time target-small detail-small)
summary
large=$(merge_time target-large detail-small)
summary
printf '  into target-small %8.3f s\n  into target-large %8.3f s\n' "$small" "$large"
printf '  ratio             %8.2f   (target: at most 1.2)\n' "$(echo "$large / $small" | bc -l)"
fi

if has b; then
echo
echo "(b) a ~60 MB detail model into a ~200 MB model"
big=$(merge_time target-200mb detail-60mb)
summary
printf '  detail-60mb into target-200mb %8.3f s   (target: under 3 s)\n' "$big"
fi

has c || exit 0
echo
echo "(c) the extra time of --register (detail shifted 4 m east, 1.5 m up)"
# Plain and --register merges alternate, so that the load of a shared machine falls on both alike.
plains=() registereds=()
for (( i = 0; i < REPEAT; i++ )); do
  plains+=("$(merge_once target-small detail-shift)")
  cp "$WORK/last.out" "$WORK/plain.out"
  cp "$WORK/last.time" "$WORK/plain.time"
  registereds+=("$(merge_once target-small detail-shift --register)")
done
check_last
plain=$(median "${plains[@]}")
registered=$(median "${registereds[@]}")
grep -h '^merged\|^memory' "$WORK/plain.out" | sed 's/^/    /'
sed 's/^/    last run: /' "$WORK/plain.time"
summary
printf '    the transform moves the detail centre by %s (expected: -4 east, 0 north, -1.5 up)\n' \
  "$("$PYTHON" "$HERE/merge_transform.py" "$WORK/last.out" -100.043 36.043)"
printf '  without --register %8.3f s   (runs: %s)\n' "$plain" "${plains[*]}"
printf '  with --register    %8.3f s   (runs: %s)\n' "$registered" "${registereds[*]}"
printf '  extra             %8.1f %%  (target: at most 25 %%)\n' \
  "$(echo "($registered - $plain) / $plain * 100" | bc -l)"
