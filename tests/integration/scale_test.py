#!/usr/bin/python3
"""The index of a large model (issue 31), end to end: a synthetic model of tiny patches written by
tests/bench/scale_gen (depth 8 by default: 87,381 patches of 17 x 17, no textures), the real `vsm`
and the real vsmd on 127.0.0.1:0.

    /usr/bin/python3 scale_test.py --vsm <vsm> --vsmd <vsmd> --gen <scale_gen> --work <dir>
                                   [--depth 8]

1. The index scale_gen writes (as `vsm index` does) describes the hierarchy on disk: its stamp
   (inode, size, mtime) is the file's. `vsm info` from the index prints exactly what the full read
   of every Patch.xml prints (the index moved away).
2. A merge job publishes a new version and its index inside the same commit: afterwards the index
   describes the new hierarchy (stamp), the kept revision has its own (a hard link of the old one),
   and `vsm info` from the index again equals the full read.
3. vsmd killed (SIGKILL) and started again opens the model from the index at the same version, and
   answers the same model summary as a vsmd that read it in full (the index moved away).

And the model's metadata is charged to the memory budget: a budget it fills answers patch data
with 503 saying so.

The fault sweep (fault.sweep, model_states.py) covers a fault in the index write: the index's
calls come just before the commit point, inside the sweep's window.
"""

import argparse
import os
import shutil
import signal
import struct
import subprocess
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from hold import poll  # noqa: E402

ARGS = None
TOKEN = "scale-test-token"
INDEX = "patchhierarchy.vsmidx"


def vsm(*args):
    return subprocess.run([ARGS.vsm, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True, timeout=600)


def index_stamp(path):
    """(inode, size, mtime ns) an index records, after its magic and format."""
    with open(path, "rb") as f:
        head = f.read(8 + 4 + 24)
    assert head[:6] == b"VSMIDX", head[:8]
    return struct.unpack_from("<QQq", head, 12)


def file_stamp(path):
    st = os.stat(path)
    return (st.st_ino, st.st_size, st.st_mtime_ns)


def info_both_ways(opc):
    """`vsm info` from the index and from the full read (the index moved away, then back)."""
    indexed = vsm("info", opc)
    index = os.path.join(opc, "Patches", INDEX)
    moved = index + ".away"
    os.rename(index, moved)
    try:
        full = vsm("info", opc)
    finally:
        os.rename(moved, index)
    return indexed, full


class Scale(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.root = os.path.join(ARGS.work, "root")
        shutil.rmtree(cls.root, ignore_errors=True)
        os.makedirs(cls.root)
        cls.model = os.path.join(cls.root, "big")
        out = subprocess.run([ARGS.gen, cls.model, str(ARGS.depth)], stdout=subprocess.PIPE,
                             text=True, check=True)
        cls.patches = int(out.stdout.split()[0])
        subprocess.run([ARGS.gen, os.path.join(cls.root, "detail"), "2", "17", "-98.49", "33.49",
                        "0.75"], stdout=subprocess.DEVNULL, check=True)

    def test_index_merge_and_restart(self):
        patches = os.path.join(self.model, "Patches")
        hierarchy = os.path.join(patches, "patchhierarchy.xml")
        # 1.
        self.assertEqual(index_stamp(os.path.join(patches, INDEX)), file_stamp(hierarchy))
        indexed, full = info_both_ways(self.model)
        self.assertEqual(indexed.returncode, 0, indexed.stderr)
        self.assertEqual(indexed.stdout, full.stdout)
        self.assertIn("patches     %d" % self.patches, indexed.stdout)

        # 2.
        daemon = harness.Daemon("--token", TOKEN, "--memory-budget", "64MiB", root=self.root)
        try:
            before = daemon.get_json("/v1/models/big")[2]
            job = daemon.submit({"type": "merge", "target": "big", "source": "detail"})
            done = daemon.wait_job(job["id"])
            self.assertEqual(done["state"], "succeeded", done)
            after = daemon.get_json("/v1/models/big")[2]
            self.assertEqual(after["version"], before["version"] + 1)
        finally:
            daemon.kill()  # 3. SIGKILL: nothing is finished on the way out
        self.assertEqual(index_stamp(os.path.join(patches, INDEX)), file_stamp(hierarchy))
        kept = os.path.join(patches, "vsm-revision-%d.xml" % before["version"])
        kept_index = os.path.join(patches, "vsm-revision-%d.vsmidx" % before["version"])
        self.assertTrue(os.path.exists(kept) and os.path.exists(kept_index))
        self.assertEqual(index_stamp(kept_index), file_stamp(kept))
        indexed, full = info_both_ways(self.model)
        self.assertEqual(indexed.stdout, full.stdout)
        self.assertEqual(indexed.returncode, 0, indexed.stderr)

        # 3.
        daemon = harness.Daemon("--token", TOKEN, "--memory-budget", "64MiB", root=self.root)
        try:
            from_index = daemon.get_json("/v1/models/big")[2]
        finally:
            daemon.stop()
        self.assertEqual(from_index["version"], after["version"])
        index = os.path.join(patches, INDEX)
        os.rename(index, index + ".away")
        try:
            daemon = harness.Daemon("--token", TOKEN, "--memory-budget", "64MiB",
                                    root=self.root)
            try:
                from_files = daemon.get_json("/v1/models/big")[2]
            finally:
                daemon.stop()
        finally:
            os.rename(index + ".away", index)
        self.assertEqual(from_index, from_files)

    def test_the_metadata_of_the_open_models_is_charged_to_the_memory_budget(self):
        # 87,381 patch descriptions take ~15 MB: more than an 8 MiB budget, which then has no room
        # for patch data (503, saying why), while what needs no patch data still answers.
        daemon = harness.Daemon("--token", TOKEN, "--memory-budget", "8MiB", root=self.root)
        try:
            # Charged by the daemon's housekeeping once it serves (every half second).
            def charged():
                stats = daemon.get_json("/v1/stats")[2]
                return stats if stats["memory"]["resident_bytes_by_model"].get("big") else None

            stats = poll(charged, timeout=60)
            self.assertIsNotNone(stats, "no metadata charged")
            metadata = stats["memory"]["resident_bytes_by_category"]["metadata"]
            self.assertGreater(metadata, 8 * 1024 * 1024)
            self.assertGreater(stats["memory"]["resident_bytes_by_model"]["big"], 8 * 1024 * 1024)
            status, _, body = daemon.request("GET", "/v1/models/big/patches/0_0_0/positions")
            self.assertEqual(status, 503, body[:300])
            self.assertIn(b"metadata", body)
            status, _, summary = daemon.get_json("/v1/models/big")
            self.assertEqual(status, 200, summary)
        finally:
            daemon.stop()
        # With room: the same charge (within the half second's change), and the data served.
        daemon = harness.Daemon("--token", TOKEN, "--memory-budget", "512MiB", root=self.root)
        try:
            self.assertIsNotNone(poll(charged, timeout=60), "no metadata charged")
            status, _, body = daemon.request("GET", "/v1/models/big/patches/0_0_0/positions")
            self.assertEqual(status, 200, body[:300])
            _, _, stats = daemon.get_json("/v1/stats")
            memory = stats["memory"]
            charged = memory["resident_bytes_by_category"]["metadata"]
            # Between the bare descriptions (the C++ struct is 168 bytes) and twice the first
            # daemon's figure.
            self.assertGreater(charged, self.patches * 168)
            self.assertLess(charged, 2 * metadata)
            self.assertLessEqual(memory["resident_bytes"], memory["budget_bytes"])
            self.assertEqual(sum(memory["resident_bytes_by_category"].values()),
                             memory["resident_bytes"])
        finally:
            daemon.stop()


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--gen", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--depth", type=int, default=8)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    os.makedirs(ARGS.work, exist_ok=True)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    harness.run_tests(rest)


if __name__ == "__main__":
    main()
