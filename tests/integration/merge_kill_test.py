#!/usr/bin/python3
"""Kill test: `vsm merge <target> <detail>` (in place) killed with SIGKILL at many points, and the
target checked after each kill.

    /usr/bin/python3 merge_kill_test.py --vsm <vsm> --target <A-opc> --detail <B-opc>
                                        --work <dir> [--runs 24] [--publish-runs 10] [--seed N]

A and B are OPCs that `vsm import` made (in CI: PRISMelevation.tif and jacksboro_fault_dem.tif,
65 x 65 patches). First one complete in-place merge of a copy of A, timed from the start of the
process to its exit, with the moment its "publishing" stage begins (progress lines on stderr); a
second complete merge must give the same bytes (so "the new version" is one well-defined set of
files). Then, for `--runs` delays spread evenly over that duration (one random point in each of
`--runs` equal slices, fixed seed) and `--publish-runs` more from the "publishing 0%" line over
the publishing stage and half as long beyond: a fresh copy of A, `vsm merge copy B`, SIGKILL after
the delay. After each kill:

- `vsm validate copy` passes;
- the copy is exactly the old or exactly the new version: its patchhierarchy.xml has the bytes of
  A's or of the completed merge's, and every patch folder the hierarchy reaches holds the same
  files with the same bytes as in that version;
- entries of Patches/ that the hierarchy does not reach: before reopening, draft folders
  (`<key>-v<n>`) are allowed; then the model is reopened (`vsm merge copy <outside>`, with a
  one-patch model far outside A: LiveModel::open runs, the merge fails with "outside", nothing
  changes) and afterwards no draft folder may remain and the version must be the same as before;
  other unreachable entries (an old version's folders whose removal was cut short, a temporary
  hierarchy file) are reported as warnings, since opening does not promise to remove them;
- when the copy is still the old version, for the first `--complete-runs` such kills, a second
  `vsm merge copy B` must complete and give exactly the new version (recovery from the crash).

At least 20 of the runs must actually kill the merge before it exits. The copies live under
/dev/shm when it is writable (--scratch to choose): SIGKILL kills the process, not the kernel, so
what the files hold afterwards does not depend on fsync, and a merge there takes about a second
instead of several (fsync-bound on a real disk).

Exit 0 printing a summary; exit 1 listing the failures.
"""

import argparse
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
from osgeo import gdal, osr

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from check_import import find_ci, read_hierarchy  # noqa: E402
from merge_check import folder_digest  # noqa: E402

gdal.UseExceptions()

DRAFT = re.compile(r"[0-9]+_[0-9]+_[0-9]+-v[0-9]+")
MAX_EXTRA = 30
MIN_KILLS = 20


def version_of(opc):
    """(hierarchy bytes, {reachable folder: {file: sha256}}, unreachable entries of Patches/)."""
    patches_dir, root, children = read_hierarchy(opc)
    with open(find_ci(patches_dir, "patchhierarchy.xml"), "rb") as f:
        hierarchy = f.read()
    reachable = set()
    stack = [root]
    while stack:
        folder = stack.pop()
        if folder in reachable:
            continue
        reachable.add(folder)
        stack.extend(children.get(folder, {}).values())
    folders = {folder: folder_digest(os.path.join(patches_dir, folder)) for folder in reachable}
    others = sorted(e for e in os.listdir(patches_dir)
                    if e not in reachable and e.lower() != "patchhierarchy.xml")
    return hierarchy, folders, others


def which(version, old, new):
    if version[0] == old[0] and version[1] == old[1]:
        return "old"
    if version[0] == new[0] and version[1] == new[1]:
        return "new"
    return None


def describe_difference(version, reference):
    missing = set(reference[1]) - set(version[1])
    extra = set(version[1]) - set(reference[1])
    changed = [f for f in set(version[1]) & set(reference[1]) if version[1][f] != reference[1][f]]
    return ("hierarchy %s, %d folders missing, %d extra, %d with other bytes (e.g. %s)" %
            ("equal" if version[0] == reference[0] else "differs", len(missing), len(extra),
             len(changed), sorted(missing | extra | set(changed))[:3]))


def timed_merge(vsm, target, detail):
    """Runs a merge to completion: (seconds to exit, [seconds to "publishing 0%", to "publishing
    100%"] on stderr, rc, stderr)."""
    start = time.monotonic()
    proc = subprocess.Popen([vsm, "merge", target, detail], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    publishing = [None, None]
    lines = []

    def read():
        for line in proc.stderr:
            lines.append(line)
            if publishing[0] is None and line.startswith("publishing"):
                publishing[0] = time.monotonic() - start
            if line.startswith("publishing 100%"):
                publishing[1] = time.monotonic() - start

    reader = threading.Thread(target=read)
    reader.start()
    rc = proc.wait()
    end = time.monotonic() - start
    reader.join()
    return end, publishing, rc, "".join(lines)


def wait_for_line(stream, prefix, seen):
    """Reads `stream` to its end, setting `seen` at the first line starting with `prefix`."""
    for line in stream:
        if prefix is not None and line.startswith(prefix):
            seen.set()
    seen.set()


def make_outside_model(vsm, directory, patch_size):
    """A one-patch model in the Alps (10 E, 47 N), far outside any CONUS target."""
    tif = os.path.join(directory, "outside.tif")
    ds = gdal.GetDriverByName("GTiff").Create(tif, patch_size, patch_size, 1, gdal.GDT_Float32)
    ds.SetGeoTransform((10.0, 1.0 / 3600, 0.0, 47.0, 0.0, -1.0 / 3600))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ds.SetProjection(srs.ExportToWkt())
    ds.GetRasterBand(1).WriteArray(np.full((patch_size, patch_size), 1000.0, np.float32))
    ds = None
    out = os.path.join(directory, "outside")
    subprocess.run([vsm, "import", tif, out, "--patch-size", str(patch_size)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return out


def fresh_copy(source, destination):
    if os.path.exists(destination):
        shutil.rmtree(destination)
    shutil.copytree(source, destination)


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--target", required=True)
    parser.add_argument("--detail", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--scratch", help="where the copies go (default: /dev/shm if writable, "
                        "else --work)")
    parser.add_argument("--runs", type=int, default=24)
    parser.add_argument("--publish-runs", type=int, default=10)
    parser.add_argument("--complete-runs", type=int, default=4)
    parser.add_argument("--patch-size", type=int, default=65)
    parser.add_argument("--seed", type=int, default=20261125)
    args = parser.parse_args()

    os.makedirs(args.work, exist_ok=True)
    scratch_parent = args.scratch
    if scratch_parent is None:
        scratch_parent = "/dev/shm" if os.access("/dev/shm", os.W_OK) else args.work
    scratch = tempfile.mkdtemp(prefix="vsm-merge-kill-", dir=scratch_parent)
    try:
        return run(args, scratch)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def run(args, scratch):
    failures = []
    warnings = []
    started = time.monotonic()
    vsm = args.vsm
    old_dir = os.path.join(scratch, "old")
    detail = os.path.join(scratch, "detail")
    shutil.copytree(args.target, old_dir)
    shutil.copytree(args.detail, detail)
    outside = make_outside_model(vsm, scratch, args.patch_size)
    old = version_of(old_dir)
    if old[2]:
        print("FAIL the target has unreachable entries in Patches/ to begin with: %s" % old[2][:5])
        return 1

    # The new version and the timeline of a complete merge (twice: the same bytes both times).
    durations = []
    new = None
    for attempt in range(2):
        ref = os.path.join(scratch, "new-%d" % attempt)
        fresh_copy(old_dir, ref)
        end, publishing, rc, err = timed_merge(vsm, ref, detail)
        if rc != 0:
            print("FAIL the complete merge exited %d:\n%s" % (rc, err))
            return 1
        if None in publishing:
            print("FAIL no \"publishing\" stage from 0%% to 100%% on stderr:\n%s" % err)
            return 1
        durations.append((end, publishing))
        version = version_of(ref)
        if version[2]:
            failures.append("a complete merge leaves unreachable entries in Patches/: %s" %
                            version[2][:5])
        if new is None:
            new = version
        elif which(version, old, new) != "new":
            print("FAIL two complete merges of the same models differ: %s" %
                  describe_difference(version, new))
            return 1
        shutil.rmtree(ref)
    if which(new, old, new) == "old" or new[0] == old[0]:
        print("FAIL the complete merge did not change the target")
        return 1
    duration = max(d[0] for d in durations)
    print("complete merges: %s; %d folders before, %d after" %
          ("; ".join("%.3f s, publishing %.3f-%.3f s" % (d[0], d[1][0], d[1][1])
                     for d in durations), len(old[1]), len(new[1])))

    rng = random.Random(args.seed)
    # Kill points: (anchor, delay after it). From the start of the process, one random point in
    # each of --runs equal slices of the fastest complete merge (so nearly all of them kill); from
    # the "publishing 0%" line on stderr, --publish-runs more over the publishing stage and half
    # as long beyond (writing the drafts, the hierarchy's rename, removing the old folders; a
    # short window: anchoring at the stage itself keeps start-up jitter out of it).
    fastest = min(d[0] for d in durations)
    window = 1.5 * max(max(d[1][1] - d[1][0] for d in durations), 1e-3)
    kills = [(None, (i + rng.random()) / args.runs * 0.95 * fastest) for i in range(args.runs)]
    kills += [("publishing", (i + rng.random()) / args.publish_runs * window)
              for i in range(args.publish_runs)]

    copy = os.path.join(scratch, "copy")
    counts = {"old": 0, "new": 0, "killed": 0, "finished": 0, "completed": 0}
    # A loaded machine may finish merges before their kill point: then more points, earlier in
    # the merge, until MIN_KILLS runs were killed (at most MAX_EXTRA more).
    extra = 0
    run_index = -1
    while run_index + 1 < len(kills):
        run_index += 1
        anchor, delay = kills[run_index]
        fresh_copy(old_dir, copy)
        start = time.monotonic()
        proc = subprocess.Popen([vsm, "merge", copy, detail], stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True)
        seen = threading.Event()
        reader = threading.Thread(target=wait_for_line, args=(proc.stderr, anchor, seen))
        reader.start()
        if anchor is not None:
            seen.wait(timeout=10 * duration)
            origin = time.monotonic()
        else:
            origin = start
        remaining = delay - (time.monotonic() - origin)
        if remaining > 0:
            time.sleep(remaining)
        killed = proc.poll() is None
        if killed:
            proc.send_signal(signal.SIGKILL)
        rc = proc.wait()
        reader.join()
        at = time.monotonic() - start
        if killed and rc == -signal.SIGKILL:
            counts["killed"] += 1
        else:
            counts["finished"] += 1
            planned = sum(1 for a, _ in kills[run_index + 1:])
            if counts["killed"] + planned < MIN_KILLS and extra < MAX_EXTRA:
                kills.append((None, rng.random() * 0.5 * at))
                extra += 1
            if rc != 0:
                failures.append("run %d: the merge exited %d without being killed" %
                                (run_index, rc))
                continue
        where = "%.3f s" % at if anchor is None else \
            "%.3f s, %.1f ms after %s" % (at, 1000 * delay, anchor)
        label = ("run %d (kill at %s)" if killed else "run %d (finished before %s)") % \
            (run_index, where)

        validate = subprocess.run([vsm, "validate", copy], stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True)
        if validate.returncode != 0:
            failures.append("%s: vsm validate fails: %s" % (label, validate.stdout.strip()[-800:]))
        try:
            version = version_of(copy)
        except (OSError, ValueError, KeyError, AttributeError) as e:
            failures.append("%s: the model cannot be read: %s: %s" % (label, type(e).__name__, e))
            continue
        state = which(version, old, new)
        if state is None:
            failures.append("%s: neither the old version (%s) nor the new one (%s)" %
                            (label, describe_difference(version, old),
                             describe_difference(version, new)))
            continue
        counts[state] += 1
        stray = [e for e in version[2] if not DRAFT.fullmatch(e)]

        # Reopen: LiveModel::open removes draft leftovers; the merge then fails (outside).
        reopen = subprocess.run([vsm, "merge", copy, outside], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        if reopen.returncode == 0 or "outside" not in reopen.stderr:
            failures.append("%s: merging a model outside the target: exit %d, %s" %
                            (label, reopen.returncode, reopen.stderr.strip()[-300:]))
        after = version_of(copy)
        if which(after, old, new) != state:
            failures.append("%s: reopening changed the model from the %s version to %s" %
                            (label, state, which(after, old, new)))
        drafts = [e for e in after[2] if DRAFT.fullmatch(e)]
        if drafts:
            failures.append("%s: draft folders left after reopening: %s" % (label, drafts[:5]))
        left = [e for e in after[2] if not DRAFT.fullmatch(e)]
        if left:
            warnings.append("%s (%s version): entries no version uses stay after reopening: %s%s"
                            % (label, state, left[:5], " ..." if len(left) > 5 else ""))
        print("%s: %s version, %d unreachable entries (%d not drafts) -> %d after reopening" %
              (label, state, len(version[2]), len(stray), len(after[2])))

        if state == "old" and counts["completed"] < args.complete_runs:
            # Recovery: merging again after the crash gives exactly the new version.
            again = subprocess.run([vsm, "merge", copy, detail], stdout=subprocess.DEVNULL,
                                   stderr=subprocess.PIPE, text=True)
            counts["completed"] += 1
            if again.returncode != 0:
                failures.append("%s: merging again after the kill exits %d: %s" %
                                (label, again.returncode, again.stderr.strip()[-300:]))
            else:
                completed = version_of(copy)
                if which(completed, old, new) != "new":
                    failures.append("%s: merging again after the kill does not give the new "
                                    "version: %s" % (label, describe_difference(completed, new)))
                elif completed[2]:
                    failures.append("%s: merging again after the kill leaves %s" %
                                    (label, completed[2][:5]))

    if counts["killed"] < MIN_KILLS:
        failures.append("only %d of %d runs were killed before the merge finished (need %d)" %
                        (counts["killed"], len(kills), MIN_KILLS))
    if counts["old"] == 0 or counts["new"] == 0:
        failures.append("the kills never left the %s version: the delays do not span the merge" %
                        ("old" if counts["old"] == 0 else "new"))
    summary = ("%d runs over a %.2f s merge: %d killed, %d finished first; %d left the old "
               "version, %d the new one; %d recovered by merging again; %d warnings; %.1f s" %
               (len(kills), duration, counts["killed"], counts["finished"], counts["old"],
                counts["new"], counts["completed"], len(warnings), time.monotonic() - started))
    for message in warnings:
        print("WARN " + message)
    if failures:
        for message in failures[:50]:
            print("FAIL " + message)
        print(summary)
        print("%d failures" % len(failures))
        return 1
    print("OK " + summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
