#!/usr/bin/python3
"""The client examples against the real daemon: vsmd on 127.0.0.1:0 (harness.py)
over a data root holding PRISM (target) and Jacksboro (detail) imported by `vsm import` at 65 x 65,
and a copy of PRISM for the curl walk-through's merge. Runs client-examples/curl.sh, the Python
client (with the real-data merge PRISM + Jacksboro as a job, its printed progress rising to 1) and
the C++ client, and checks what they print against the daemon's own answers. The Python client's
merge is held mid-way (its file creations under PRISM wait at a gate of the LD_PRELOAD library
tests/fault/fault_inject.c, hold.py) until the client has printed progress between 0 and 1, so
that it does on any machine. Run by ctest:
    clients_test.py --vsmd build/server/vsmd --vsm build/server/cli/vsm --data ../shared/data \\
        --proto proto --clients client-examples --cpp-client build/.../vsm_client_example \\
        --lib build/tests/fault/libvsm_fault_inject.so"""

import argparse
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from hold import Hold, poll  # noqa: E402
from harness import Daemon  # noqa: E402

TOKEN = "clients-token-0123456789"
PATCH = 65
ARGS = None


class Clients(unittest.TestCase):
    daemon = None

    @classmethod
    def setUpClass(cls):
        def prepare(root):
            harness.import_dem(os.path.join(ARGS.data, "PRISMelevation.tif"),
                               os.path.join(root, "prism"), PATCH)
            harness.import_dem(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"),
                               os.path.join(root, "jacksboro"), PATCH)
            shutil.copytree(os.path.join(root, "prism"), os.path.join(root, "prism-curl"))

        root = tempfile.mkdtemp(prefix="vsmd-test-")
        prepare(root)
        cls.gate = tempfile.mkdtemp(prefix="vsmd-gate-")
        cls.hold = Hold(ARGS.lib, os.path.join(root, "prism"), "create",
                        os.path.join(cls.gate, "gate"))
        cls.daemon = Daemon("--token", TOKEN, "--memory-budget", "256MiB", root=root,
                            env=cls.hold.env())
        cls.url = cls.daemon.base

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is None:
            return
        try:
            cls.hold.release()
            shutil.rmtree(cls.gate, ignore_errors=True)
            code = cls.daemon.stop()
            if code != 0:
                raise AssertionError("vsmd exited %d:\n%s" % (code, cls.daemon.log()))
        finally:
            cls.daemon.cleanup()

    def run_client(self, args, env=None, timeout=900):
        result = subprocess.run(args, capture_output=True, text=True, timeout=timeout,
                                env={**os.environ, **(env or {})})
        self.assertEqual(result.returncode, 0,
                         "%s exited %d\nstdout:\n%s\nstderr:\n%s"
                         % (args[0], result.returncode, result.stdout, result.stderr))
        return result.stdout

    def merge_held_mid_way(self, args):
        """Runs the client's merge (`args`) with the merge held at a file creation where its
        progress is between 0 and 1 until the client has printed such progress; its stdout."""
        hold = self.hold
        allowed = hold.let_through(hold.calls())  # the merge's next creation waits
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        lines = []
        reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")))
        reader.start()

        def printed_progress():
            return [float(p) for p in re.findall(r"^progress ([0-9.]+) ", "".join(list(lines)),
                                                  re.M)]

        try:
            submitted = poll(lambda: next((m for m in (re.match(r"job (\S+) submitted", line)
                                                        for line in list(lines)) if m), None)
                             or proc.poll() is not None)
            self.assertTrue(submitted is not None and submitted is not True, "".join(lines))
            job_id = submitted.group(1)

            def ended():
                job = self.daemon.get_json("/v1/jobs/" + job_id)[2]
                return job["state"] not in ("queued", "running")

            while True:
                self.assertIsNotNone(hold.wait_held(allowed + 1, ended=ended),
                                     "the merge ended before it was seen mid-way")
                job = self.daemon.get_json("/v1/jobs/" + job_id)[2]
                if job["state"] == "running" and 0 < round(job["progress"], 3) < 1:
                    break
                allowed = hold.let_through(allowed + 8)
            # The client prints it once the daemon's event (held back at most 250 ms) reaches it.
            self.assertTrue(poll(lambda: any(0 < p < 1 for p in printed_progress())),
                            "the client printed no progress of the held merge (%.3f):\n%s"
                            % (job["progress"], "".join(lines)))
        finally:
            hold.release()
            try:
                proc.wait(timeout=900)
            finally:
                proc.kill()
                reader.join()
        err = proc.stderr.read()
        proc.stdout.close()
        proc.stderr.close()
        self.assertEqual(proc.returncode, 0, "%s exited %d\nstdout:\n%s\nstderr:\n%s"
                         % (args[0], proc.returncode, "".join(lines), err))
        return "".join(lines)

    def test_cpp_client_lists_models_and_decodes_a_patch(self):
        out = self.run_client([ARGS.cpp_client, "--port", str(self.daemon.port), "jacksboro"])
        _, _, listed = self.daemon.get_json("/v1/models")
        self.assertIn("models: %d" % len(listed["models"]), out)
        for model in listed["models"]:
            self.assertIn("model %s: version %d, %d patches" % (model["id"], model["version"],
                                                               model["patches"]), out)
        self.assertIn("aara header: type V3f, %d x %d, data at byte 13" % (PATCH, PATCH), out)
        self.assertIn("vertices: %d, defined " % (PATCH * PATCH), out)
        _, headers, data = self.daemon.request(
            "GET", "/v1/models/jacksboro/patches/0_0_0/positions")
        self.assertIn("patch jacksboro/0_0_0: %d bytes, etag %s" % (len(data), headers["ETag"]),
                      out)
        defined = sum(1 for i in range(13, len(data), 12)
                      if struct.unpack_from("<f", data, i)[0] == struct.unpack_from("<f", data, i)[0])
        self.assertIn("defined %d" % defined, out)
        self.assertIn("local2global: " + headers["X-VSM-Local2Global"], out)

    def test_curl_walkthrough_reads_everything_and_merges(self):
        out = self.run_client(["bash", os.path.join(ARGS.clients, "curl.sh"), "prism-curl",
                               "jacksboro"], env={"VSM_URL": self.url, "VSM_TOKEN": TOKEN})
        self.assertIn('{"status":"ok"}', out)
        self.assertIn('{"status":"ready"}', out)
        self.assertRegex(out, r"leaf: \d+_\d+_\d+")
        self.assertRegex(out, r'etag: "[^"]+"')
        self.assertIn("positions: %d bytes, type V3f, %d x %d vertices"
                      % (13 + PATCH * PATCH * 12, PATCH, PATCH), out)
        self.assertIn("conditional GET: 304, 0 body bytes", out)
        self.assertRegex(out, r'\{"model":"prism-curl","version":1,"resolution":[0-9.e+]+,'
                              r'"patches":[1-9]\d*,')
        job = re.search(r"job (\w+) succeeded", out)
        self.assertIsNotNone(job, out)
        self.assertIn("  succeeded done 100%", out)
        _, _, summary = self.daemon.get_json("/v1/models/prism-curl")
        self.assertEqual(summary["version"], 2)
        _, _, diff = self.daemon.get_json("/v1/models/prism-curl/diff?from=1&to=2")
        self.assertIn('"changed_patches":%d,' % diff["totals"]["changed_patches"], out)
        self.assertRegex(out, r"diff\.png: \d+ bytes, displacement from revision 1 to 2")
        self.assertIn("walk-through done", out)

    def test_python_client_walks_downloads_and_merges_prism_with_jacksboro(self):
        client = [ARGS.python, os.path.join(ARGS.clients, "python", "vsm_client.py"),
                  "--url", self.url, "--token", TOKEN]
        _, _, before = self.daemon.get_json("/v1/models/prism")
        self.assertEqual(before["version"], 1)

        out = self.run_client(client + ["walk", "prism"])
        self.assertIn("hierarchy prism version 1: %d nodes, %d leaves"
                      % (before["patches"], before["leaves"]), out)
        self.assertEqual(len(re.findall(r"^level \d+:", out, re.M)), before["depth"] + 1)

        path = os.path.join(self.daemon.dir, "root.aara")
        out = self.run_client(client + ["patch", "prism", "0_0_0", "--out", path])
        self.assertIn("aara: type V3f, sizes %dx%d, %d vertices" % (PATCH, PATCH, PATCH * PATCH),
                      out)
        self.assertIn("inside box: yes", out)
        self.assertIn("conditional GET with the etag: 304 not modified", out)
        with open(path, "rb") as f:
            self.assertEqual(f.read(), self.daemon.request(
                "GET", "/v1/models/prism/patches/0_0_0/positions")[2])

        out = self.merge_held_mid_way(client + ["merge", "prism", "jacksboro"])
        progress = [float(p) for p in re.findall(r"^progress ([0-9.]+) ", out, re.M)]
        self.assertGreater(len(progress), 2, out)
        self.assertEqual(progress, sorted(progress), "progress went down:\n" + out)
        self.assertEqual(progress[-1], 1.0, out)
        self.assertTrue(any(0 < p < 1 for p in progress), out)
        self.assertRegex(out, r"job \w+ succeeded in [0-9.]+ s")
        self.assertIn("result: version 1 -> 2", out)
        _, _, after = self.daemon.get_json("/v1/models/prism")
        self.assertEqual(after["version"], 2)
        self.assertGreater(after["patches"], before["patches"])
        self.assertGreater(after["depth"], before["depth"])

        # What the merge changed, as the client reads it: the route's totals.
        png = os.path.join(self.daemon.dir, "diff.png")
        out = self.run_client(client + ["diff", "prism", "1", "2", "--png", png, "--size", "300"])
        _, _, diff = self.daemon.get_json("/v1/models/prism/diff?from=1&to=2")
        totals = diff["totals"]
        self.assertGreater(totals["changed_patches"], 0)
        self.assertIn("diff prism 1 -> 2: %d patches changed, 0 removed, %d shared"
                      % (totals["changed_patches"], totals["shared_patches"]), out)
        self.assertIn("rms %.4f" % totals["rms"], out)
        self.assertIn("red +%.4g m" % totals["max_abs"], out)
        with open(png, "rb") as f:
            self.assertEqual(f.read(8), b"\x89PNG\r\n\x1a\n")

    def test_python_client_reports_errors_as_one_line(self):
        result = subprocess.run([ARGS.python, os.path.join(ARGS.clients, "python", "vsm_client.py"),
                                 "--url", self.url, "walk", "no-such-model"],
                                capture_output=True, text=True, timeout=60)
        self.assertEqual(result.returncode, 1)
        self.assertIn("vsm_client: HTTP 404 not_found:", result.stderr)
        result = subprocess.run([ARGS.python, os.path.join(ARGS.clients, "python", "vsm_client.py"),
                                 "--url", self.url, "merge", "prism", "jacksboro"],
                                capture_output=True, text=True, timeout=60)
        self.assertEqual(result.returncode, 1)
        self.assertIn("vsm_client: HTTP 401 unauthorized:", result.stderr)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--proto", required=True)
    parser.add_argument("--clients", required=True)
    parser.add_argument("--cpp-client", required=True)
    parser.add_argument("--lib", required=True, help="libvsm_fault_inject.so (tests/fault)")
    parser.add_argument("--python", default=sys.executable)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
