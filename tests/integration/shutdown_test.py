#!/usr/bin/python3
"""SIGTERM loses nothing: the real vsmd on 127.0.0.1:0 (harness.py) with a memory
budget so small that a merge of Jacksboro into PRISM (both imported by `vsm import` at 65 x 65)
writes dirty patches back to disk before it publishes. SIGTERM while that merge runs (held
mid-way, after write-backs, by the LD_PRELOAD library of tests/fault, so on any machine), SIGTERM
after it published, and SIGTERM with a patch download in flight: vsmd exits 0 every time, and the
model reopens (`vsm validate` passes, a fresh daemon serves it) as exactly the old version or the
new one. Run by ctest:
    shutdown_test.py --vsmd build/server/vsmd --vsm build/server/cli/vsm --data ../shared/data \\
        --proto proto --lib build/tests/fault/libvsm_fault_inject.so"""

import argparse
import os
import re
import shutil
import signal
import socket
import struct
import sys
import tempfile
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from hold import Hold, poll  # noqa: E402
from harness import Daemon  # noqa: E402

TOKEN = "shutdown-token-0123456789"
PATCH = 65
# 65 x 65 positions are 50 KiB: a few dozen patches fit, a merge makes a few hundred.
BUDGET = "3MiB"
ARGS = None


class Shutdown(unittest.TestCase):
    """Each test copies the pristine models (imported once) into a fresh data root."""

    pristine = None

    @classmethod
    def setUpClass(cls):
        cls.pristine = tempfile.mkdtemp(prefix="vsmd-shutdown-")
        harness.import_dem(os.path.join(ARGS.data, "PRISMelevation.tif"),
                           os.path.join(cls.pristine, "prism"), PATCH)
        harness.import_dem(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"),
                           os.path.join(cls.pristine, "jacksboro"), PATCH)
        # 257 x 257 patches (774 KiB each): eight of them overflow a socket's send buffer.
        harness.import_dem(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"),
                           os.path.join(cls.pristine, "jacksboro257"), 257)

    @classmethod
    def tearDownClass(cls):
        if cls.pristine is not None:
            shutil.rmtree(cls.pristine, ignore_errors=True)

    def setUp(self):
        self.daemons = []

    def tearDown(self):
        for daemon in self.daemons:
            daemon.cleanup()

    def start(self, root=None, *flags, models=("prism", "jacksboro"), env=None):
        def prepare(dir):
            for name in models:
                shutil.copytree(os.path.join(self.pristine, name), os.path.join(dir, name))

        daemon = Daemon("--token", TOKEN, "--memory-budget", BUDGET, *flags,
                        prepare=None if root else prepare, root=root, env=env)
        self.daemons.append(daemon)
        return daemon

    def model_state(self, daemon):
        """What identifies a published version: the summary's ETag, the tree, and a hash of the
        positions of every patch."""
        status, headers, summary = daemon.get_json("/v1/models/prism")
        self.assertEqual(status, 200, summary)
        keys = sorted(daemon.keys("prism"))
        conn = daemon.connection(timeout=30)
        data = {}
        try:
            for key in keys:
                conn.request("GET", "/v1/models/prism/patches/%s/positions" % key)
                response = conn.getresponse()
                body = response.read()
                self.assertEqual(response.status, 200, key)
                data[key] = hash(body)
        finally:
            conn.close()
        return {"etag": headers["ETag"], "patches": summary["patches"],
                "depth": summary["depth"], "keys": keys, "data": data}

    def stop_and_reopen(self, daemon):
        """SIGTERM (exit 0, no leftovers of an edit), `vsm validate`, then a fresh daemon on the
        same data root; returns the reopened state and the first daemon's log."""
        self.assertEqual(daemon.stop(timeout=60), 0, daemon.log())
        log = daemon.log()  # the reopened daemon writes the same file
        self.assertIn("stopped", log)
        result = harness.vsm("validate", os.path.join(daemon.dir, "prism"))
        self.assertEqual(result.returncode, 0, result.stdout + result.stderr)
        reopened = self.start(daemon.dir)
        state = self.model_state(reopened)
        self.assertEqual(reopened.stop(), 0, reopened.log())
        self.assertIn("stopped", reopened.log())
        return state, log

    def test_sigterm_during_a_merge_that_wrote_dirty_patches_reopens_the_old_version(self):
        # The merge's file creations under PRISM wait at a gate the test opens step by step, so
        # the merge is still running at SIGTERM on any machine, however fast.
        root = tempfile.mkdtemp(prefix="vsmd-test-")
        for name in ("prism", "jacksboro"):
            shutil.copytree(os.path.join(self.pristine, name), os.path.join(root, name))
        gate = tempfile.mkdtemp(prefix="vsmd-gate-")
        self.addCleanup(shutil.rmtree, gate, True)
        hold = Hold(ARGS.lib, os.path.join(root, "prism"), "create", os.path.join(gate, "gate"))
        self.addCleanup(hold.release)  # also when a check below fails: the daemon can stop
        daemon = self.start(root, env=hold.env())
        before = self.model_state(daemon)
        allowed = hold.let_through(hold.calls())
        job_id = daemon.submit({"type": "merge", "target": "prism", "source": "jacksboro"})["id"]

        def ended():
            return daemon.get_json("/v1/jobs/" + job_id)[2]["state"] not in ("queued", "running")

        # Held at a creation after the budget forced dirty patches out to disk.
        while True:
            self.assertIsNotNone(hold.wait_held(allowed + 1, ended=ended),
                                 "the merge ended without a write-back")
            if daemon.get_json("/v1/stats")[2]["cache"]["write_backs"] > 0:
                break
            allowed = hold.let_through(allowed + 8)
        _, _, job = daemon.get_json("/v1/jobs/" + job_id)
        self.assertEqual(job["state"], "running", job)
        daemon.proc.send_signal(signal.SIGTERM)
        # The merge goes on once the daemon has asked it to stop: it stops at its next check.
        self.assertTrue(poll(lambda: "job=%s cancel requested" % job_id in daemon.log()),
                        daemon.log())
        hold.release()
        after, log = self.stop_and_reopen(daemon)
        outcome = re.search(r"job=%s (succeeded|cancelled)" % job_id, log)
        self.assertIsNotNone(outcome, log)
        print("\n  merge at SIGTERM: %s %.3f, then %s"
              % (job["stage"], job["progress"], outcome.group(1)), file=sys.stderr)
        self.assertEqual(outcome.group(1), "cancelled")
        self.assertEqual(after, before)
        leftovers = [n for n in os.listdir(os.path.join(daemon.dir, "prism", "Patches"))
                     if re.search(r"-v2(-[0-9a-f]{8})?$", n)]
        self.assertEqual(leftovers, [], "the cancelled edit left folders")

    def test_what_an_interrupted_edit_left_goes_once_the_daemon_serves(self):
        # Leftovers of a killed writer: a draft folder and tile named like vsm's, which no kept
        # revision names, and a temporary file. vsmd opens without listing Patches/ (a folder per
        # patch) and removes them in its housekeeping, after it answers; the model is untouched.
        root = tempfile.mkdtemp(prefix="vsmd-test-")
        shutil.copytree(os.path.join(self.pristine, "prism"), os.path.join(root, "prism"))
        patches = os.path.join(root, "prism", "Patches")
        draft = os.path.join(patches, "1_0_0-v9-0badf00d")
        os.mkdir(draft)
        with open(os.path.join(draft, "Patch.xml"), "w") as f:
            f.write("half written")
        temp = os.path.join(patches, ".patchhierarchy.xml.tmp-1-0")
        with open(temp, "w") as f:
            f.write("<Aard")
        mine = os.path.join(patches, "notes")  # not named like vsm's: never touched
        os.mkdir(mine)
        daemon = self.start(root, models=("prism",))
        self.assertTrue(poll(lambda: not os.path.exists(draft) and not os.path.exists(temp),
                             timeout=60), daemon.log())
        self.assertIn("removing leftover 1_0_0-v9-0badf00d", daemon.log())
        self.assertTrue(os.path.isdir(mine))
        os.rmdir(mine)
        result = harness.vsm("validate", os.path.join(root, "prism"))
        self.assertEqual(result.returncode, 0, result.stdout + result.stderr)
        self.model_state(daemon)  # every patch still served

    def test_sigterm_after_a_merge_published_reopens_the_new_version(self):
        daemon = self.start()
        before = self.model_state(daemon)
        job_id = daemon.submit({"type": "merge", "target": "prism", "source": "jacksboro"})["id"]
        job = daemon.wait_job(job_id, until=lambda j: j["state"] in ("succeeded", "failed"),
                              interval=0.01)
        self.assertEqual(job["state"], "succeeded", job)
        _, _, stats = daemon.get_json("/v1/stats")
        self.assertGreater(stats["cache"]["write_backs"], 0, "the budget never forced a write-back")
        self.assertLessEqual(stats["memory"]["resident_bytes"], stats["memory"]["budget_bytes"])
        merged = self.model_state(daemon)
        self.assertGreater(merged["patches"], before["patches"])
        self.assertEqual(self.stop_and_reopen(daemon)[0], merged)

    def test_sigterm_finishes_a_patch_download_in_flight_then_exits_0(self):
        daemon = self.start()
        # More answers than the socket's buffers hold (about 6 MB against 4 MB), so vsmd is still writing them
        # when the last request begins to arrive.
        tree_keys = daemon.keys("prism")
        keys = [tree_keys[i % len(tree_keys)] for i in range(120)]
        # A small receive window, so the answers wait in vsmd until read below (not in the
        # kernel's buffers).
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.settimeout(30)
        sock.connect(("127.0.0.1", daemon.port))
        with sock:
            # Pipelined downloads, the last one's request not yet complete.
            requests = [b"GET /v1/models/prism/patches/%s/positions HTTP/1.1\r\nHost: x\r\n"
                        b"\r\n" % k.encode() for k in keys]
            sock.sendall(b"".join(requests[:-1]))
            # The first answer has begun: vsmd is reading the pipeline (peeked, so it is read below).
            deadline = time.monotonic() + 10
            while not sock.recv(16, socket.MSG_PEEK).startswith(b"HTTP/1.1 200"):
                self.assertLess(time.monotonic(), deadline, "no answer to the pipelined requests")
            # The last begins while the others are answered (their bodies fill the socket, which
            # is not read yet): it arrives behind them, and must be read after SIGTERM too.
            sock.sendall(requests[-1][:-2])
            time.sleep(0.2)
            daemon.proc.send_signal(signal.SIGTERM)
            # A negative check needs a window: vsmd must still be running with a request unfinished.
            time.sleep(0.3)
            self.assertIsNone(daemon.proc.poll(), "vsmd exited with requests in flight")
            sock.sendall(requests[-1][-2:])
            reader = sock.makefile("rb")
            for i, key in enumerate(keys):
                status_line = reader.readline()
                self.assertIn(b" 200 ", status_line, key)
                length, close = 0, False
                while True:
                    line = reader.readline().strip()
                    if not line:
                        break
                    name, _, value = line.partition(b":")
                    if name.lower() == b"content-length":
                        length = int(value)
                    if name.lower() == b"connection" and value.strip().lower() == b"close":
                        close = True
                body = reader.read(length)
                self.assertEqual(len(body), 13 + PATCH * PATCH * 12, key)
                self.assertEqual(body[:5], b"\x03V3f\x02")
                self.assertEqual(close, i == len(keys) - 1, "Connection: close on the last only")
            self.assertEqual(reader.read(1), b"")
        self.assertEqual(daemon.proc.wait(timeout=30), 0, daemon.log())
        self.assertIn("stopped", daemon.log())
        with self.assertRaises(OSError):
            socket.create_connection(("127.0.0.1", daemon.port), timeout=2).close()

    def test_clients_that_vanish_mid_download_do_not_stop_vsmd(self):
        # Patch data goes out by sendfile(2), which raises SIGPIPE on a connection the peer reset
        # unless the network threads block it.
        daemon = self.start(models=("jacksboro257",))
        keys = daemon.keys("jacksboro257")
        keys = (keys * 8)[:8]
        requests = b"".join(b"GET /v1/models/jacksboro257/patches/%s/positions HTTP/1.1\r\nHost: x\r\n"
                            b"\r\n" % k.encode() for k in keys)
        for _ in range(20):
            sock = socket.socket()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            sock.connect(("127.0.0.1", daemon.port))
            sock.sendall(requests)
            sock.recv(100)
            time.sleep(0.02)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            sock.close()  # a reset, with most of the bodies unsent
        time.sleep(0.3)
        self.assertIsNone(daemon.proc.poll(), daemon.log())
        self.assertEqual(daemon.get_json("/healthz")[0], 200)
        status, _, data = daemon.request("GET",
                                         "/v1/models/jacksboro257/patches/%s/positions" % keys[0])
        self.assertEqual((status, len(data)), (200, 13 + 257 * 257 * 12))
        self.assertEqual(daemon.stop(), 0, daemon.log())
        self.assertRegex(daemon.log(), r'error="(Broken pipe|Connection reset by peer)"',
                         "no download was cut short: the test tests nothing")


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--proto", required=True)
    parser.add_argument("--lib", required=True, help="libvsm_fault_inject.so (tests/fault)")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
