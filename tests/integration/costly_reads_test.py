#!/usr/bin/python3
"""Bounded costly reads (issue 32, finding 7): the real vsmd on 127.0.0.1:0, a synthetic DEM model
imported by the real `vsm` and merged three times by `vsm merge` (revisions 1..3 kept, 4 current),
driven over HTTP. Nothing waits for a time: reads are held at a file-system call by the LD_PRELOAD
library of tests/fault (class `read`: opens for reading) and states are polled.

    /usr/bin/python3 costly_reads_test.py --vsm <vsm> --vsmd <vsmd> --lib <fault lib> --work <dir>

1. Single flight: N concurrent `?rev=1` reads while the first one is held at the open of
   Patches/vsm-revision-1.xml read that file once; the others wait for that read
   (/v1/stats reads.revisions: reads 1, shared_reads N-1) and all answer revision 1.
2. Terrain layers of old revisions are built once: layer.json?rev=1,2,3 and again 1,2,3 build
   each revision's layer once (the daemon's log line "terrain layer of version N"), as the
   revisions stay cached (today's two-entry cache rebuilt revision 1's).
3. Diffs are bounded: with limits.diffs=1, a diff.png held at its first read keeps its slot and
   its map's working memory is charged to the budget (encoded bytes "diff", pinned); a second
   diff meanwhile is 503 with Retry-After; once the first ends, the charge is gone.
4. Diffs stop: one held at its first read past limits.diff_timeout is answered 503 naming the
   limit (diffs.timed_out); one whose client closes the connection while it is held stops at its
   next patch instead of running to the end for nobody (diffs.abandoned), and frees its slot.
"""

import argparse
import json
import os
import shutil
import sys
import threading
import time
import unittest

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import import_dem, write_raster  # noqa: E402
from hold import Hold, poll  # noqa: E402

gdal.UseExceptions()
ARGS = None
MODEL = "base"
CONCURRENT = 4
PNG_SIZE = 512


def make_model(root, work):
    """Revision 1: a 129 x 129 tilted surface over 1 degree; revisions 2..4: a bump merged into a
    different corner each time, 65 x 65 pixels at a quarter of the spacing."""
    rows = np.arange(129, dtype=np.float64)[:, None]
    cols = np.arange(129, dtype=np.float64)[None, :]
    write_raster(os.path.join(work, "base.tif"), 300.0 + 2.0 * cols - 1.5 * rows, -97.0, 34.0,
                 1.0 / 128)
    import_dem(os.path.join(work, "base.tif"), os.path.join(root, MODEL), 33)
    r = np.arange(65, dtype=np.float64)[:, None]
    c = np.arange(65, dtype=np.float64)[None, :]
    for i, (west, north) in enumerate([(-96.9, 33.9), (-96.4, 33.9), (-96.9, 33.4)]):
        detail = os.path.join(work, "detail-%d.tif" % i)
        bump = 50.0 * (i + 1) * np.exp(-((r - 32) ** 2 + (c - 32) ** 2) / 200.0)
        # The base surface there plus the bump (pixel (c, r) at lon west + c * step).
        step = 1.0 / 512
        base_col = (west + 97.0) * 128 + c * step * 128
        base_row = (34.0 - north) * 128 + r * step * 128
        write_raster(detail, 300.0 + 2.0 * base_col - 1.5 * base_row + bump, west, north, step)
        import_dem(detail, detail[:-len(".tif")], 33)
        harness.vsm("merge", os.path.join(root, MODEL), detail[:-len(".tif")], check=True)


def stats(daemon):
    status, _, body = daemon.get_json("/v1/stats")
    assert status == 200, body
    return body


def reads(daemon, group, key):
    """/v1/stats reads.<group>.<key>, or None when the daemon has no such counter."""
    return stats(daemon).get("reads", {}).get(group, {}).get(key)


class Fixture(unittest.TestCase):
    """One model with revisions 1..3 kept and 4 current, shared by the tests (read only)."""

    @classmethod
    def setUpClass(cls):
        work = os.path.join(ARGS.work, "model")
        root = os.path.join(ARGS.work, "root")
        if not os.path.exists(os.path.join(root, MODEL, "Patches", "vsm-revision-3.xml")):
            shutil.rmtree(work, ignore_errors=True)
            shutil.rmtree(root, ignore_errors=True)
            os.makedirs(work)
            os.makedirs(root)
            make_model(root, work)
        cls.root = root
        revisions = sorted(int(n[len("vsm-revision-"):-len(".xml")])
                           for n in os.listdir(os.path.join(root, MODEL, "Patches"))
                           if n.startswith("vsm-revision-") and n.endswith(".xml"))
        assert revisions == [1, 2, 3], revisions

    def start(self, hold, *flags):
        daemon = harness.Daemon(*flags, root=self.root, env=hold.env() if hold else None)
        self.addCleanup(daemon.stop)
        if hold:
            self.addCleanup(hold.release)
        return daemon

    def in_thread(self, daemon, path):
        """GET `path` on a thread of its own; returns (thread, result list)."""
        result = []

        def run():
            conn = daemon.connection(timeout=600)
            try:
                conn.request("GET", path)
                response = conn.getresponse()
                result.append((response.status, dict(response.headers), response.read()))
            finally:
                conn.close()

        thread = threading.Thread(target=run)
        thread.start()
        return thread, result


class SingleFlight(Fixture):
    def test_concurrent_reads_of_an_uncached_revision_read_it_once(self):
        hold = Hold(ARGS.lib, os.path.join(self.root, MODEL, "Patches", "vsm-revision-1.xml"),
                    "read", os.path.join(ARGS.work, "gate-single"))
        daemon = self.start(hold, "--set", "threads.cpu=%d" % (CONCURRENT + 4))
        n = hold.let_through(hold.calls())  # opening the model read it; the next read waits
        requests = [self.in_thread(daemon, "/v1/models/%s?rev=1" % MODEL)
                    for _ in range(CONCURRENT)]
        self.assertIsNotNone(hold.wait_held(n + 1))
        # Every request is in: waiting for the held read, or (without a single flight) held at
        # an open of its own.
        poll(lambda: reads(daemon, "revisions", "waiting") == CONCURRENT - 1
             or hold.calls() >= n + CONCURRENT)
        hold.release()
        for thread, _ in requests:
            thread.join()
        bodies = set()
        for _, result in requests:
            status, _, body = result[0]
            self.assertEqual(status, 200, body)
            self.assertEqual(json.loads(body)["version"], 1)
            bodies.add(body)
        self.assertEqual(len(bodies), 1)
        self.assertEqual(hold.calls() - n, 1, "revision 1's file was read more than once")
        self.assertEqual(reads(daemon, "revisions", "reads"), 1)
        self.assertEqual(reads(daemon, "revisions", "shared_reads"), CONCURRENT - 1)
        self.assertEqual(reads(daemon, "revisions", "waiting"), 0)


class TerrainLayers(Fixture):
    def test_the_layer_of_each_old_revision_is_built_once(self):
        daemon = self.start(None)
        for _ in range(2):
            for rev in (1, 2, 3):
                status, _, body = daemon.get_json("/v1/models/%s/terrain/layer.json?rev=%d"
                                                  % (MODEL, rev))
                self.assertEqual(status, 200, body)
                self.assertEqual(body["model_version"], rev)
        log = daemon.log()
        for rev in (1, 2, 3):
            self.assertEqual(log.count("terrain layer of version %d:" % rev), 1, log)
        self.assertEqual(reads(daemon, "revisions", "reads"), 3)
        self.assertEqual(reads(daemon, "revisions", "cached"), 3)


class Diffs(Fixture):
    def test_a_diff_over_the_bound_is_503_and_the_running_one_is_charged(self):
        hold = Hold(ARGS.lib, os.path.join(self.root, MODEL), "read",
                    os.path.join(ARGS.work, "gate-diff"))
        daemon = self.start(hold, "--set", "limits.diffs=1", "--set", "threads.cpu=6")
        n = hold.let_through(hold.calls())  # the diff's first read (revision 1's file) waits
        first = self.in_thread(daemon, "/v1/models/%s/diff.png?from=1&to=2&size=%d"
                               % (MODEL, PNG_SIZE))
        self.assertIsNotNone(hold.wait_held(n + 1))
        memory = stats(daemon)["memory"]
        charged = memory["encoded_bytes_by_encoding"].get("diff")
        # The map's floats, RGBA and PNG (12 bytes a pixel) and the spatial indexes' bound
        # (core/diff, kDiffIndexBytes: 96 MiB, 48 a side).
        self.assertEqual(charged, PNG_SIZE * PNG_SIZE * 12 + (96 << 20), memory)
        self.assertGreaterEqual(memory["pinned_bytes"], charged)
        self.assertEqual(reads(daemon, "diffs", "running"), 1)
        # A second diff while the first runs: refused at once (without a bound it would read
        # too, and be held at its own open).
        second = self.in_thread(daemon, "/v1/models/%s/diff?from=1&to=3" % MODEL)
        poll(lambda: second[1] or hold.calls() >= n + 2)
        hold.release()
        first[0].join()
        second[0].join()
        status, headers, body = second[1][0]
        self.assertEqual(status, 503, body)
        self.assertEqual(headers.get("Retry-After"), "1")
        self.assertIn("limits.diffs", json.loads(body)["error"]["message"])
        status, headers, body = first[1][0]
        self.assertEqual(status, 200, body)
        self.assertEqual(body[:8], b"\x89PNG\r\n\x1a\n")
        after = stats(daemon)
        self.assertEqual(after["memory"]["encoded_bytes_by_encoding"]["diff"], 0)
        self.assertEqual(after["reads"]["diffs"]["running"], 0)
        self.assertEqual(after["reads"]["diffs"]["refused"], 1)
        # The slot is free again.
        status, _, body = daemon.request("GET", "/v1/models/%s/diff?from=1&to=3" % MODEL)
        self.assertEqual(status, 200, body)


class Stopping(Fixture):
    def test_a_diff_past_its_deadline_is_503(self):
        hold = Hold(ARGS.lib, os.path.join(self.root, MODEL), "read",
                    os.path.join(ARGS.work, "gate-deadline"))
        daemon = self.start(hold, "--set", "limits.diff_timeout=1ms", "--set", "threads.cpu=4")
        n = hold.let_through(hold.calls())
        diff = self.in_thread(daemon, "/v1/models/%s/diff?from=1&to=3" % MODEL)
        self.assertIsNotNone(hold.wait_held(n + 1))
        time.sleep(0.01)  # not a wait for an event: the 1 ms deadline has passed for certain
        hold.release()
        diff[0].join()
        status, headers, body = diff[1][0]
        self.assertEqual(status, 503, body)
        self.assertIn("limits.diff_timeout", json.loads(body)["error"]["message"])
        self.assertEqual(reads(daemon, "diffs", "timed_out"), 1)
        self.assertEqual(reads(daemon, "diffs", "running"), 0)

    def test_a_diff_whose_client_went_away_stops(self):
        hold = Hold(ARGS.lib, os.path.join(self.root, MODEL), "read",
                    os.path.join(ARGS.work, "gate-gone"))
        daemon = self.start(hold, "--set", "limits.diffs=1", "--set", "threads.cpu=4")
        n = hold.let_through(hold.calls())
        client = daemon.socket()
        client.sendall(("GET /v1/models/%s/diff?from=1&to=3 HTTP/1.1\r\nHost: vsm\r\n\r\n"
                        % MODEL).encode())
        self.assertIsNotNone(hold.wait_held(n + 1))
        self.assertEqual(reads(daemon, "diffs", "running"), 1)
        client.close()
        hold.release()
        poll(lambda: reads(daemon, "diffs", "running") == 0)
        self.assertEqual(reads(daemon, "diffs", "abandoned"), 1)
        self.assertEqual(reads(daemon, "diffs", "timed_out"), 0)
        # The slot is free, and a diff whose client stays is answered whole.
        status, _, body = daemon.request("GET", "/v1/models/%s/diff?from=1&to=3" % MODEL)
        self.assertEqual(status, 200, body)
        self.assertEqual(reads(daemon, "diffs", "abandoned"), 1)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--lib", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    ARGS.work = os.path.abspath(ARGS.work)
    harness.configure(ARGS)
    os.makedirs(ARGS.work, exist_ok=True)
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
