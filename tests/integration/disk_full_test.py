#!/usr/bin/python3
"""Disk full: the writers of vsm run on a real, size-limited file system (a tmpfs mounted with
`size=`) that runs out of space part way.

    /usr/bin/python3 disk_full_test.py --vsm <vsm> --vsmd <vsmd> --data <shared/data> --work <dir>
                                       [--scenarios merge,vsmd,merge-out,import]

Needs root (mount(2)); when mounting is not permitted it says so and exits 77 (CTest's skip code,
SKIP_RETURN_CODE of the test). The inputs are the small crops of the real DEMs that
fault_sweep_test.py uses (17 x 17 patches). A reference run of each writer on a large tmpfs
measures the pages a complete run adds (statvfs before and after); then each run gets its tmpfs
remounted so that exactly a fraction of that is free (10, 30, 50, 70, 90, 99 %, and 150 % as the
control that must fit):
- merge: `vsm merge <target> <detail>` in place, the target on the tmpfs; also the two runs around
  the fewest free pages with which it fits (found by bisection): the one below runs out of space
  at the last write before the commit point;
- vsmd: the real vsmd with the tmpfs as its data root (target and detail both in it: a job names
  models of the data root), a merge job over HTTP on 127.0.0.1, the space limited once vsmd is
  ready; the same fractions and the two runs around the fewest pages the CLI merge needed;
- merge-out: `vsm merge <target> <detail> --out <tmpfs>/out`, also with no page free;
- import: `vsm import` onto the tmpfs, also with no page free.

Each run must end with exit 1 and one "vsm: error: ... No space left on device ..." line (for
vsmd: the job failed with that message, the model still served, the model read again from disk,
exit 0 on SIGTERM), or exit 0 when it fit; never a crash or a hang. An in-place merge leaves the
target exactly the old or the new version, passing `vsm validate`; after the next open for writing
(vsm merge of a model outside the target, which fails) no orphan is left and the free space is
back where it was before the run (old), or lower by what a complete merge adds (new), within a few
pages. A failed import or --out merge leaves neither <out> nor <out>.partial-*, and the space free
again; one that fit leaves <out> valid (for the merge: exactly the new version).

Exit 0 printing the counts; exit 1 listing the failures; 77 when tmpfs cannot be mounted.
"""

import argparse
import ctypes
import errno
import os
import shutil
import subprocess
import sys
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from fault_support import PATCH, CliMerge, DaemonMerge, Scenario  # noqa: E402
from model_states import (  # noqa: E402
                          assert_no_failures, check_valid_and_reopened, crop, digest_tree,
                          make_outside_model, version_of, which)

SKIP = 77
TIMEOUT = 60
FRACTIONS = [0.10, 0.30, 0.50, 0.70, 0.90, 0.99, 1.50]
STAGED_FRACTIONS = [0.0, 0.10, 0.50, 0.99, 1.50]  # import and merge --out: quick to fail cleanly
SLACK = 3  # pages: the writer lock file, directory growth
ENOSPC = "No space left on device"
FILLER = "filler"
MS_REMOUNT = 32
MNT_DETACH = 2
LIBC = ctypes.CDLL("libc.so.6", use_errno=True)


class CannotMount(Exception):
    pass


# ---- the size-limited file system ------------------------------------------------------------

def mount_tmpfs(directory, size_bytes, remount=False):
    options = ("size=%d" % size_bytes).encode()
    if LIBC.mount(b"tmpfs", os.fsencode(directory), b"tmpfs", MS_REMOUNT if remount else 0,
                  options) != 0:
        code = ctypes.get_errno()
        message = "mount -t tmpfs -o %s tmpfs %s: %s" % (options.decode(), directory,
                                                         os.strerror(code))
        if code in (errno.EPERM, errno.EACCES):
            raise CannotMount(message)
        raise OSError(code, message)


def unmount(directory):
    if LIBC.umount2(os.fsencode(directory), MNT_DETACH) != 0:
        code = ctypes.get_errno()
        raise OSError(code, "umount -l %s: %s" % (directory, os.strerror(code)))


def mounts_under(root):
    found = []
    with open("/proc/self/mounts") as f:
        for line in f:
            point = line.split()[1].replace("\\040", " ")
            if point == root or point.startswith(root + "/"):
                found.append(point)
    return sorted(found, key=len, reverse=True)


def pages(directory):
    """(page size, used pages, free pages) of the file system of `directory`."""
    st = os.statvfs(directory)
    return st.f_bsize, st.f_blocks - st.f_bfree, st.f_bavail


def limit_free(directory, free_pages):
    """Remounts the tmpfs at `directory` so that exactly `free_pages` pages are free. An empty
    tmpfs gets a one-page FILLER first: size=0 would mean no limit."""
    size, used, _ = pages(directory)
    if used == 0:
        with open(os.path.join(directory, FILLER), "wb") as f:
            f.write(b"\0" * size)
        size, used, _ = pages(directory)
    mount_tmpfs(directory, (used + free_pages) * size, remount=True)
    free = pages(directory)[2]
    if free != free_pages:
        raise RuntimeError("asked for %d free pages on %s, got %d" % (free_pages, directory, free))


def clear(directory):
    for entry in os.listdir(directory):
        path = os.path.join(directory, entry)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        else:
            os.remove(path)


class OnTmpfs(Scenario):
    """run_dir is a tmpfs mount point: reset() empties it (with room to copy the inputs)."""

    big = 64 << 20

    def reset(self):
        mount_tmpfs(self.run_dir, self.big, remount=True)
        clear(self.run_dir)


class TmpfsMerge(CliMerge, OnTmpfs):
    pass


class TmpfsDaemonMerge(DaemonMerge, OnTmpfs):
    pass


# ---- checks ----------------------------------------------------------------------------------

def classify(rc, err):
    """'fit', 'ENOSPC' or None (no clear outcome)."""
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("vsm: error:")]
    if rc == 0 and not errors:
        return "fit"
    if rc == 1 and len(errors) == 1 and ENOSPC in errors[0]:
        return "ENOSPC"
    return None


def check_merge_state(label, scenario, new, free_before, need, failures):
    """The target is old or new, valid, and after the next open without orphans, with the space
    free that its version leaves. Returns 'old', 'new' or None."""
    where = scenario.state()
    version = version_of(where)
    state = which(version, scenario.old, new)
    if state is None:
        failures.append("%s: the target is neither the old nor the new version" % label)
        return None
    check_valid_and_reopened(ARGS.vsm, where, scenario.outside, scenario.old, new, state, label,
                             failures, timeout=TIMEOUT)
    leftovers = [e for e in os.listdir(scenario.run_dir) if ".partial-" in e or ".tmp-" in e]
    if leftovers:
        failures.append("%s: left in the data directory: %s" % (label, leftovers))
    free = pages(scenario.run_dir)[2]
    expected = free_before if state == "old" else free_before - need
    if abs(free - expected) > SLACK:
        failures.append("%s: %d pages free after reopening the %s version, expected %d (%d "
                        "before the run)" % (label, free, state, expected, free_before))
    return state


def run_limited(scenario, free_pages):
    """One run of the scenario with exactly `free_pages` pages free (for vsmd: once it is ready,
    so that its start-up does not count). Returns (exit code, stderr)."""

    def limit():
        limit_free(scenario.run_dir, free_pages)

    scenario.reset()
    if isinstance(scenario, DaemonMerge):
        return scenario.run(dict(os.environ), on_ready=limit)
    limit()
    return scenario.run(dict(os.environ))


def smallest_fit(scenario, low, high):
    """The fewest free pages with which the merge fits, by bisection between `low` (assumed too
    few) and `high` (enough): the runs just below it are out of space at the last write before
    the commit point. Unchecked probes; None when `high` does not fit."""
    if classify(*run_limited(scenario, high)) != "fit":
        return None
    while high - low > 1:
        middle = (low + high) // 2
        if classify(*run_limited(scenario, middle)) == "fit":
            high = middle
        else:
            low = middle
    return high


def merge_runs(scenario, counts, failures, edge=None):
    """The reference run on a large tmpfs; then one run per fraction of the pages it adds, and
    (a CLI merge finds them, vsmd reuses them) the two runs around the smallest space that fits.
    Returns that smallest space."""
    started = time.monotonic()
    before = {}

    def measure():
        before["free"] = pages(scenario.run_dir)[2]

    scenario.reset()
    if isinstance(scenario, DaemonMerge):
        rc, err = scenario.run(dict(os.environ), on_ready=measure)
    else:
        measure()
        rc, err = scenario.run(dict(os.environ))
    if rc != 0:
        failures.append("%s: the reference run exits %d: %s" % (scenario.name, rc, err[-400:]))
        return None
    new = version_of(scenario.state())
    if new[2]:
        failures.append("%s: the reference run leaves orphans: %s" % (scenario.name, new[2][:5]))
    need = before["free"] - pages(scenario.run_dir)[2]
    print("%s: a complete merge adds %d pages (%d files in the new version)" %
          (scenario.name, need, len(digest_tree(scenario.state()))), flush=True)
    if need <= 0:
        failures.append("%s: the reference merge adds no pages" % scenario.name)
        return None
    runs = [("%d%%" % round(f * 100), int(need * f), f >= 1.0) for f in FRACTIONS]
    if edge is None and not isinstance(scenario, DaemonMerge):
        # A merge replaces some folders: at its peak it holds a little more than it adds.
        edge = (smallest_fit(scenario, need - 1, need + need // 10) or
                smallest_fit(scenario, need - 1, int(need * FRACTIONS[-1])))
        if edge is None:
            failures.append("%s: no fit with %d pages free" % (scenario.name,
                                                               int(need * FRACTIONS[-1])))
    if edge is not None:
        runs += [("edge-1", edge - 1, False), ("edge", edge, False)]
    for name, free_pages, must_fit in runs:
        label = "%s: %s (%d of %d pages free)" % (scenario.name, name, free_pages, need)
        try:
            rc, err = run_limited(scenario, free_pages)
        except subprocess.TimeoutExpired:
            failures.append("%s: hangs" % label)
            continue
        counts["runs"] += 1
        outcome = classify(rc, err)
        if outcome is None:
            failures.append("%s: exit %d without a clear outcome: %s" % (label, rc,
                                                                        err.strip()[-600:]))
            continue
        counts[outcome] += 1
        state = check_merge_state(label, scenario, new, free_pages, need, failures)
        if state:
            counts[state] += 1
            line = [ln for ln in err.splitlines() if ln.startswith("vsm: error:")]
            print("%s -> exit %d, %s version; %s" % (label, rc, state, line[0] if line else "fit"),
                  flush=True)
        if must_fit and outcome != "fit":
            failures.append("%s: the control with room to spare did not fit" % label)
    counts["seconds"] += time.monotonic() - started
    return edge


def staged_runs(name, work, command_for, new, counts, failures):
    """A writer that builds <out> in <out>.partial-<pid> on the tmpfs and renames it into place
    (`vsm import`, `vsm merge --out`): the reference run, then runs with no page free and with
    each fraction of what it adds. A run out of space leaves neither <out> nor a staging
    directory, and the space free again; a run that fit leaves <out> valid and, for a merge,
    exactly the new version."""
    mount = os.path.join(work, name, "run")
    out = os.path.join(mount, "out")
    command = command_for(out)
    started = time.monotonic()
    scenario = OnTmpfs(name, work)
    scenario.reset()
    before = pages(mount)[2]
    reference = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               timeout=TIMEOUT)
    if reference.returncode != 0:
        failures.append("%s: the reference run exits %d: %s" % (name, reference.returncode,
                                                                reference.stderr[-400:]))
        return
    need = before - pages(mount)[2]
    print("%s: a complete run adds %d pages" % (name, need), flush=True)
    for fraction in STAGED_FRACTIONS:
        free_pages = int(need * fraction)
        label = "%s: %d%% (%d of %d pages free)" % (name, round(fraction * 100), free_pages,
                                                   need)
        scenario.reset()
        limit_free(mount, free_pages)
        try:
            proc = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, timeout=TIMEOUT)
        except subprocess.TimeoutExpired:
            failures.append("%s: hangs" % label)
            continue
        counts["runs"] += 1
        outcome = classify(proc.returncode, proc.stderr)
        if outcome is None:
            failures.append("%s: exit %d without a clear outcome: %s" %
                            (label, proc.returncode, proc.stderr.strip()[-600:]))
            continue
        counts[outcome] += 1
        left = sorted(e for e in os.listdir(mount)
                      if e != FILLER and (e != "out" or outcome == "ENOSPC"))
        free = pages(mount)[2]
        if outcome == "ENOSPC":
            if left:
                failures.append("%s: left behind: %s" % (label, left))
            if abs(free - free_pages) > SLACK:
                failures.append("%s: %d pages free after the failed run, %d before" %
                                (label, free, free_pages))
            counts["old"] += 1
        else:
            validate = subprocess.run([ARGS.vsm, "validate", out], stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True, timeout=TIMEOUT)
            if validate.returncode != 0:
                failures.append("%s: vsm validate: %s" % (label, validate.stdout[-400:]))
            if new is not None and which(version_of(out), None, new) != "new":
                failures.append("%s: <out> is not the merged version" % label)
            if left:
                failures.append("%s: left beside the output: %s" % (label, left))
            counts["new"] += 1
        if fraction >= 1.0 and outcome != "fit":
            failures.append("%s: the control with room to spare did not fit" % label)
        line = [ln for ln in proc.stderr.splitlines() if ln.startswith("vsm: error:")]
        print("%s -> exit %d, %s; %s" % (label, proc.returncode,
                                          "<out> complete" if outcome == "fit" else "nothing left",
                                          line[0] if line else "fit"), flush=True)
    counts["seconds"] += time.monotonic() - started


# ---- main ------------------------------------------------------------------------------------

ARGS = None


class DiskFull(unittest.TestCase):
    def test_a_full_disk_leaves_the_old_or_the_new_version(self):
        """Each writer on a tmpfs with 10 to 99 % of the pages it adds free: a clear ENOSPC
        error, the model old or new and valid, no orphan, the space back after the next open."""
        work = os.path.abspath(ARGS.work)
        # Leftovers of an earlier run that did not get to unmount.
        for point in mounts_under(work):
            unmount(point)
        if os.path.exists(work):
            shutil.rmtree(work)
        inputs = os.path.join(work, "inputs")
        os.makedirs(inputs)
        names = ARGS.scenarios.split(",")
        mounted = []
        try:
            for name in names:
                point = os.path.join(work, name, "run")
                os.makedirs(point)
                mount_tmpfs(point, OnTmpfs.big)
                mounted.append(point)
        except CannotMount as e:
            for point in mounted:
                unmount(point)
            self.skipTest("cannot mount a size-limited tmpfs (this test needs root): %s" % e)
        try:
            prism = os.path.join(ARGS.data, "PRISMelevation.tif")
            jack = os.path.join(ARGS.data, "jacksboro_fault_dem.tif")
            target_tif = crop(prism, os.path.join(inputs, "target.tif"), -84.8, 36.8, -83.8, 35.8)
            detail_tif = crop(jack, os.path.join(inputs, "detail.tif"), -84.40, 36.44, -84.36, 36.40)

            def imported(tif, name):
                out = os.path.join(inputs, name)
                harness.import_dem(tif, out, PATCH)
                return out

            target, detail = imported(target_tif, "target"), imported(detail_tif, "detail")
            outside = make_outside_model(ARGS.vsm, inputs, PATCH)
            failures, totals = [], []
            edge = None
            for name in names:
                counts = {"runs": 0, "fit": 0, "ENOSPC": 0, "old": 0, "new": 0, "seconds": 0.0}
                if name == "merge":
                    edge = merge_runs(TmpfsMerge("merge", work, target, detail, outside), counts,
                                      failures)
                elif name == "vsmd":
                    merge_runs(TmpfsDaemonMerge("vsmd", work, target, detail, outside), counts,
                               failures, edge)
                elif name == "merge-out":
                    merged = os.path.join(inputs, "merged")
                    harness.vsm("merge", target, detail, "--out", merged, check=True)
                    staged_runs(name, work, lambda out: [ARGS.vsm, "merge", target, detail, "--out",
                                                         out], version_of(merged), counts, failures)
                elif name == "import":
                    staged_runs(name, work, lambda out: [ARGS.vsm, "import", detail_tif, out,
                                                         "--patch-size", str(PATCH)], None, counts,
                                failures)
                else:
                    self.fail("unknown scenario " + name)
                totals.append((name, counts))
        finally:
            for point in mounted:
                unmount(point)
        for name, counts in totals:
            print("%s: %d runs; outcomes: %d ENOSPC errors, %d fit; %d old, %d new%s; %.1f s" %
                  (name, counts["runs"], counts["ENOSPC"], counts["fit"], counts["old"],
                   counts["new"], " (old: nothing at <out>)" if name in ("import", "merge-out") else "",
                   counts["seconds"]))
        assert_no_failures(self, failures)


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--scenarios", default="merge,vsmd,merge-out,import")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    harness.run_tests(rest, skip_code=SKIP)


if __name__ == "__main__":
    main()
