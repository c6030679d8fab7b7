#!/usr/bin/env bash
# Benchmark (not a test): how long `vsm` takes to start and answer `--help`, `info` and `validate`,
# and how many shared libraries it loads for each.
#
# The model is REAL: ../shared/data/PRISMelevation.tif imported with vsm's defaults (257 x 257
# patches), as the issue's "demo model"; or $VSM_BENCH_MODEL, an OPC directory.
#
#   tests/bench/startup_bench.sh [label=path/to/vsm ...]
# Default: build=build/server/cli/vsm. Several binaries give a before/after table, e.g. a copy of
# an older vsm (with its shared libraries it is self-contained) against the build:
#   tests/bench/startup_bench.sh before=/tmp/vsm-old after=build/server/cli/vsm
# The model is imported with the last binary, into a temporary directory (removed afterwards).
#
# Each figure is the median of $VSM_BENCH_REPEAT (default 20) runs, the binaries taking turns run
# by run so that the load of a shared machine falls on all alike: wall time from posix_spawn to
# exit (stdout and stderr to /dev/null), and the CPU time (user + system) of the process;
# "libraries" is the number of shared objects ld.so mapped (LD_DEBUG=files, dlopen included; not
# counting the binary, the vDSO and ld.so itself). /bin/true, run in the same turns, is the floor:
# what starting any process costs on this machine at the moment. The load average is printed
# with the table.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
PYTHON=/usr/bin/python3
REPEAT=${VSM_BENCH_REPEAT:-20}
specs=("$@")
[[ ${#specs[@]} -gt 0 ]] || specs=("build=$ROOT/build/server/cli/vsm")
for spec in "${specs[@]}"; do
  [[ $spec == *=* && -x ${spec#*=} ]] || { echo "not label=path/to/vsm: $spec" >&2; exit 2; }
done

MODEL=${VSM_BENCH_MODEL:-}
if [[ -z $MODEL ]]; then
  WORK=$(mktemp -d)
  trap 'rm -rf "$WORK"' EXIT
  MODEL=$WORK/prism
  last=${specs[-1]}
  "${last#*=}" import "$ROOT/../shared/data/PRISMelevation.tif" "$MODEL" >/dev/null 2>&1 ||
    { echo "cannot import the demo model with ${last#*=}" >&2; exit 1; }
fi

"$PYTHON" - "$REPEAT" "$MODEL" "${specs[@]}" <<'PYEOF'
import os
import statistics
import subprocess
import sys
import time

repeat, model, specs = int(sys.argv[1]), sys.argv[2], sys.argv[3:]
binaries = [(s.split("=", 1)[0], os.path.abspath(s.split("=", 1)[1])) for s in specs]
commands = [("--help", ["--help"]), ("info", ["info", model]), ("validate", ["validate", model])]


NULL_OUTPUT = [(os.POSIX_SPAWN_OPEN, fd, os.devnull, os.O_WRONLY, 0) for fd in (1, 2)]


def run_once(argv):
    """Wall and CPU milliseconds of one run, output discarded. posix_spawn (vfork), not fork: a
    fork of this Python process costs more than all of a small vsm (/bin/true: 50 ms against 14 ms
    on a busy 2-core VM), and its page faults would count as the child's CPU time."""
    start = time.perf_counter()
    pid = os.posix_spawn(argv[0], argv, os.environ, file_actions=NULL_OUTPUT)
    _, status, usage = os.wait4(pid, 0)
    wall = (time.perf_counter() - start) * 1000
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit("failed: " + " ".join(argv))
    return wall, (usage.ru_utime + usage.ru_stime) * 1000


def libraries(argv):
    env = dict(os.environ, LD_DEBUG="files")
    err = subprocess.run(argv, env=env, capture_output=True, text=True).stderr
    return sum(1 for line in err.splitlines() if line.endswith("generating link map"))


# The floor: the cost of starting any process on this machine now.
floor = []
samples = {(b, c): [] for b, _ in binaries for c, _ in commands}
for _ in range(repeat):
    floor.append(run_once(["/bin/true"]))
    for name, args in commands:
        for label, path in binaries:
            samples[(label, name)].append(run_once([path, *args]))

patches = os.path.join(model, "Patches")
folders = sum(1 for e in os.listdir(patches) if os.path.isdir(os.path.join(patches, e)))
print("vsm start-up: median of %d runs; load average %s on %d cores; model %s (%d patches)"
      % (repeat, " ".join(open("/proc/loadavg").read().split()[:3]), os.cpu_count(), model,
         folders))
print("%-10s %-9s %12s %11s %10s" % ("binary", "command", "wall ms", "cpu ms", "libraries"))
print("%-10s %-9s %12.1f %11.1f %10s" % ("/bin/true", "", statistics.median(w for w, _ in floor),
                                         statistics.median(c for _, c in floor), "-"))
for name, args in commands:
    for label, path in binaries:
        walls = [w for w, _ in samples[(label, name)]]
        cpus = [c for _, c in samples[(label, name)]]
        print("%-10s %-9s %12.1f %11.1f %10d" % (label, name, statistics.median(walls),
                                                  statistics.median(cpus),
                                                  libraries([path, *args])))
PYEOF
