# What the benches share (import_bench.sh, merge_bench.sh, merge_budget.sh, scaling_bench.sh;
# serve_bench.sh and soak.sh for median and install_missing), sourced, not run:
#
#   source "$(dirname "$0")/bench_lib.sh"
#   bench_vsm_and_work "$@"
#
# Sets ROOT (the checkout), HERE (tests/bench) and PYTHON (Debian's python3: it has python3-gdal
# and python3-numpy). bench_vsm_and_work [path/to/vsm] [work-dir] sets VSM (default
# build/server/cli/vsm) and WORK (default a temporary directory, removed on exit), and exits 2
# when VSM is no executable.
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
HERE=$ROOT/tests/bench
PYTHON=/usr/bin/python3

bench_vsm_and_work() {
  VSM=${1:-$ROOT/build/server/cli/vsm}
  if [[ -n "${2:-}" ]]; then
    WORK=$2
    mkdir -p "$WORK"
  else
    WORK=$(mktemp -d)
    trap 'rm -rf "$WORK"' EXIT
  fi
  [[ -x "$VSM" ]] || { echo "no vsm binary at $VSM" >&2; exit 2; }
}

# Seconds since the epoch, to the nanosecond.
now() { date +%s.%N; }

# The median of its arguments (numbers; the lower middle one of an even count).
median() { printf '%s\n' "$@" | sort -g | sed -n "$(( ($# + 1) / 2 ))p"; }

# The size of a file or directory in MB (10^6 bytes), rounded down.
megabytes() { echo $(( $(du -sb "$1" | cut -f1) / 1000000 )); }

# Installs the Debian packages named (apt-get, with sudo when not root); nothing without any.
install_missing() {
  (($#)) || return 0
  local sudo=""
  [[ $(id -u) -ne 0 ]] && sudo=sudo
  echo "installing for the benchmark: $*"
  $sudo apt-get update -q
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q --no-install-recommends "$@"
}
