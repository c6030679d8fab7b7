#!/usr/bin/python3
"""Fault sweep: every writer of vsm run with one file-system call failed (EIO or ENOSPC) by the
LD_PRELOAD library tests/fault/fault_inject.c, over the calls of the whole run.

    /usr/bin/python3 fault_sweep_test.py --vsm <vsm> --vsmd <vsmd> --lib <libvsm_fault_inject.so>
                                         --data <shared/data> --work <dir> [--scenarios ...]

Scenarios, on small crops of the real DEMs (PRISM around Jacksboro as the target, a corner of the
Jacksboro DEM as the detail, 17 x 17 patches):
- import: `vsm import` of the detail crop;
- merge: `vsm merge` in place;
- textured: `vsm merge` in place of models imported with the NASA image;
- hidden: `vsm merge` in place of a target with hidden levels (`--visible-texels-per-quad 4`):
  its second hierarchy file commits with the hierarchy (a version is told by that file's
  content, and one no kept hierarchy names is an orphan);
- vsmd: a merge job submitted to the real vsmd over HTTP, the library preloaded into vsmd.
The merge and vsmd targets carry a full index (`vsm index`), which their publish adopts as the base
of its delta index by a hard link; the textured target has none, so its publish writes a new base.

For each: one run without a fault records every counted call (class, index, path) and the commit
point (the rename of the new hierarchy, or of the import's staging directory). Then a run per
chosen N for each class (write, sync, rename, mkdir, create, unlink, link): every N within
--window calls (in the order of all classes) of the commit point, and --samples evenly spread
over the rest, alternating EIO and ENOSPC. Each run must:
- end with a clear error (exit 1 with one "vsm: error:" line, or the job failed with a message)
  or succeed with the fault reported as a warning; never a crash or a hang. A fault neither
  reported nor hit is counted apart ("missed": the call did not happen in that run);
- leave the model opening as exactly the old or the new version (same hierarchy bytes, same
  bytes in every folder the hierarchy reaches) and passing `vsm validate`;
- leave no orphan after the next open (vsm merge of a model outside the target opens it for
  writing and fails): no folder, tile or temporary file that the hierarchy does not name, no
  staging directory.
The vsmd runs also check that the daemon keeps serving the model after a failed job, reads it
again from disk after an I/O error, and exits 0 on SIGTERM.

Exit 0 printing the counts; exit 1 listing the failures.
"""

import argparse
import os
import shutil
import subprocess
import sys
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from fault_support import PATCH, CliImport, CliMerge, DaemonMerge  # noqa: E402
from model_states import (  # noqa: E402
                          assert_no_failures, check_valid_and_reopened, crop,
                          make_outside_model, version_of, which)


CLASSES = ["write", "sync", "rename", "mkdir", "create", "unlink", "link"]


# ---- running with a fault --------------------------------------------------------------------

def fault_env(prefix, trace=None, fault=None, report=None):
    """The fault library under `prefix`: tracing its calls, or failing call n of class cls with
    errno code (fault=(cls, n, code)), reported to `report`."""
    cls, n, code = fault or (None, None, None)
    return harness.fault_env(ARGS.lib, prefix, trace=trace or None, **{"class": cls}, n=n,
                             errno=code, report=report if fault else None)


def read_trace(path):
    calls = []
    if os.path.exists(path):
        with open(path) as f:
            for line in f:
                seq, cls, n, target = line.rstrip("\n").split(" ", 3)
                calls.append((int(seq), cls, int(n), target))
    return calls


def choose(calls, commit, first, window, samples):
    """[(class, n)]: per class every n within `window` of the commit's sequence number, and
    `samples` evenly spread over the others from `first[class]` on, and the last."""
    chosen = []
    for cls in CLASSES:
        mine = [(seq, n) for seq, c, n, _ in calls if c == cls and n > first.get(cls, 0)]
        if not mine:
            continue
        near = {n for seq, n in mine if abs(seq - commit) <= window}
        rest = [n for seq, n in mine if n not in near]
        if rest:
            picks = {rest[int(i * (len(rest) - 1) / max(samples - 1, 1))]
                     for i in range(min(samples, len(rest)))}
            picks.add(rest[-1])
        else:
            picks = set()
        chosen += [(cls, n) for n in sorted(near | picks)]
    return chosen


def injected(report):
    if not os.path.exists(report):
        return None
    with open(report) as f:
        return f.read().strip() or None


# ---- the sweep -------------------------------------------------------------------------------

def sweep(scenario, failures, totals):
    started = time.monotonic()
    trace = os.path.join(scenario.work, "trace")
    # The reference run: no fault, every call traced.
    scenario.reset()
    if os.path.exists(trace):
        os.remove(trace)
    first = {}

    def startup_counts():
        for _, cls, n, _ in read_trace(trace):
            first[cls] = max(first.get(cls, 0), n)

    kwargs = {"on_ready": startup_counts} if isinstance(scenario, DaemonMerge) else {}
    rc, err = scenario.run(fault_env(scenario.run_dir, trace=trace), **kwargs)
    if rc != 0:
        failures.append("%s: the run without a fault exits %d: %s" % (scenario.name, rc, err))
        return
    calls = read_trace(trace)
    new = version_of(scenario.state())
    if new[2]:
        failures.append("%s: a complete run leaves orphans: %s" % (scenario.name, new[2][:5]))
    commit = scenario.commit_of(calls)
    chosen = choose(calls, commit, first, ARGS.window, ARGS.samples)
    per_class = {cls: sum(1 for c in calls if c[1] == cls and c[2] > first.get(cls, 0))
                 for cls in CLASSES}
    counts = {"runs": 0, "injected": 0, "missed": 0, "error": 0, "warned": 0, "old": 0, "new": 0}
    report = os.path.join(scenario.work, "report")
    for index, (cls, n) in enumerate(chosen):
        code = "EIO" if index % 2 == 0 else "ENOSPC"
        label = "%s: %s #%d %s" % (scenario.name, cls, n, code)
        scenario.reset()
        if os.path.exists(report):
            os.remove(report)
        try:
            rc, err = scenario.run(fault_env(scenario.run_dir, fault=(cls, n, code),
                                             report=report))
        except subprocess.TimeoutExpired:
            failures.append("%s: hangs" % label)
            continue
        counts["runs"] += 1
        hit = injected(report)
        if hit:
            counts["injected"] += 1
        lines = [line for line in err.splitlines() if line.strip()]
        errors = [line for line in lines if line.startswith("vsm: error:")]
        warned = [line for line in lines if " WARN " in line]
        if rc == 1 and len(errors) == 1 and hit:
            counts["error"] += 1
            outcome = errors[0]
        elif rc == 0 and not hit:
            counts["missed"] += 1
            outcome = "not hit"
        elif rc == 0 and hit and warned:
            counts["warned"] += 1
            outcome = warned[0]
        else:
            failures.append("%s (fault %s): exit %d without a clear outcome: %s" %
                            (label, hit or "not hit", rc, err.strip()[-600:]))
            continue
        where = scenario.state()
        if isinstance(scenario, CliImport) and not os.path.exists(where):
            state = "old"
            version = None
        else:
            version = version_of(where)
            state = which(version, scenario.old, new)
        if state is None:
            failures.append("%s: neither the old nor the new version" % label)
            continue
        counts[state] += 1
        print("%s -> %s version; %s" % (label, state, outcome[-160:]), flush=True)
        if version is not None:
            # The next open (for writing) removes every orphan.
            check_valid_and_reopened(ARGS.vsm, where, scenario.outside, scenario.old, new,
                                     state, label, failures)
        staging = [e for e in os.listdir(scenario.run_dir) if ".partial-" in e]
        if staging:
            failures.append("%s: staging directories left: %s" % (label, staging))
    totals.append((scenario.name, len(calls), per_class, counts, time.monotonic() - started))


ARGS = None


class FaultSweep(unittest.TestCase):
    def test_every_fault_leaves_the_old_or_the_new_version(self):
        """Each writer with one file-system call failed at sampled points: a clear error or a
        reported warning, the model old or new, valid, no orphans after the next open."""
        work = os.path.abspath(ARGS.work)
        if os.path.exists(work):
            shutil.rmtree(work)
        inputs = os.path.join(work, "inputs")
        os.makedirs(inputs)
        prism = os.path.join(ARGS.data, "PRISMelevation.tif")
        jack = os.path.join(ARGS.data, "jacksboro_fault_dem.tif")
        image = os.path.join(ARGS.data, "conus_visible_earth.tif")
        target_tif = crop(prism, os.path.join(inputs, "target.tif"), -84.8, 36.8, -83.8, 35.8)
        detail_tif = crop(jack, os.path.join(inputs, "detail.tif"), -84.40, 36.44, -84.36, 36.40)

        def imported(tif, name, texture=False, hidden=False):
            out = os.path.join(inputs, name)
            extra = ["--texture", image] if texture else []
            extra += ["--visible-texels-per-quad", "4"] if hidden else []
            harness.import_dem(tif, out, PATCH, *extra)
            return out

        target, detail = imported(target_tif, "target"), imported(detail_tif, "detail")
        ttarget, tdetail = imported(target_tif, "ttarget", True), imported(detail_tif, "tdetail", True)
        htarget = imported(target_tif, "htarget", hidden=True)
        outside = make_outside_model(ARGS.vsm, inputs, PATCH)
        scenarios = {
            "import": lambda: CliImport("import", work, detail_tif, outside),
            "merge": lambda: CliMerge("merge", work, target, detail, outside, indexed=True),
            "textured": lambda: CliMerge("textured", work, ttarget, tdetail, outside),
            "hidden": lambda: CliMerge("hidden", work, htarget, detail, outside),
            "vsmd": lambda: DaemonMerge("vsmd", work, target, detail, outside, indexed=True),
        }
        failures, totals = [], []
        for name in ARGS.scenarios.split(","):
            sweep(scenarios[name](), failures, totals)
        for name, calls, per_class, counts, seconds in totals:
            print("%s: %d counted calls (%s); %d runs, %d faults injected, %d missed; outcomes: "
                  "%d errors, %d warnings; %d old, %d new; %.1f s" %
                  (name, calls, ", ".join("%s %d" % kv for kv in per_class.items()), counts["runs"],
                   counts["injected"], counts["missed"], counts["error"], counts["warned"],
                   counts["old"], counts["new"], seconds))
        assert_no_failures(self, failures)


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--lib", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--scenarios", default="import,merge,textured,hidden,vsmd")
    parser.add_argument("--window", type=int, default=6)
    parser.add_argument("--samples", type=int, default=5)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
