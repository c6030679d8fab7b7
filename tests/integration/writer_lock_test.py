#!/usr/bin/python3
"""One writer per model, across processes, as a user meets it: the real vsmd and the real vsm.

    /usr/bin/python3 writer_lock_test.py --vsm <vsm> --vsmd <vsmd> --data <shared/data>
                                         --work <dir>

1. vsmd serves a model; `vsm merge` into it exits 1 at once with one line naming vsmd and its
   pid, and the model's files keep their bytes. A merge into a copy, and `vsm merge --out` from
   the served model (a reader), both work meanwhile.
2. A `vsm merge` in progress (stopped with SIGSTOP while it holds the lock): vsmd opens that
   directory for reading only, and a merge job into it answers 409 naming vsm and its pid; once
   the merge is done, vsmd follows it (the read-only opening is read again when the hierarchy file
   is replaced) and serves the merged version, the new patches included; closed and opened again,
   the model is the merged version too.
3. A model on a read-only mount (a read-only bind mount, as root) is served for reading; a merge
   job into it fails with a message saying so. Skipped, with a line saying why, where mounting is
   not allowed.
"""

import argparse
import functools
import os
import shutil
import signal
import subprocess
import sys
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import Daemon  # noqa: E402
from model_states import crop, digest_tree  # noqa: E402


ARGS = None
TOKEN = "lock-test"


class WriterLock(unittest.TestCase):
    def test_one_writer_per_model(self):
        check = functools.partial(harness.check, self)
        work = os.path.abspath(ARGS.work)
        leftover = os.path.join(work, "root", "readonly")
        if os.path.ismount(leftover):  # an interrupted earlier run's read-only mount
            subprocess.run(["umount", "-l", leftover])
        shutil.rmtree(work, ignore_errors=True)
        root = os.path.join(work, "root")
        os.makedirs(root)
        target_tif = crop(os.path.join(ARGS.data, "PRISMelevation.tif"),
                          os.path.join(work, "target.tif"), -84.8, 36.8, -83.8, 35.8)
        detail = os.path.join(work, "detail")
        served = os.path.join(root, "served")
        for tif, out in ((target_tif, served),
                         (os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), detail)):
            harness.import_dem(tif, out, 17, timeout=300)
        spare = os.path.join(work, "spare")
        shutil.copytree(served, spare)

        # 3. A read-only copy: a read-only bind mount of a model directory inside the data root.
        readonly = os.path.join(root, "readonly")
        shutil.copytree(spare, readonly)
        mounted = subprocess.run(["mount", "--bind", "-o", "ro", readonly, readonly],
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 text=True).returncode == 0 and \
            subprocess.run(["mount", "-o", "remount,bind,ro", readonly],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode == 0
        if not mounted:
            subprocess.run(["umount", readonly], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            shutil.rmtree(readonly)
            print("skip a read-only mount: mounting is not allowed here")

        daemon = Daemon("--token", TOKEN, root=root, port_file=os.path.join(work, "port"),
                        log_path=os.path.join(work, "vsmd.log"), start_deadline=30)
        try:
            status, _, _ = daemon.json("GET", "/v1/models/served")
            check(status == 200, "vsmd serves the model")

            # 1. A second writer fails at once, naming the holder, and changes nothing.
            before = digest_tree(served)
            started = time.monotonic()
            result = harness.vsm("merge", served, detail)
            seconds = time.monotonic() - started
            lines = [line for line in result.stderr.splitlines() if line.strip()]
            print("     vsm merge into the served model: exit %d in %.2f s: %s" %
                  (result.returncode, seconds, " / ".join(lines)))
            check(result.returncode == 1, "vsm merge into a model vsmd serves exits 1")
            check(len(lines) == 1 and lines[0] == "vsm: error: '%s' is being written by vsmd "
                  "(pid %d); one writer per model at a time" % (served, daemon.pid),
                  "its one line names vsmd and its pid")
            check(digest_tree(served) == before, "the served model keeps every byte")
            out = os.path.join(work, "merged-out")
            result = harness.vsm("merge", served, detail, "--out", out)
            check(result.returncode == 0, "vsm merge --out from the served model works (a reader)" +
                  ("" if result.returncode == 0 else ": " + result.stderr[-300:]))
            check(digest_tree(served) == before, "... and leaves the served model as it was")
            result = harness.vsm("merge", spare, detail)
            check(result.returncode == 0, "a merge into another directory works meanwhile")

            # 2. vsmd cannot open a model a vsm merge is writing: 409 naming it.
            busy = os.path.join(root, "busy")
            shutil.copytree(served, busy)  # its copied lock file is no lock
            merge = subprocess.Popen([ARGS.vsm, "merge", busy, detail], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)
            # Its first progress line comes after the lock is taken.
            first = merge.stderr.readline()
            merge.send_signal(signal.SIGSTOP)
            status, _, body = daemon.json("POST", "/v1/models",
                                          {"id": "busy", "source": {"path": "busy"}})
            print("     POST /v1/models during the merge (%s): %d" % (first.strip(), status))
            check(status == 201, "vsmd opens a model another process is writing, for reading only")
            status, _, body = daemon.json("POST", "/v1/jobs",
                                          {"type": "merge", "target": "busy", "source": "served"})
            message = (body or {}).get("error", {}).get("message", "")
            print("     POST /v1/jobs merge into it: %d %s" % (status, message))
            check(status == 409 and "is being written by vsm (pid %d)" % merge.pid in message,
                  "a merge job into it answers 409 naming the vsm merge that holds the lock")
            status, _, unmerged = daemon.json("GET", "/v1/models/busy")
            merge.send_signal(signal.SIGCONT)
            merge.stderr.read()
            check(merge.wait(timeout=300) == 0, "the merge completes")
            finished = time.monotonic()
            followed = None
            while time.monotonic() < finished + 20:
                status, _, now = daemon.json("GET", "/v1/models/busy")
                if status == 200 and now.get("depth", 0) > unmerged.get("depth", 0):
                    followed = time.monotonic() - finished
                    break
                time.sleep(0.05)
            print("     vsmd serves the merged version %s" %
                  ("%.2f s after the merge exited" % followed if followed is not None else "never"))
            check(followed is not None, "vsmd follows the publish of the other writer (depth %s, "
                  "before %s)" % (now.get("depth"), unmerged.get("depth")))
            status, _, tree = daemon.json("GET", "/v1/models/busy/hierarchy")
            deepest = max(harness.keys(tree), key=lambda k: int(k.split("_")[0]))
            status, _, data = daemon.request("GET", "/v1/models/busy/patches/%s/positions" % deepest,
                                             timeout=30)
            check(status == 200 and len(data) > 13, "... and serves its new patches (%s)" % deepest)
            status, _, _ = daemon.json("DELETE", "/v1/models/busy")
            check(status in (200, 204), "closing the read-only model: %d" % status)
            status, _, body = daemon.json("POST", "/v1/models",
                                          {"id": "busy", "source": {"path": "busy"}})
            check(status in (200, 201), "opening it again after the merge: %d" % status)
            status, _, merged = daemon.json("GET", "/v1/models/busy")
            status_served, _, original = daemon.json("GET", "/v1/models/served")
            check(status == 200 and merged.get("depth", 0) > original.get("depth", 0),
                  "... as the merged version (depth %s, the unmerged one %s)" %
                  (merged.get("depth"), original.get("depth")))

            if mounted:
                status, _, _ = daemon.json("GET", "/v1/models/readonly")
                check(status == 200, "a model on a read-only mount is served")
                status, _, body = daemon.json(
                    "POST", "/v1/jobs", {"type": "merge", "target": "readonly", "source": "served"})
                job = body.get("id") if status == 202 else None
                deadline = time.monotonic() + 60
                while job and time.monotonic() < deadline:
                    status, _, body = daemon.json("GET", "/v1/jobs/" + job)
                    if body["state"] in ("succeeded", "failed", "cancelled"):
                        break
                    time.sleep(0.05)
                message = (body.get("error") or {}).get("message", "")
                check(status == 409 and "for reading only" in message,
                      "a merge job into it answers 409 saying it is open for reading only: %s" %
                      message)
        finally:
            check(daemon.stop(timeout=60) == 0, "vsmd exits 0 on SIGTERM")
            if mounted:
                subprocess.run(["umount", readonly])


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
