#!/usr/bin/python3
"""End-to-end tests of vsmd's model, patch, LOD and job routes on real data: the real daemon on
127.0.0.1:0 (harness.py) over a data root holding the Jacksboro DEM
imported by `vsm import` at 65 x 65, and PRISM imported over HTTP as a job, then merged with
Jacksboro as a job. Responses are checked against proto/examples and decoded independently
(the .aara bytes with struct). The merges' file creations under PRISM pass a gate of the
LD_PRELOAD library tests/fault/fault_inject.c (hold.py), so that the test sees a merge mid-way and
cancels one before it can end, on any machine. Run by ctest:
    server_models_test.py --vsmd build/server/vsmd --vsm build/server/cli/vsm \\
        --data ../shared/data --proto proto --lib build/tests/fault/libvsm_fault_inject.so"""

import argparse
import json
import math
import os
import re
import shutil
import struct
import sys
import tempfile
import threading
import unittest
import urllib.parse

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import Daemon, decode_aara, example, shape, walk  # noqa: E402
from check_import import Failures, check_pro3d  # noqa: E402
from hold import Hold  # noqa: E402

TOKEN = "models-token-0123456789"
AUTH = {"Authorization": "Bearer " + TOKEN}
JSON = {"Content-Type": "application/json"}
PATCH = 65
ARGS = None



def import_opc(dem, out, size=PATCH, *options):
    harness.import_dem(os.path.join(ARGS.data, dem), out, size, *options, timeout=300)


def assert_pro3d_complete(opc):
    """check_import.check_pro3d: Images/, and a coordinates file and texture tile per patch."""
    failures = Failures()
    checked = check_pro3d(opc, failures)
    assert failures.count == 0 and checked > 0, (opc, failures.items)


def key_parts(key):
    d, x, y = (int(v) for v in key.split("_"))
    return d, x, y


class Models(unittest.TestCase):
    """One daemon over a data root with Jacksboro (imported by `vsm`), a copy of the PRISM raster,
    an outside directory reachable through a symlink, and entries that are not models."""

    daemon = None
    outside = None

    @classmethod
    def setUpClass(cls):
        if not ARGS.vsm or not ARGS.data:
            raise unittest.SkipTest("--vsm and --data are needed")
        cls.outside = tempfile.mkdtemp(prefix="vsmd-outside-")
        import_opc("jacksboro_fault_dem.tif", os.path.join(cls.outside, "outside-model"))
        with open(os.path.join(cls.outside, "secret.tif"), "wb") as f:
            f.write(b"not for clients")

        def prepare(root):
            import_opc("jacksboro_fault_dem.tif", os.path.join(root, "jacksboro"))
            os.mkdir(os.path.join(root, "rasters"))
            shutil.copy(os.path.join(ARGS.data, "PRISMelevation.tif"),
                        os.path.join(root, "rasters", "prism.tif"))
            os.mkdir(os.path.join(root, "empty-dir"))
            os.mkdir(os.path.join(root, "bad.name"))
            os.symlink(cls.outside, os.path.join(root, "escape"))

        root = tempfile.mkdtemp(prefix="vsmd-test-")
        prepare(root)
        cls.gate = tempfile.mkdtemp(prefix="vsmd-gate-")
        cls.hold = Hold(ARGS.lib, os.path.join(root, "prism"), "create",
                        os.path.join(cls.gate, "gate"))
        cls.daemon = Daemon("--token", TOKEN, "--memory-budget", "256MiB",
                            "--set", "threads.cpu=4", "--set", "limits.body_bytes=4KiB",
                            root=root, env=cls.hold.env())
        cls.outside_before = cls.snapshot_outside()

    @classmethod
    def snapshot_outside(cls):
        out = {}
        for dirpath, dirnames, filenames in os.walk(cls.outside):
            for name in dirnames + filenames:
                path = os.path.join(dirpath, name)
                st = os.lstat(path)
                out[os.path.relpath(path, cls.outside)] = (st.st_size, st.st_mtime_ns)
        return out

    @classmethod
    def tearDownClass(cls):
        try:
            cls.hold.release()
            shutil.rmtree(cls.gate, ignore_errors=True)
            if cls.daemon is not None:
                code = cls.daemon.stop()
                if code != 0:
                    raise AssertionError("vsmd exited %d:\n%s" % (code, cls.daemon.log()))
        finally:
            if cls.daemon is not None:
                cls.daemon.cleanup()
            if cls.outside is not None:
                shutil.rmtree(cls.outside, ignore_errors=True)

    def assert_error(self, status, body, expected_status, code):
        self.assertEqual(status, expected_status, body)
        error = json.loads(body) if isinstance(body, bytes) else body
        self.assertEqual(shape(error), shape(example("error-not-found.json")))
        self.assertEqual(error["error"]["code"], code)

    # ---- start-up and reads ----------------------------------------------------------------

    def test_startup_opens_the_opcs_and_skips_the_rest(self):
        status, headers, body = self.daemon.get_json("/v1/models")
        self.assertEqual(status, 200)
        self.assertEqual(headers["Cache-Control"], "no-cache")
        ids = [m["id"] for m in body["models"]]
        self.assertIn("jacksboro", ids)
        for skipped in ("empty-dir", "bad.name", "rasters", "escape"):
            self.assertNotIn(skipped, ids)
        entry = next(m for m in body["models"] if m["id"] == "jacksboro")
        self.assertEqual(shape(entry), shape(example("models.json")["models"][0]))
        log = self.daemon.log()
        self.assertIn("model=jacksboro opened", log)
        self.assertIn("skipping 'bad.name'", log)

    def test_summary_has_bounds_levels_and_an_etag(self):
        status, headers, body = self.daemon.get_json("/v1/models/jacksboro")
        self.assertEqual(status, 200)
        self.assertEqual(shape(body), shape(example("model.json")))
        self.assertEqual(body["grid_size"], PATCH)
        self.assertEqual(len(body["levels"]), body["depth"] + 1)
        self.assertEqual(sum(level["patches"] for level in body["levels"]), body["patches"])
        self.assertEqual(body["levels"][0]["patches"], 1)
        # ECEF metres, Tennessee: about 6.37e6 m from the earth's centre.
        lo, hi = body["bounds"]["min"], body["bounds"]["max"]
        self.assertAlmostEqual(math.dist([0, 0, 0], [(a + b) / 2 for a, b in zip(lo, hi)]),
                               6.37e6, delta=0.02e6)
        etag = headers["ETag"]
        self.assertRegex(etag, r'^"[^"]+"$')
        self.assertEqual(headers["Cache-Control"], "no-cache")
        status, headers, data = self.daemon.request("GET", "/v1/models/jacksboro",
                                                    headers={"If-None-Match": etag})
        self.assertEqual(status, 304)
        self.assertEqual(data, b"")
        self.assertEqual(headers["ETag"], etag)

    def test_hierarchy_is_the_whole_tree_or_a_cut_of_it(self):
        _, _, summary = self.daemon.get_json("/v1/models/jacksboro")
        status, _, tree = self.daemon.get_json("/v1/models/jacksboro/hierarchy")
        self.assertEqual(status, 200)
        self.assertEqual(tree["model"], "jacksboro")
        nodes = list(walk(tree["root"]))
        self.assertEqual(len(nodes), summary["patches"])
        self.assertEqual(sum(1 for n in nodes if n["leaf"]), summary["leaves"])
        for node in nodes:  # children are the node's quadrants, inside its box
            d, x, y = key_parts(node["key"])
            for child in node.get("children", []):
                cd, cx, cy = key_parts(child["key"])
                self.assertEqual((cd, cx // 2, cy // 2), (d + 1, x, y))
                for axis in range(3):
                    self.assertGreaterEqual(child["box"]["min"][axis],
                                            node["box"]["min"][axis] - 1e-6)
                    self.assertLessEqual(child["box"]["max"][axis],
                                         node["box"]["max"][axis] + 1e-6)
        status, _, top = self.daemon.get_json("/v1/models/jacksboro/hierarchy?depth=1")
        self.assertEqual(status, 200)
        self.assertEqual(shape(top), shape(example("hierarchy.json")))
        for child in top["root"]["children"]:
            self.assertNotIn("children", child)
        first = top["root"]["children"][0]["key"]
        status, _, sub = self.daemon.get_json("/v1/models/jacksboro/hierarchy?root=" + first)
        self.assertEqual(sub["root"]["key"], first)
        for query, code in (("root=9_9", 400), ("root=1_7_0", 400), ("depth=abc", 400),
                            ("depth=-2", 400), ("root=25_0_0", 404)):
            status, _, body = self.daemon.request("GET", "/v1/models/jacksboro/hierarchy?" + query)
            self.assert_error(status, body, code,
                              "invalid_argument" if code == 400 else "not_found")

    def a_leaf(self):
        _, _, tree = self.daemon.get_json("/v1/models/jacksboro/hierarchy")
        leaves = [n for n in walk(tree["root"]) if n["leaf"]]
        return leaves[len(leaves) // 2]

    def test_patch_metadata_and_positions_agree(self):
        leaf = self.a_leaf()
        status, headers, meta = self.daemon.get_json("/v1/models/jacksboro/patches/" + leaf["key"])
        self.assertEqual(status, 200)
        self.assertEqual(shape(meta), shape(example("patch.json")))
        self.assertEqual(meta["key"], leaf["key"])
        self.assertEqual(meta["box"], leaf["box"])
        self.assertEqual(headers["Cache-Control"], "public, max-age=60")
        etag = headers["ETag"]

        status, headers, data = self.daemon.request(
            "GET", "/v1/models/jacksboro/patches/%s/positions" % leaf["key"])
        self.assertEqual(status, 200)
        self.assertEqual(headers["Content-Type"], "application/octet-stream")
        self.assertEqual(headers["ETag"], etag)
        self.assertIn("X-VSM-Local2Global", headers["Access-Control-Expose-Headers"])
        self.assertEqual(data[:13], b"\x03V3f\x02" + struct.pack("<ii", PATCH, PATCH))
        name, sizes, payload = decode_aara(data)
        self.assertEqual((name, sizes), ("V3f", (PATCH, PATCH)))
        self.assertEqual(len(payload), PATCH * PATCH * 12)
        floats = struct.unpack("<%df" % (PATCH * PATCH * 3), payload)
        vertices = [floats[i:i + 3] for i in range(0, len(floats), 3)]
        defined = [v for v in vertices if not any(math.isnan(c) for c in v)]
        self.assertGreater(len(defined), 0)
        self.assertEqual(len(vertices), PATCH * PATCH)
        # Local + Local2Global = global, inside the patch's box.
        m = [float(v) for v in headers["X-VSM-Local2Global"].split(",")]
        self.assertEqual(len(m), 16)
        self.assertEqual(m, meta["local2global"])
        lo, hi = meta["box"]["min"], meta["box"]["max"]
        for v in defined[:: max(1, len(defined) // 50)]:
            g = [m[4 * r] * v[0] + m[4 * r + 1] * v[1] + m[4 * r + 2] * v[2] + m[4 * r + 3]
                 for r in range(3)]
            for axis in range(3):
                self.assertGreaterEqual(g[axis], lo[axis] - 0.01)
                self.assertLessEqual(g[axis], hi[axis] + 0.01)

        status, headers, data = self.daemon.request(
            "GET", "/v1/models/jacksboro/patches/%s/positions" % leaf["key"],
            headers={"If-None-Match": etag})
        self.assertEqual(status, 304)
        self.assertEqual(data, b"")
        status, headers, data = self.daemon.request(
            "HEAD", "/v1/models/jacksboro/patches/%s/positions" % leaf["key"])
        self.assertEqual(status, 200)
        self.assertEqual(int(headers["Content-Length"]), 13 + PATCH * PATCH * 12)

    def test_unknown_models_and_patches_are_404_and_bad_keys_400(self):
        for path in ("/v1/models/nope", "/v1/models/nope/hierarchy",
                     "/v1/models/nope/patches/0_0_0", "/v1/models/nope/patches/0_0_0/positions",
                     "/v1/models/nope/lod?box=0,0,0,1,1,1&resolution=1",
                     "/v1/models/jacksboro/patches/20_0_0",
                     "/v1/models/jacksboro/patches/20_0_0/positions",
                     "/v1/models/%2E%2E", "/v1/models/..%2Fjacksboro", "/v1/jobs/nope"):
            status, _, body = self.daemon.request("GET", path)
            self.assert_error(status, body, 404, "not_found")
        for path in ("/v1/models/jacksboro/patches/0_0", "/v1/models/jacksboro/patches/x_y_z",
                     "/v1/models/jacksboro/patches/1_2_0", "/v1/models/jacksboro/patches/-1_0_0",
                     "/v1/models/jacksboro/patches/0_0_0_0/positions"):
            status, _, body = self.daemon.request("GET", path)
            self.assert_error(status, body, 400, "invalid_argument")

    def test_lod_cuts_the_tree_by_box_and_resolution(self):
        _, _, summary = self.daemon.get_json("/v1/models/jacksboro")
        lo, hi = summary["bounds"]["min"], summary["bounds"]["max"]
        box = ",".join("%.17g" % v for v in lo + hi)
        status, headers, coarse = self.daemon.get_json(
            "/v1/models/jacksboro/lod?box=%s&resolution=1e9" % box)
        self.assertEqual(status, 200)
        self.assertEqual(shape(coarse), shape(example("lod.json")))
        self.assertEqual([p["key"] for p in coarse["patches"]], ["0_0_0"])
        _, _, fine = self.daemon.get_json("/v1/models/jacksboro/lod?box=%s&resolution=0.001" % box)
        self.assertEqual(len(fine["patches"]), summary["leaves"])
        self.assertTrue(all(p["leaf"] for p in fine["patches"]))
        finest = summary["resolution"]["finest"]
        _, _, mid = self.daemon.get_json(
            "/v1/models/jacksboro/lod?box=%s&resolution=%r" % (box, finest * 2.5))
        self.assertLess(len(mid["patches"]), len(fine["patches"]))
        for p in mid["patches"]:
            self.assertTrue(p["leaf"] or p["resolution"] <= finest * 2.5)
        # A small box in a corner selects only the patches that meet it.
        corner = ",".join("%.17g" % v for v in lo + [lo[i] + (hi[i] - lo[i]) * 0.05 for i in range(3)])
        _, _, small = self.daemon.get_json(
            "/v1/models/jacksboro/lod?box=%s&resolution=0.001" % urllib.parse.quote(corner))
        self.assertLess(len(small["patches"]), len(fine["patches"]))
        self.assertEqual(self.daemon.request(
            "GET", "/v1/models/jacksboro/lod?box=%s&resolution=1e9" % box,
            headers={"If-None-Match": headers["ETag"]})[0], 304)
        for query in ("", "box=%s" % box, "resolution=5", "box=1,2,3&resolution=5",
                      "box=%s&resolution=0" % box, "box=%s&resolution=abc" % box,
                      "box=3,0,0,1,1,1&resolution=5", "box=0,0,0,1,1,inf&resolution=5"):
            status, _, body = self.daemon.request("GET", "/v1/models/jacksboro/lod?" + query)
            self.assert_error(status, body, 400, "invalid_argument")

    # ---- writes --------------------------------------------------------------------------

    def test_writes_need_the_token(self):
        status, _, body = self.daemon.request(
            "POST", "/v1/models", body=b'{"id": "x", "source": {"path": "jacksboro"}}',
            headers=JSON)
        self.assert_error(status, body, 401, "unauthorized")
        for method, path in (("DELETE", "/v1/models/jacksboro"), ("POST", "/v1/jobs"),
                             ("DELETE", "/v1/jobs/x")):
            self.assertEqual(self.daemon.request(method, path)[0], 401, path)
        self.assertEqual(self.daemon.get_json("/v1/models/jacksboro")[0], 200)

    def test_an_oversize_body_is_413(self):
        status, _, body = self.daemon.request(
            "POST", "/v1/models", body=json.dumps({"id": "x" * 5000}).encode(),
            headers={**JSON, **AUTH})
        self.assert_error(status, body, 413, "payload_too_large")

    def test_bad_json_and_bad_requests_are_400(self):
        for body in (b"not json", b"[]", b'{"id": "x"}', b'{"id": "x", "source": {}}',
                     b'{"id": "x", "source": {"path": "jacksboro"}, "extra": 1}',
                     b'{"id": "x", "source": {"import": "rasters/prism.tif", "patch_size": 64}}',
                     b'{"id": "x", "source": {"import": "rasters/prism.tif", "texture": "nasa"}}',
                     b'{"id": "x", "source": {"import": "rasters/prism.tif", "texture": false}}',
                     b'{"id": "x", "source": {"path": "jacksboro", "texture": "none"}}',
                     b'{"id": "x", "source": {"path": "jacksboro", "visible_texels_per_quad": 4}}',
                     b'{"id": "x", "source": {"import": "rasters/prism.tif", '
                     b'"visible_texels_per_quad": 3}}',
                     b'{"id": "x", "source": {"import": "rasters/prism.tif", '
                     b'"visible_texels_per_quad": "4"}}',
                     b'{"id": "x", "source": {"import": "rasters/prism.tif", '
                     b'"visible_texels_per_quad": 32}}',
                     b'{"id": "x", "source": {"import": "rasters/prism.tif", '
                     b'"visible_texels_per_quad": -4}}',
                     b'{"id": "x", "source": {"import": "rasters/prism.tif", "texture": "none", '
                     b'"visible_texels_per_quad": 4}}'):
            status, _, data = self.daemon.request("POST", "/v1/models", body=body,
                                                  headers={**JSON, **AUTH})
            self.assert_error(status, data, 400, "invalid_argument")
        for body in (b'{"type": "merge"}', b'{"type": "split", "target": "a", "source": "b"}',
                     b'{"type": "merge", "target": "jacksboro", "source": "jacksboro"}'):
            status, _, data = self.daemon.request("POST", "/v1/jobs", body=body,
                                                  headers={**JSON, **AUTH})
            self.assert_error(status, data, 400, "invalid_argument")

    def test_path_tricks_in_ids_and_sources_are_400_and_touch_nothing_outside(self):
        before = sorted(os.listdir(self.daemon.dir))
        tricks = [
            {"id": "../evil", "source": {"path": "jacksboro"}},
            {"id": "a/b", "source": {"path": "jacksboro"}},
            {"id": "..", "source": {"path": "jacksboro"}},
            {"id": "x" * 65, "source": {"path": "jacksboro"}},
            {"id": "", "source": {"path": "jacksboro"}},
            {"id": "ok", "source": {"path": "../" + os.path.basename(self.outside)}},
            {"id": "ok", "source": {"path": self.outside}},
            {"id": "ok", "source": {"path": "escape/outside-model"}},
            {"id": "ok", "source": {"path": "escape"}},
            {"id": "ok", "source": {"path": "jacksboro/../../x"}},
            {"id": "ok", "source": {"path": "."}},
            {"id": "ok", "source": {"import": "escape/secret.tif", "patch_size": 65}},
            {"id": "ok", "source": {"import": "/etc/passwd", "patch_size": 65}},
            {"id": "ok", "source": {"import": "../../etc/passwd", "patch_size": 65}},
            {"id": "../../tmp/evil", "source": {"import": "rasters/prism.tif", "patch_size": 65}},
        ]
        for body in tricks:
            status, _, data = self.daemon.json("POST", "/v1/models", body)
            self.assert_error(status, data, 400, "invalid_argument")
        for path in ("/v1/models/..%2F..%2Fetc", "/v1/models/%2E%2E%2Fx/hierarchy"):
            status, _, data = self.daemon.request("DELETE", path, headers=AUTH)
            self.assertIn(status, (404, 405), data)
        self.assertEqual(sorted(os.listdir(self.daemon.dir)), before)
        self.assertEqual(self.snapshot_outside(), self.outside_before)
        ids = [m["id"] for m in self.daemon.get_json("/v1/models")[2]["models"]]
        self.assertNotIn("ok", ids)

    def test_open_conflict_close_and_reopen(self):
        status, _, body = self.daemon.json("POST", "/v1/models",
                                           {"id": "jacksboro", "source": {"path": "jacksboro"}})
        self.assert_error(status, body, 409, "conflict")
        status, _, body = self.daemon.json("POST", "/v1/models",
                                           {"id": "twin", "source": {"path": "jacksboro"}})
        self.assert_error(status, body, 409, "conflict")
        status, _, body = self.daemon.json("POST", "/v1/models",
                                           {"id": "nothing", "source": {"path": "empty-dir"}})
        self.assert_error(status, body, 404, "not_found")
        # A second copy, opened by path, closed, and opened again.
        shutil.copytree(os.path.join(self.daemon.dir, "jacksboro"),
                        os.path.join(self.daemon.dir, "rasters", "copy"))
        status, headers, body = self.daemon.json("POST", "/v1/models",
                                                 {"id": "copy", "source": {"path": "rasters/copy"}})
        self.assertEqual(status, 201, body)
        self.assertEqual(headers["Location"], "/v1/models/copy")
        self.assertEqual(shape(body), shape(example("model.json")))
        status, _, data = self.daemon.request("DELETE", "/v1/models/copy", headers=AUTH)
        self.assertEqual(status, 204)
        self.assertEqual(data, b"")
        self.assertEqual(self.daemon.get_json("/v1/models/copy")[0], 404)
        self.assertEqual(self.daemon.request("DELETE", "/v1/models/copy", headers=AUTH)[0], 404)
        self.assertTrue(os.path.isdir(os.path.join(self.daemon.dir, "rasters", "copy", "Patches")))
        status, _, body = self.daemon.json("POST", "/v1/models",
                                           {"id": "copy", "source": {"path": "rasters/copy"}})
        self.assertEqual(status, 201, body)
        self.assertEqual(self.daemon.request("DELETE", "/v1/models/copy", headers=AUTH)[0], 204)

    # ---- jobs: import, merge with reads during it, cancel, restart ------------------------

    def test_z_import_then_merge_then_cancel_then_restart(self):
        d = self.daemon
        # Import PRISM as a job.
        status, headers, job = d.json("POST", "/v1/models", {
            "id": "prism", "source": {"import": "rasters/prism.tif", "patch_size": PATCH}})
        self.assertEqual(status, 202, job)
        self.assertEqual(shape(job), shape(example("job-import.json")))
        self.assertEqual(headers["Location"], "/v1/jobs/" + job["id"])
        status, _, again = d.json("POST", "/v1/models", {
            "id": "prism", "source": {"import": "rasters/prism.tif", "patch_size": PATCH}})
        self.assert_error(status, again, 409, "conflict")
        done = d.wait_job(job["id"])
        self.assertEqual(done["state"], "succeeded", done)
        self.assertEqual(done["progress"], 1)
        status, _, prism = d.get_json("/v1/models/prism")
        self.assertEqual(status, 200)
        self.assertEqual(prism["version"], 1)
        self.assertEqual(done["result"]["patches"], prism["patches"])
        self.assertEqual(done["params"]["texture"], "relief")
        assert_pro3d_complete(os.path.join(d.dir, "prism"))
        # "texture": "none": no Images/ and no coordinates (PRo3D will not open it, vsm does).
        status, _, job = d.json("POST", "/v1/models", {
            "id": "bare", "source": {"import": "rasters/prism.tif", "patch_size": PATCH,
                                     "texture": "none"}})
        self.assertEqual(status, 202, job)
        self.assertEqual(job["params"]["texture"], "none")
        self.assertEqual(d.wait_job(job["id"])["state"], "succeeded")
        self.assertTrue(os.path.isdir(os.path.join(d.dir, "bare", "Patches")))
        self.assertFalse(os.path.exists(os.path.join(d.dir, "bare", "Images")))
        self.assertIsNone(d.get_json("/v1/models/bare/patches/0_0_0")[2]["texture"])

        # Merge Jacksboro into PRISM; readers hammer PRISM meanwhile. Its file creations under
        # PRISM wait at the gate (from the next one on) until the test has looked at it mid-way.
        _, before_headers, before_tree = d.get_json("/v1/models/prism/hierarchy")
        before_count = len(list(walk(before_tree["root"])))
        hold = self.hold
        allowed = hold.let_through(hold.calls())
        status, _, job = d.json("POST", "/v1/jobs", {"type": "merge", "target": "prism",
                                "source": "jacksboro", "register": False})
        self.assertEqual(status, 202, job)
        self.assertEqual(shape(job), shape(example("job.json")))
        self.assertIn(job["state"], ("queued", "running"))
        # The job holds the target (it cannot end before the gate opens): it cannot be closed
        # under it.
        status, _, body = d.request("DELETE", "/v1/models/prism", headers=AUTH)
        self.assert_error(status, body, 409, "conflict")

        stop = threading.Event()
        failures = []
        versions = {}

        def reader():
            while not stop.is_set():
                try:
                    status, headers, tree = d.get_json("/v1/models/prism/hierarchy")
                    if status != 200:
                        failures.append(("hierarchy", status))
                        continue
                    nodes = list(walk(tree["root"]))
                    keys = sorted(n["key"] for n in nodes)
                    seen = versions.setdefault(tree["version"], (headers["ETag"], keys))
                    if seen != (headers["ETag"], keys):
                        failures.append(("two trees for version %d" % tree["version"],))
                    for n in nodes:
                        if not n["leaf"] and len(n.get("children", [])) != n["child_count"]:
                            failures.append(("node without its children", n["key"]))
                    status, headers, data = d.request(
                        "GET", "/v1/models/prism/patches/0_0_0/positions")
                    if status != 200 or len(data) != 13 + PATCH * PATCH * 12:
                        failures.append(("positions", status, len(data)))
                except Exception as e:  # noqa: BLE001 - reported below
                    failures.append(("exception", repr(e)))

        readers = [threading.Thread(target=reader) for _ in range(3)]
        for t in readers:
            t.start()
        seen = []
        try:
            # Held where it has made progress and has more to make (a few creations at a time).
            def ended():
                return d.get_json("/v1/jobs/" + job["id"])[2]["state"] not in ("queued", "running")

            while True:
                self.assertIsNotNone(hold.wait_held(allowed + 1, ended=ended),
                                     "the merge ended before it was seen mid-way")
                _, _, now = d.get_json("/v1/jobs/" + job["id"])
                if now["state"] == "running" and 0 < now["progress"] < 1:
                    break
                allowed = hold.let_through(allowed + 8)
            seen.append((now["state"], now["stage"], now["progress"]))
            # Readers meanwhile see the published version whole (checked by reader()).
            hold.release()
            done = d.wait_job(job["id"], seen=seen)
        finally:
            hold.release()
            stop.set()
            for t in readers:
                t.join(timeout=60)
        self.assertEqual(done["state"], "succeeded", done)
        self.assertEqual(failures, [])
        self.assertLessEqual(set(versions), {1, 2})
        progress = [p for _, _, p in seen]
        self.assertEqual(progress, sorted(progress), "progress went down")
        self.assertEqual(progress[-1], 1)
        self.assertTrue(any(0 < p < 1 for p in progress), seen[:20])
        self.assertEqual(done["result"]["version"], 2)
        self.assertGreater(done["result"]["new_patches"], 0)
        assert_pro3d_complete(os.path.join(d.dir, "prism"))
        _, after_headers, after = d.get_json("/v1/models/prism")
        self.assertEqual(after["version"], 2)
        self.assertEqual(after["patches"], before_count + done["result"]["new_patches"])
        self.assertGreater(after["depth"], prism["depth"])
        self.assertNotEqual(after_headers["ETag"], before_headers["ETag"])
        status, _, _ = d.request("GET", "/v1/models/prism/hierarchy",
                                 headers={"If-None-Match": before_headers["ETag"]})
        self.assertEqual(status, 200)
        status, _, jobs = d.get_json("/v1/jobs")
        self.assertEqual(status, 200)
        self.assertIn(job["id"], [j["id"] for j in jobs["jobs"]])

        # Cancel a second merge: the model stays as it is. Held at its first file creation under
        # PRISM, so that it cannot end before the cancel arrives.
        _, summary_headers, summary = d.get_json("/v1/models/prism")
        hold.let_through(hold.calls())
        try:
            status, _, job = d.json("POST", "/v1/jobs", {"type": "merge", "target": "prism",
                                    "source": "jacksboro"})
            self.assertEqual(status, 202, job)
            status, _, cancelled = d.request("DELETE", "/v1/jobs/" + job["id"], headers=AUTH)
            self.assertIn(status, (200, 202), cancelled)
            self.assertTrue(json.loads(cancelled)["cancel_requested"])
        finally:
            hold.release()
        final = d.wait_job(job["id"])
        self.assertEqual(final["state"], "cancelled", final)
        self.assertEqual(final["error"]["code"], "cancelled")
        status, headers, now = d.get_json("/v1/models/prism")
        self.assertEqual(now, summary)
        self.assertEqual(headers["ETag"], summary_headers["ETag"])
        status, _, body = d.request("DELETE", "/v1/jobs/" + job["id"], headers=AUTH)
        self.assert_error(status, body, 409, "conflict")
        self.assertFalse([n for n in os.listdir(os.path.join(d.dir, "prism", "Patches"))
                          if re.search(r"-v3(-[0-9a-f]{8})?$", n)], "a discarded edit left folders")

        # Restart: the merged model opens at its published version, with the same content.
        self.assertEqual(d.stop(), 0)
        restarted = Daemon("--token", TOKEN, root=d.dir)
        try:
            status, headers, reopened = restarted.get_json("/v1/models/prism")
            self.assertEqual(status, 200)
            self.assertEqual(reopened["patches"], after["patches"])
            self.assertEqual(reopened["depth"], after["depth"])
            self.assertEqual(headers["ETag"], after_headers["ETag"])
            self.assertEqual(restarted.get_json("/v1/jobs")[2], {"jobs": []})
        finally:
            self.assertEqual(restarted.stop(), 0)
            restarted.cleanup(keep=True)


class TexturedModel(unittest.TestCase):
    """The texture routes on Jacksboro imported with the NASA image draped over it, checked
    against the files `vsm import` wrote (read with GDAL and our own .aara decoder)."""

    daemon = None

    @classmethod
    def setUpClass(cls):
        if not ARGS.vsm or not ARGS.data:
            raise unittest.SkipTest("--vsm and --data are needed")

        def prepare(root):
            import_opc("jacksboro_fault_dem.tif", os.path.join(root, "textured"), PATCH,
                       "--texture", os.path.join(ARGS.data, "conus_visible_earth.tif"))
            # Untextured on purpose: the texture routes' 404s and "texture": null.
            import_opc("jacksboro_fault_dem.tif", os.path.join(root, "plain"), PATCH,
                       "--texture", "none")

        cls.daemon = Daemon("--token", TOKEN, prepare=prepare)
        cls.root = cls.daemon.dir

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is not None:
            code = cls.daemon.stop()
            cls.daemon.cleanup()
            if code != 0:
                raise AssertionError("vsmd exited %d" % code)

    def keys(self):
        return self.daemon.keys("textured")

    def test_patch_metadata_names_the_texture(self):
        status, _, meta = self.daemon.get_json("/v1/models/textured/patches/0_0_0")
        self.assertEqual(status, 200)
        self.assertEqual(meta["texture"], {"layer": "Diffuse", "coordinates": True})
        status, _, plain = self.daemon.get_json("/v1/models/plain/patches/0_0_0")
        self.assertEqual(status, 200)
        self.assertIsNone(plain["texture"])

    def test_coordinates_are_the_stored_file_u_v_per_stored_vertex(self):
        for key in self.keys():
            _, _, meta = self.daemon.get_json("/v1/models/textured/patches/" + key)
            status, headers, data = self.daemon.request(
                "GET", "/v1/models/textured/patches/%s/coordinates" % key)
            self.assertEqual(status, 200, data)
            self.assertEqual(headers["Content-Type"], "application/octet-stream")
            with open(os.path.join(self.root, "textured", "Patches", meta["folder"],
                                   "Coordinates.aara"), "rb") as f:
                self.assertEqual(data, f.read(), key)
            name, sizes, payload = decode_aara(data)
            stored = meta["stored"]
            self.assertEqual(name, "V2f")
            self.assertEqual(list(sizes), [stored["x1"] - stored["x0"], stored["y1"] - stored["y0"]])
            uv = struct.unpack("<%df" % (2 * sizes[0] * sizes[1]), payload)
            # Vertex (x, y) of the full grid sits at (x, y) / (grid size - 1) of the tile.
            for i in (0, sizes[0] * sizes[1] // 2, sizes[0] * sizes[1] - 1):
                x = stored["x0"] + i % sizes[0]
                y = stored["y0"] + i // sizes[0]
                self.assertAlmostEqual(uv[2 * i], x / (PATCH - 1), places=6)
                self.assertAlmostEqual(uv[2 * i + 1], y / (PATCH - 1), places=6)

    def test_texture_is_the_tile_as_png_with_etag_and_layer(self):
        from osgeo import gdal
        gdal.UseExceptions()
        key = self.keys()[-1]
        _, _, meta = self.daemon.get_json("/v1/models/textured/patches/" + key)
        status, headers, png = self.daemon.request(
            "GET", "/v1/models/textured/patches/%s/texture" % key)
        self.assertEqual(status, 200, png)
        self.assertEqual(headers["Content-Type"], "image/png")
        self.assertEqual(png[:8], b"\x89PNG\r\n\x1a\n")
        self.assertEqual(headers["X-VSM-Texture-Layer"], "Diffuse")
        gdal.FileFromMemBuffer("/vsimem/served.png", png)
        served = gdal.Open("/vsimem/served.png").ReadAsArray()
        gdal.Unlink("/vsimem/served.png")
        tile = gdal.Open(os.path.join(self.root, "textured", "Images", "Diffuse",
                                      meta["folder"] + ".tif")).ReadAsArray()
        self.assertEqual(served.shape, tile.shape)
        self.assertTrue((served == tile).all())
        # Conditional GET, and the layer named in any letter case.
        status, _, data = self.daemon.request(
            "GET", "/v1/models/textured/patches/%s/texture" % key,
            headers={"If-None-Match": headers["ETag"]})
        self.assertEqual((status, data), (304, b""))
        status, _, data = self.daemon.request(
            "GET", "/v1/models/textured/patches/%s/texture/diffuse" % key)
        self.assertEqual((status, data), (200, png))

    def test_missing_textures_and_layers_are_not_found(self):
        for path in ("/v1/models/plain/patches/0_0_0/texture",
                     "/v1/models/plain/patches/0_0_0/coordinates",
                     "/v1/models/textured/patches/0_0_0/texture/Normal",
                     "/v1/models/textured/patches/0_0_0/texture/..%2F..%2Fetc",
                     "/v1/models/textured/patches/9_9_9/texture"):
            status, _, body = self.daemon.request("GET", path)
            self.assertEqual(status, 404, path)
            self.assertEqual(json.loads(body)["error"]["code"], "not_found", path)
        status, _, body = self.daemon.request("GET", "/v1/models/textured/patches/x/texture")
        self.assertEqual(status, 400, body)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--proto", required=True)
    parser.add_argument("--vsm")
    parser.add_argument("--data")
    parser.add_argument("--lib", required=True, help="libvsm_fault_inject.so (tests/fault)")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
