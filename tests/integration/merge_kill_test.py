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
/dev/shm when it is writable, or under --scratch (a real disk: ext4 in CI, where a merge is
fsync-bound and the kernel's write-back is part of what is tested).

--vsmd <vsmd>: the merge runs as a job of the real vsmd (data root: the copy and the detail),
which is SIGKILLed instead; the delays count from the job's acceptance, the "publishing" anchor
is the job's stage seen by polling. --crops <data>: small target and detail models cropped from
the real DEMs, instead of --target and --detail (100 kills in a few minutes); with
--hidden-levels, the target is imported with hidden levels (--visible-texels-per-quad 4).

Exit 0 printing a summary; exit 1 listing the failures.
"""

import argparse
import http.client
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
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from harness import Daemon  # noqa: E402
import harness  # noqa: E402
from model_states import (assert_no_failures, crop, make_outside_model, version_of,  # noqa: E402
                          which)

DRAFT = re.compile(r"[0-9]+_[0-9]+_[0-9]+-v[0-9]+-[0-9a-f]{8}")
MAX_EXTRA = 30
MIN_KILLS = 20


def describe_difference(version, reference):
    missing = set(reference[1]) - set(version[1])
    extra = set(version[1]) - set(reference[1])
    changed = [f for f in set(version[1]) & set(reference[1]) if version[1][f] != reference[1][f]]
    return ("hierarchy %s, %d folders missing, %d extra, %d with other bytes (e.g. %s)" %
            ("equal" if version[0] == reference[0] else "differs", len(missing), len(extra),
             len(changed), sorted(missing | extra | set(changed))[:3]))


class CliMerge:
    """`vsm merge <copy> <detail>` in place; the "publishing" progress lines on stderr."""

    def __init__(self, vsm, copy, detail):
        self.vsm, self.copy, self.detail = vsm, copy, detail

    def start(self):
        """Starts the merge; the time its clock starts from."""
        self.publishing = [None, None]  # seconds to "publishing 0%" and to "publishing 100%"
        self.seen = threading.Event()
        self.lines = []
        self.start_time = time.monotonic()
        self.proc = subprocess.Popen([self.vsm, "merge", self.copy, self.detail],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.reader = threading.Thread(target=self._read)
        self.reader.start()
        return self.start_time

    def _read(self):
        for line in self.proc.stderr:
            self.lines.append(line)
            if self.publishing[0] is None and line.startswith("publishing"):
                self.publishing[0] = time.monotonic() - self.start_time
                self.seen.set()
            if line.startswith("publishing 100%"):
                self.publishing[1] = time.monotonic() - self.start_time
        self.seen.set()

    def running(self):
        return self.proc.poll() is None

    def kill(self):
        self.proc.send_signal(signal.SIGKILL)

    def finish(self):
        """Waits for the end: (0 when the merge completed, -SIGKILL when killed, else the exit
        code; seconds since start; the output)."""
        rc = self.proc.wait()
        end = time.monotonic() - self.start_time
        self.reader.join()
        return rc, end, "".join(self.lines)


class DaemonMerge:
    """A merge job of the real vsmd over HTTP: the data root holds the copy as "target" and the
    detail as "detail"; the clock starts when the job is accepted, the "publishing" stage is
    seen by polling the job."""

    def __init__(self, vsmd, root, scratch):
        self.vsmd, self.root, self.scratch = vsmd, root, scratch

    def start(self):
        self.daemon = Daemon("--token", "kill", root=self.root, vsmd=self.vsmd,
                             port_file=os.path.join(self.scratch, "port"),
                             log_path=os.path.join(self.scratch, "vsmd.log"), start_deadline=30)
        self.proc = self.daemon.proc
        self.publishing = [None, None]
        self.seen = threading.Event()
        self.state = None
        self.job = self.daemon.submit({"type": "merge", "target": "target",
                                       "source": "detail"})["id"]
        self.start_time = time.monotonic()
        self.poller = threading.Thread(target=self._poll)
        self.poller.start()
        return self.start_time

    def _poll(self):
        while self.proc.poll() is None:
            try:
                _, _, job = self.daemon.get_json("/v1/jobs/" + self.job)
            except (OSError, ValueError, http.client.HTTPException):
                break  # killed
            now = time.monotonic() - self.start_time
            if self.publishing[0] is None and job.get("stage") == "publishing":
                self.publishing[0] = now
                self.seen.set()
            if job["state"] in ("succeeded", "failed", "cancelled"):
                self.state = job["state"]
                self.publishing[1] = now
                break
            time.sleep(0.002)
        self.seen.set()

    def running(self):
        return self.state is None and self.proc.poll() is None

    def kill(self):
        self.proc.send_signal(signal.SIGKILL)

    def finish(self):
        if self.proc.poll() is None:
            self.poller.join()
        end = time.monotonic() - self.start_time
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        rc = self.proc.wait()
        self.poller.join()
        if rc == 0 and self.state != "succeeded":
            rc = 1
        with open(os.path.join(self.scratch, "vsmd.log")) as f:
            return rc, end, "job %s\n%s" % (self.state, f.read()[-2000:])


def make_crops(vsm, data, work, target_options=()):
    """PRISM around Jacksboro and a corner of the Jacksboro DEM, imported with 17 x 17 patches
    (the target with `target_options` besides)."""
    made = []
    for name, dem, window, extra in (
            ("target", "PRISMelevation.tif", (-84.8, 36.8, -83.8, 35.8), list(target_options)),
            ("detail", "jacksboro_fault_dem.tif", (-84.4, 36.44, -84.36, 36.40), [])):
        tif = crop(os.path.join(data, dem), os.path.join(work, name + ".tif"), *window)
        out = os.path.join(work, name)
        shutil.rmtree(out, ignore_errors=True)
        subprocess.run([vsm, "import", tif, out, "--patch-size", "17", *extra], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        made.append(out)
    return made


def fresh_copy(source, destination):
    if os.path.exists(destination):
        shutil.rmtree(destination)
    shutil.copytree(source, destination)


ARGS = None


class MergeKill(unittest.TestCase):
    def test_a_killed_merge_leaves_the_old_or_the_new_version(self):
        """The merge SIGKILLed at sampled points: each time exactly the old or the new version,
        valid, no draft left after the next open, and merging again gives the new one."""
        if ARGS.crops is None and (ARGS.target is None or ARGS.detail is None):
            self.fail("--target and --detail, or --crops")

        os.makedirs(ARGS.work, exist_ok=True)
        if ARGS.crops is not None:
            ARGS.target, ARGS.detail = make_crops(
                ARGS.vsm, ARGS.crops, ARGS.work,
                ["--visible-texels-per-quad", "4"] if ARGS.hidden_levels else [])
            ARGS.patch_size = 17
        scratch_parent = ARGS.scratch
        if scratch_parent is None:
            scratch_parent = "/dev/shm" if os.access("/dev/shm", os.W_OK) else ARGS.work
        scratch = tempfile.mkdtemp(prefix="vsm-merge-kill-", dir=scratch_parent)
        try:
            run(self, ARGS, scratch)
        finally:
            shutil.rmtree(scratch, ignore_errors=True)


def run(test, args, scratch):
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
        test.fail("the target has unreachable entries in Patches/ to begin with: %s" % old[2][:5])

    root = os.path.join(scratch, "root")  # vsmd's data root: the copy and the detail
    os.makedirs(root)
    copy = os.path.join(root, "target")
    if args.vsmd:
        shutil.copytree(detail, os.path.join(root, "detail"))

    def runner():
        if args.vsmd:
            return DaemonMerge(args.vsmd, root, scratch)
        return CliMerge(vsm, copy, detail)

    # The new version and the timeline of a complete merge (twice: the same bytes both times).
    durations = []
    new = None
    for attempt in range(2):
        fresh_copy(old_dir, copy)
        merge = runner()
        merge.start()
        rc, end, err = merge.finish()
        publishing = merge.publishing
        if rc != 0:
            test.fail("the complete merge exited %d:\n%s" % (rc, err))
        if None in publishing:
            test.fail("no \"publishing\" stage from its start to its end:\n%s" % err)
        durations.append((end, publishing))
        version = version_of(copy)
        if version[2]:
            failures.append("a complete merge leaves unreachable entries in Patches/: %s" %
                            version[2][:5])
        if new is None:
            new = version
        elif which(version, old, new) != "new":
            test.fail("two complete merges of the same models differ: %s" %
                      describe_difference(version, new))
    if which(new, old, new) == "old" or new[0] == old[0]:
        test.fail("the complete merge did not change the target")
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
    # At least 0.2 s: under load a publish (its syncs) takes longer than in the reference runs.
    window = max(1.5 * max(d[1][1] - d[1][0] for d in durations), 0.2)
    kills = [(None, (i + rng.random()) / args.runs * 0.95 * fastest) for i in range(args.runs)]
    kills += [("publishing", (i + rng.random()) / args.publish_runs * window)
              for i in range(args.publish_runs)]

    counts = {"old": 0, "new": 0, "killed": 0, "finished": 0, "completed": 0}
    # A loaded machine may finish merges before their kill point: then more points, earlier in
    # the merge, until MIN_KILLS runs were killed; or publish slower: then more points later in
    # publishing, until one run leaves the new version (at most MAX_EXTRA more in all).
    extra = 0
    run_index = -1
    while True:
        if run_index + 1 >= len(kills):
            if counts["new"] > 0 or extra >= MAX_EXTRA:
                break
            # A loaded machine may publish slower than the reference runs did (its syncs): later
            # kills in the publishing stage, further each time, until one leaves the new version.
            kills.append(("publishing", window * (1.0 + 0.5 * extra + rng.random())))
            extra += 1
        run_index += 1
        anchor, delay = kills[run_index]
        fresh_copy(old_dir, copy)
        merge = runner()
        start = merge.start()
        if anchor is not None:
            merge.seen.wait(timeout=10 * duration)
            origin = time.monotonic()
        else:
            origin = start
        remaining = delay - (time.monotonic() - origin)
        if remaining > 0:
            time.sleep(remaining)
        killed = merge.running()
        if killed:
            merge.kill()
        rc, at, err = merge.finish()
        if killed and rc == -signal.SIGKILL:
            counts["killed"] += 1
        else:
            counts["finished"] += 1
            planned = sum(1 for a, _ in kills[run_index + 1:])
            if counts["killed"] + planned < MIN_KILLS and extra < MAX_EXTRA:
                kills.append((None, rng.random() * 0.5 * at))
                extra += 1
            if rc != 0:
                failures.append("run %d: the merge exited %d without being killed: %s" %
                                (run_index, rc, err[-300:]))
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
            merge = runner()
            merge.start()
            again_rc, _, again_err = merge.finish()
            counts["completed"] += 1
            if again_rc != 0:
                failures.append("%s: merging again after the kill exits %d: %s" %
                                (label, again_rc, again_err.strip()[-300:]))
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
    print(summary)
    assert_no_failures(test, failures)


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", help="kill vsmd running the merge as a job instead of vsm")
    parser.add_argument("--target", help="the target OPC (or --crops)")
    parser.add_argument("--detail", help="the detail OPC (or --crops)")
    parser.add_argument("--crops", metavar="DATA",
                        help="make small target and detail models from crops of the real DEMs "
                        "in DATA (17 x 17 patches) instead of --target and --detail")
    parser.add_argument("--hidden-levels", action="store_true",
                        help="with --crops: the target has hidden levels (--visible-texels-per-quad "
                             "4), whose second hierarchy file commits with the hierarchy")
    parser.add_argument("--work", required=True)
    parser.add_argument("--scratch", help="where the copies go (default: /dev/shm if writable, "
                        "else --work)")
    parser.add_argument("--runs", type=int, default=24)
    parser.add_argument("--publish-runs", type=int, default=10)
    parser.add_argument("--complete-runs", type=int, default=4)
    parser.add_argument("--patch-size", type=int, default=65)
    parser.add_argument("--seed", type=int, default=20261125)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
