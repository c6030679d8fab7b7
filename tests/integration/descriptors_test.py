#!/usr/bin/python3
"""Descriptors are a bounded resource: vsmd under `ulimit -n 1024` (soft and hard), with the
default memory budget, serving a model of 5461 patches (more than the limit allows files open)
to 8 clients that each read every patch's positions once, on keep-alive connections. Every
answer is 200 with the stored bytes, the daemon never holds more descriptors than its limit
allows, and new connections are still accepted afterwards.

Run by ctest:
    descriptors_test.py --vsmd build/server/vsmd --vsm build/server/cli/vsm"""

import argparse
import http.client
import json
import os
import random
import resource
import shutil
import socket
import sys
import tempfile
import threading
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import Daemon, write_dem  # noqa: E402

ARGS = None
LIMIT = 1024
CLIENTS = 8
# A 513 x 513 DEM in patches of 9 x 9: 64 x 64 leaves and every overview, 5461 patches.
DEM_SIZE = 513
PATCH_SIZE = 9
PATCHES = sum(4 ** d for d in range(7))


def limit_descriptors():
    resource.setrlimit(resource.RLIMIT_NOFILE, (LIMIT, LIMIT))


class DescriptorLimit(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.dir = tempfile.mkdtemp(prefix="vsmd-descriptors-")
        write_dem(os.path.join(cls.dir, "dem.asc"), DEM_SIZE, slope=0.0)
        harness.import_dem(os.path.join(cls.dir, "dem.asc"), os.path.join(cls.dir, "data", "many"),
                           PATCH_SIZE)
        # The default budget (1 GiB), the default connection limit (512).
        cls.daemon = Daemon("--log-level", "info", root=os.path.join(cls.dir, "data"),
                            port_file=os.path.join(cls.dir, "port"),
                            log_path=os.path.join(cls.dir, "vsmd.log"),
                            preexec_fn=limit_descriptors, start_deadline=60)
        cls.proc = cls.daemon.proc
        cls.port = cls.daemon.port

    @classmethod
    def tearDownClass(cls):
        try:
            code = cls.daemon.stop(timeout=30)
        except AssertionError:
            code = None
        if code == 0:
            shutil.rmtree(cls.dir, ignore_errors=True)
        else:
            print("vsmd exited %s; kept %s" % (code, cls.dir), file=sys.stderr)

    @classmethod
    def log(cls):
        return cls.daemon.log()

    def get(self, conn, path):
        conn.request("GET", path)
        response = conn.getresponse()
        return response.status, response.read()

    def descriptors(self):
        return len(os.listdir("/proc/%d/fd" % self.proc.pid))

    def test_every_patch_read_by_eight_clients_is_200_and_connections_are_accepted_after(self):
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=30)
        status, body = self.get(conn, "/v1/models/many/hierarchy")
        self.assertEqual(status, 200, body[:300])

        def walk(node):
            yield node["key"]
            for child in node.get("children", []):
                yield from walk(child)
        keys = list(walk(json.loads(body)["root"]))
        self.assertEqual(len(keys), PATCHES)
        self.assertGreater(len(keys), 5000)
        self.assertIn("soft limit %d" % LIMIT, self.log())
        self.assertIn("hard limit %d" % LIMIT, self.log())

        failures = []
        counts = [0] * CLIENTS
        peak = [0]
        # Every answer's bytes are checked against the stored file for a sample of patches
        # stored whole (cropped ones come out as the full grid, longer than their file).
        expected = {}
        for key in random.Random(1).sample(keys, 64):
            with open(os.path.join(self.dir, "data", "many", "Patches", key,
                                   "Positions.aara"), "rb") as f:
                expected[key] = f.read()

        def client(index):
            order = keys[:]
            random.Random(index).shuffle(order)
            c = http.client.HTTPConnection("127.0.0.1", self.port, timeout=60)
            try:
                for n, key in enumerate(order):
                    status, data = self.get(c, "/v1/models/many/patches/%s/positions" % key)
                    if status != 200:
                        failures.append((key, status, data[:200]))
                        return
                    if len(data) != 13 + PATCH_SIZE * PATCH_SIZE * 12:
                        failures.append((key, "length", len(data)))
                        return
                    if key in expected and len(expected[key]) == len(data) and \
                            expected[key] != data:
                        failures.append((key, "bytes differ from the stored file"))
                        return
                    counts[index] += 1
                    if n % 500 == 0:
                        peak[0] = max(peak[0], self.descriptors())
            except (OSError, http.client.HTTPException) as e:
                failures.append(("connection", repr(e)))
            finally:
                c.close()

        threads = [threading.Thread(target=client, args=(i,)) for i in range(CLIENTS)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=600)
        self.assertEqual(failures, [], self.log()[-3000:])
        self.assertEqual(counts, [PATCHES] * CLIENTS)
        self.assertLess(peak[0], LIMIT)

        status, body = self.get(conn, "/v1/stats")
        self.assertEqual(status, 200)
        memory = json.loads(body)["memory"]
        self.assertLessEqual(memory["open_files"], memory["open_files_limit"])
        self.assertLess(memory["open_files_limit"], LIMIT)
        self.assertGreater(memory["open_files"], 0)
        self.assertLessEqual(memory["resident_bytes"], memory["budget_bytes"])
        conn.close()

        # New connections are still accepted: 200 at once, each answered.
        sockets = []
        try:
            for _ in range(200):
                sockets.append(socket.create_connection(("127.0.0.1", self.port), timeout=10))
            for s in sockets:
                s.sendall(b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n")
            for s in sockets:
                self.assertTrue(s.recv(64).startswith(b"HTTP/1.1 200"))
        finally:
            for s in sockets:
                s.close()
        self.assertLess(self.descriptors(), LIMIT)
        self.assertNotIn("Too many open files", self.log())


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--vsm", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)
