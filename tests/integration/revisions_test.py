#!/usr/bin/python3
"""Revisions end to end: the real vsmd on 127.0.0.1:0 over real data (PRISM and Jacksboro imported
by the real `vsm` at --patch-size 65), driven over HTTP as a client would.

    /usr/bin/python3 revisions_test.py --vsm <vsm> --vsmd <vsmd> --data <shared/data> --work <dir>

1. PRISM is revision 1; merging Jacksboro into it (a job) makes revision 2, whose record names
   its parent and its job. `?rev=1` after the merge answers the model, the hierarchy and every
   patch's positions byte for byte as they were before the merge (a 3D Tiles tileset of ?rev=1
   points its tiles at revision 1); the ETags of the two revisions differ.
2. Restoring revision 1 (a job, with the token) makes revision 3, whose hierarchy and positions
   equal revision 1's patch for patch; its record says what it restored. The patches it removed
   still answer ?v=2 (from revision 2), and 404 for ?v=3.
3. Bad revisions: ?rev=0 and ?rev=x are 400, a revision never made is 404, a restore without
   the token is 401, of a revision not kept 404.
4. Retention: after 12 more merges with --keep-revisions 8, exactly 8 revisions are listed, the
   hierarchy files of the dropped ones are gone, and every patch folder on disk is one a kept
   revision names (the dropped revisions' own folders are gone); `vsm validate` passes, and a
   restart lists the same revisions.
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from hold import poll  # noqa: E402
from model_states import reachable_folders  # noqa: E402

ARGS = None
TOKEN = "revisions-test-token"
AUTH = {"Authorization": "Bearer " + TOKEN}
KEEP = 8
# Retention by count alone: the time floor (keep_revisions_seconds) would keep every revision of
# this quick succession of merges.
NO_TIME_FLOOR = ("--set", "keep_revisions_seconds=0")


def import_models(root):
    for name in ("PRISMelevation", "jacksboro_fault_dem"):
        harness.import_dem(os.path.join(ARGS.data, name + ".tif"), os.path.join(root, name), 65)


class Revisions(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        root = os.path.join(ARGS.work, "root")
        shutil.rmtree(root, ignore_errors=True)
        os.makedirs(root)
        import_models(root)
        cls.root = root
        cls.daemon = harness.Daemon("--token", TOKEN, "--keep-revisions", str(KEEP), *NO_TIME_FLOOR,
                                 root=root)

    @classmethod
    def tearDownClass(cls):
        cls.daemon.stop()

    def get(self, path, status=200):
        code, headers, body = self.daemon.request("GET", path)
        self.assertEqual(code, status, body[:300])
        return headers, body

    def get_json(self, path, status=200):
        return json.loads(self.get(path, status)[1])

    def wait(self, job):
        job = self.daemon.wait_job(job["id"], timeout=300, interval=0.05)
        self.assertEqual(job["state"], "succeeded", job)
        return job

    def post(self, path, body=None, status=202, headers=AUTH):
        code, _, answer = self.daemon.request(
            "POST", path, body=json.dumps(body) if body is not None else None,
            headers={**headers, "Content-Type": "application/json"})
        self.assertEqual(code, status, answer[:300])
        return json.loads(answer)

    def merge(self):
        return self.wait(self.post("/v1/jobs", {"type": "merge", "target": "PRISMelevation",
                                                "source": "jacksboro_fault_dem"}))

    def state(self, rev=None):
        """(model summary, hierarchy, {key: positions bytes}) of PRISM, of revision `rev`."""
        q = "" if rev is None else "?rev=%d" % rev
        model = self.get_json("/v1/models/PRISMelevation" + q)
        hierarchy = self.get_json("/v1/models/PRISMelevation/hierarchy" + q)
        keys = harness.keys(hierarchy)
        positions = {k: self.get("/v1/models/PRISMelevation/patches/%s/positions%s" % (k, q))[1]
                     for k in keys}
        return model, hierarchy, positions

    def revisions(self):
        return self.get_json("/v1/models/PRISMelevation/revisions")["revisions"]

    def structure(self, node):
        """The tree of keys of a hierarchy answer (versions left out)."""
        return (node["key"], sorted(self.structure(c) for c in node.get("children", [])))

    def test_revisions(self):
        # 1. Revision 1, then the merge's revision 2; ?rev=1 reads the past byte for byte.
        self.assertEqual([r["revision"] for r in self.revisions()], [1])
        before = self.state()
        etag_before = self.get("/v1/models/PRISMelevation")[0]["ETag"]
        job = self.merge()
        listed = self.revisions()
        self.assertEqual([r["revision"] for r in listed], [1, 2])
        self.assertEqual(listed[1]["parent"], 1)
        self.assertEqual(listed[1]["job"], job["id"])
        self.assertTrue(listed[1]["latest"])
        self.assertGreater(listed[1]["changed_patches"], 0)
        self.assertRegex(listed[1]["time"], r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ$")
        after = self.state()
        self.assertGreater(after[0]["depth"], before[0]["depth"])
        past = self.state(1)
        self.assertEqual(past[1]["root"], before[1]["root"])
        self.assertEqual(past[2].keys(), before[2].keys())
        for key, data in before[2].items():
            self.assertEqual(past[2][key], data, "positions of %s at ?rev=1" % key)
        self.assertEqual(self.get("/v1/models/PRISMelevation?rev=1")[0]["ETag"], etag_before)
        self.assertNotEqual(self.get("/v1/models/PRISMelevation")[0]["ETag"], etag_before)
        tileset = self.get_json("/v1/models/PRISMelevation/3dtiles/tileset.json?rev=1")
        uri = tileset["root"]["content"]["uri"]
        self.assertTrue(uri.endswith("&rev=1"), uri)
        self.get("/v1/models/PRISMelevation/3dtiles/" + uri)

        # 2. Restore 1: revision 3 has revision 1's surface, patch for patch.
        restored = self.wait(self.post("/v1/models/PRISMelevation/revisions/1/restore"))
        self.assertEqual(restored["result"]["version"], 3)
        listed = self.revisions()
        self.assertEqual([r["revision"] for r in listed], [1, 2, 3])
        self.assertEqual(listed[2]["restored_from"], 1)
        self.assertEqual(listed[2]["job"], restored["id"])
        now = self.state()
        self.assertEqual(now[0]["version"], 3)
        self.assertEqual(self.structure(now[1]["root"]), self.structure(before[1]["root"]))
        self.assertEqual(now[2], before[2])
        # The patches the restore removed, asked as version 2 holds them (the links of version
        # 2's documents): from revision 2, not 404 (seen by cluster.nemesis, seed 22).
        removed = sorted(set(after[2]) - set(before[2]))
        self.assertGreater(len(removed), 0)
        for key in removed:
            headers, data = self.get("/v1/models/PRISMelevation/patches/%s/positions?v=2" % key)
            self.assertEqual(data, after[2][key], key)
            self.assertEqual(headers["X-VSM-Patch-Version"], "2", key)
        self.get("/v1/models/PRISMelevation/patches/%s/positions?v=3" % removed[0], 404)

        # 3. Bad revisions.
        for bad in ("0", "x", "-1", "1.5", "99999999999999999999"):
            self.get("/v1/models/PRISMelevation?rev=" + bad, 400)
        self.get("/v1/models/PRISMelevation?rev=4", 404)
        self.get("/v1/models/PRISMelevation/patches/0_0_0/positions?rev=77", 404)
        self.post("/v1/models/PRISMelevation/revisions/1/restore", status=401, headers={})
        self.post("/v1/models/PRISMelevation/revisions/77/restore", status=404)

        # 4. Retention: 12 merges with 8 kept.
        for _ in range(12):
            self.merge()
        listed = self.revisions()
        self.assertEqual([r["revision"] for r in listed], list(range(8, 16)))
        patches = os.path.join(self.root, "PRISMelevation", "Patches")
        files = sorted(f for f in os.listdir(patches) if re.fullmatch(r"vsm-revision-\d+\.xml", f))
        self.assertEqual(files, sorted("vsm-revision-%d.xml" % n for n in range(8, 15)))
        opc = os.path.join(self.root, "PRISMelevation")
        kept = reachable_folders(opc)
        for name in files:
            kept |= reachable_folders(opc, name)

        def on_disk():
            return {e for e in os.listdir(patches) if os.path.isdir(os.path.join(patches, e))}
        # Every folder a kept revision names is there; the dropped ones' go after the jobs have
        # answered (vsmd's housekeeping), so they are waited for.
        self.assertLessEqual(kept, on_disk())
        self.assertEqual(poll(lambda: on_disk() == kept, timeout=60), True)
        self.assertEqual(on_disk(), kept)
        tiles = os.path.join(opc, "Images", "Diffuse")
        self.assertEqual({t[:-4] for t in os.listdir(tiles)} - kept, set())
        self.get("/v1/models/PRISMelevation?rev=7", 404)
        self.get("/v1/models/PRISMelevation/hierarchy?rev=8")
        validate = subprocess.run([ARGS.vsm, "validate", opc], stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        self.assertEqual(validate.returncode, 0, validate.stdout[-500:])
        # A restart reads the same list from disk.
        self.assertEqual(self.daemon.stop(), 0)
        type(self).daemon = harness.Daemon("--token", TOKEN, "--keep-revisions", str(KEEP),
                                        *NO_TIME_FLOOR,
                                        root=self.root)
        self.assertEqual([r["revision"] for r in self.revisions()], list(range(8, 16)))
        self.assertEqual([r["job"] for r in self.revisions()], [r["job"] for r in listed])


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    os.makedirs(ARGS.work, exist_ok=True)
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
