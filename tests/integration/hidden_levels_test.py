#!/usr/bin/python3
"""Hidden levels (issue 28, thesis 5.2): `vsm import --visible-texels-per-quad 4` of PRISM with its
shaded relief at one texel per quad, checked with our own XML, .aara and TIFF readers
(check_import.py), none of vsm's code:

- what other OPC readers see, patchhierarchy.xml alone, is a whole model as OPC.md asks (every
  patch it names has its coordinates and its tile; AvgGeometrySizes covers its levels) that ends
  two levels above the DEM's resolution, where the tiles hold 4 texels per quad;
- the levels below are named in the second file patchhierarchy.xml names (<Vsm><HiddenLevels>),
  and with them every DEM sample is a leaf vertex, every parent the reduction of its children
  (check_import.check);
- each tile of a level above a hidden one is its children's tiles side by side, texel for texel;
  above the visible leaves, tiles are 2 x 2 means as before;
- `vsm validate` passes, before and after `vsm index`; a missing second file is a clear error
  from `vsm validate` and `vsm info`;
- two merges of Jacksboro by the real vsmd keep what other readers see whole and unchanged in
  structure, and every PRISM sample outside the replaced leaf a vertex of a leaf at PRISM's
  resolution (Figure 5.2: hidden detail the merge does not cover is kept); untouched patches'
  files are the same bytes; dropping a revision drops its second file.

Run by ctest:  hidden_levels_test.py --vsm build/server/cli/vsm --vsmd build/server/vsmd
               --data ../shared/data --work <dir>"""

import argparse
import hashlib
import os
import shutil
import subprocess
import sys
import unittest
import xml.etree.ElementTree as ET

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import check_import  # noqa: E402
import harness  # noqa: E402
from check_import import QUADRANTS, child_ci, hidden_file, read_hierarchy, read_tile  # noqa: E402

ARGS = None
PATCH_SIZE = 65
VISIBLE = 4  # texels per quad side OPC readers see; the relief has 1 at the DEM's resolution
HIDDEN_LEVELS = 2


def keys_of(root_folder, children):
    """{(depth, x, y): folder} of a hierarchy, walked from the root."""
    found = {}
    stack = [(root_folder, (0, 0, 0))]
    while stack:
        folder, key = stack.pop()
        found[key] = folder
        for quadrant, child in children.get(folder, {}).items():
            qx, qy = QUADRANTS[quadrant]
            stack.append((child, (key[0] + 1, 2 * key[1] + qx, 2 * key[2] + qy)))
    return found


def digest(opc):
    """SHA-256 of every file under `opc` by relative path."""
    out = {}
    for base, _, files in os.walk(opc):
        for name in files:
            path = os.path.join(base, name)
            with open(path, "rb") as f:
                out[os.path.relpath(path, opc)] = hashlib.sha256(f.read()).hexdigest()
    return out


class HiddenLevels(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        shutil.rmtree(ARGS.work, ignore_errors=True)
        os.makedirs(ARGS.work)
        cls.dem = os.path.join(ARGS.data, "PRISMelevation.tif")
        cls.opc = os.path.join(ARGS.work, "prism")
        harness.import_dem(cls.dem, cls.opc, PATCH_SIZE, "--visible-texels-per-quad",
                           str(VISIBLE))
        cls.patches, root, cls.visible_children = read_hierarchy(cls.opc)
        cls.visible = keys_of(root, cls.visible_children)
        _, _, cls.all_children = read_hierarchy(cls.opc, hidden=True)
        cls.all = keys_of(root, cls.all_children)
        cls.depth = max(k[0] for k in cls.all)

    def assert_the_imports_levels(self, opc):
        """`opc` has the CLI import's patches: the same seen by other readers, the same in all."""
        _, root_folder, children = read_hierarchy(opc)
        self.assertEqual(set(keys_of(root_folder, children)), set(self.visible))
        _, root_folder, children = read_hierarchy(opc, hidden=True)
        self.assertEqual(set(keys_of(root_folder, children)), set(self.all))

    def tile(self, key):
        return read_tile(os.path.join(self.opc, "Images", "Diffuse", self.all[key] + ".tif"))

    def test_a_what_opc_readers_see(self):
        """The hierarchy alone: a whole model down to 4 texels per quad, as OPC.md asks."""
        failures = check_import.Failures()
        checked = check_import.check_pro3d(self.opc, failures)
        failures.assert_none(self)
        self.assertEqual(checked, len(self.visible))
        visible_depth = max(k[0] for k in self.visible)
        self.assertEqual(visible_depth, self.depth - HIDDEN_LEVELS, (visible_depth, self.depth))
        # Its leaves are the visible depth's patches, each with tiles of 4 texels per quad.
        for key, folder in self.visible.items():
            if folder not in self.visible_children:
                self.assertEqual(key[0], visible_depth, key)
                self.assertEqual(self.tile(key).shape[1:], ((PATCH_SIZE - 1) * VISIBLE,) * 2, key)
        # AvgGeometrySizes: one entry per level it names, not the hidden ones.
        ph = child_ci(ET.parse(os.path.join(self.patches, "patchhierarchy.xml")).getroot(),
                      "PatchHierarchy")
        sizes = check_import.numbers(child_ci(ph, "AvgGeometrySizes").text)
        self.assertEqual(len(sizes), visible_depth + 1, sizes)
        # No hidden patch's folder in the file other readers read.
        text = open(os.path.join(self.patches, "patchhierarchy.xml")).read()
        for key, folder in self.all.items():
            if key not in self.visible:
                self.assertNotIn(">%s<" % folder, text)
        print("hidden: OPC readers see %d patches, depth 0-%d; vsm %d, depth 0-%d"
              % (len(self.visible), visible_depth, len(self.all), self.depth))

    def test_b_every_sample_a_leaf_vertex(self):
        """With the second file: the DEM's full resolution, every parent by reduction."""
        self.assertIsNotNone(hidden_file(self.opc))
        self.assertGreater(len(self.all), len(self.visible))
        failures, summary = check_import.check(self.dem, self.opc)
        failures.assert_none(self)
        print("hidden: " + summary)

    def test_c_tiles_above_hidden_levels_are_their_childrens(self):
        """Each level above a hidden one holds its children's texels as they are; above the
        visible leaves, 2 x 2 means."""
        exact = means = 0
        for key, folder in sorted(self.all.items()):
            kids = self.all_children.get(folder, {})
            if not kids:
                continue
            parent = self.tile(key).astype(np.int32)
            size = parent.shape[1]
            for quadrant in kids:
                qx, qy = QUADRANTS[quadrant]
                child = self.tile((key[0] + 1, 2 * key[1] + qx, 2 * key[2] + qy)).astype(np.int32)
                if key[0] + 1 > self.depth - HIDDEN_LEVELS:  # a hidden child
                    self.assertEqual(child.shape[1] * 2, size, (key, quadrant))
                    half = child.shape[1]
                    part = parent[:, qy * half:(qy + 1) * half, qx * half:(qx + 1) * half]
                    np.testing.assert_array_equal(part[:3], child[:3], err_msg=str((key, quadrant)))
                    exact += 1
                else:
                    self.assertEqual(child.shape[1], size, (key, quadrant))
                    half = size // 2
                    mean = (child[:, 0::2, 0::2] + child[:, 1::2, 0::2] + child[:, 0::2, 1::2] +
                            child[:, 1::2, 1::2] + 2) // 4
                    part = parent[:, qy * half:(qy + 1) * half, qx * half:(qx + 1) * half]
                    np.testing.assert_array_equal(part[:3], mean[:3], err_msg=str((key, quadrant)))
                    means += 1
        self.assertGreater(exact, 0)
        self.assertGreater(means, 0)
        print("hidden: %d quadrants as their child's texels, %d as 2 x 2 means" % (exact, means))

    def test_d_validate_index_and_damage(self):
        """vsm validate before and after vsm index; without the second file, clear errors."""
        copy = os.path.join(ARGS.work, "prism-copy")
        shutil.rmtree(copy, ignore_errors=True)
        shutil.copytree(self.opc, copy)
        for step in ("imported", "indexed"):
            if step == "indexed":
                harness.vsm("index", copy, check=True)
            out = harness.vsm("validate", copy)
            self.assertEqual(out.returncode, 0, (step, out.stdout[-2000:], out.stderr[-2000:]))
            # vsm info counts the hidden patches, from the files or from the index.
            info = harness.vsm("info", copy, check=True).stdout
            self.assertIn("hidden      %d patches, depth %d and below" %
                          (len(self.all) - len(self.visible), self.depth - HIDDEN_LEVELS + 1),
                          info)
        # The second file gone: vsm validate (which reads in full) says which, as does vsm info
        # of a model without a current index (with one, info reads the index alone).
        damaged = os.path.join(ARGS.work, "prism-damaged")
        shutil.rmtree(damaged, ignore_errors=True)
        shutil.copytree(self.opc, damaged)
        for opc in (copy, damaged):
            os.remove(hidden_file(opc))
        for command in (["validate", copy], ["validate", damaged], ["info", damaged]):
            out = harness.vsm(*command)
            self.assertNotEqual(out.returncode, 0, command)
            self.assertIn("HiddenLevels", out.stdout + out.stderr, command)
            self.assertIn("missing", out.stdout + out.stderr, command)

    def test_e_a_merge_keeps_the_hidden_levels_it_does_not_cover(self):
        """Jacksboro merged into the model twice by the real vsmd (keep_revisions 2): every level
        served; what other readers see keeps its levels and stays whole; every PRISM sample outside
        the replaced leaf is still a vertex of a leaf at PRISM's resolution, checked against the
        raster (Figure 5.2: uncovered hidden detail is kept, not refilled from coarser levels); the
        untouched patches' files are the same bytes; a second file is left exactly for each kept
        hierarchy."""
        root = os.path.join(ARGS.work, "vsmd")
        shutil.rmtree(root, ignore_errors=True)
        os.makedirs(root)
        model = os.path.join(root, "prism")
        shutil.copytree(self.opc, model)
        harness.import_dem(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"),
                           os.path.join(root, "jack"), PATCH_SIZE)
        before = digest(model)
        # A second file no hierarchy names (as a publish killed before its commit leaves): the
        # first edit's sweep removes it.
        stray = os.path.join(model, "Patches", "vsm-hidden-00000000deadbeef.xml")
        shutil.copy(hidden_file(model), stray)
        daemon = harness.Daemon(root=root, config={"keep_revisions": 2,
                                                   "keep_revisions_seconds": 0})
        try:
            for merge in range(2):
                job = daemon.submit({"type": "merge", "target": "prism", "source": "jack"})
                job = daemon.wait_job(job["id"])
                self.assertEqual(job["state"], "succeeded", job)
                status, _, tree = daemon.get_json("/v1/models/prism/hierarchy")
                self.assertEqual(status, 200, tree)
                nodes = list(harness.walk(tree["root"]))
                served = {tuple(int(v) for v in node["key"].split("_")) for node in nodes}
                # Marked hidden: exactly the patches below the levels other readers see.
                self.assertEqual({tuple(int(v) for v in node["key"].split("_")) for node in nodes
                                  if node.get("hidden")},
                                 {k for k in served if k[0] > self.depth - HIDDEN_LEVELS})
                hidden_leaf = max(k for k in served if k[0] == self.depth)
                for route in ("patches/%d_%d_%d/positions", "3dtiles/%d_%d_%d.glb"):
                    status, _, body = daemon.request(
                        "GET", "/v1/models/prism/" + route % hidden_leaf, timeout=60)
                    self.assertEqual(status, 200, (route, body[:200]))
        finally:
            self.assertEqual(daemon.stop(timeout=30), 0)

        # What other readers see: the same patches, still a whole model.
        _, root_folder, children = read_hierarchy(model)
        self.assertEqual(set(keys_of(root_folder, children)), set(self.visible))
        failures = check_import.Failures()
        check_import.check_pro3d(model, failures)
        failures.assert_none(self)
        visible_depth = self.depth - HIDDEN_LEVELS
        for key, folder in keys_of(root_folder, children).items():
            if key[0] == visible_depth:  # the visible leaves keep 4 texels per quad
                tile = read_tile(os.path.join(model, "Images", "Diffuse", folder + ".tif"))
                self.assertEqual(tile.shape[1:], ((PATCH_SIZE - 1) * VISIBLE,) * 2, key)
        self.assertFalse(os.path.exists(stray))
        # vsm's view: the served keys are the files' (second file followed), deeper where B is.
        patches_dir, root_folder, children = read_hierarchy(model, hidden=True)
        merged = keys_of(root_folder, children)
        self.assertEqual(served, set(merged))
        self.assertGreater(max(k[0] for k in merged), self.depth)
        # Tiles of the parents the merges made: their children's side by side (twice the texels
        # per quad) while that stays within the visible 4, else at their finest child's.
        side = PATCH_SIZE - 1
        by_key = {}
        for key, folder in merged.items():
            by_key[key] = read_tile(os.path.join(model, "Images", "Diffuse", folder + ".tif"))
        checked = 0
        for key, folder in merged.items():
            kids = children.get(folder, {})
            if key[0] < visible_depth or not kids:
                continue
            finest = max(by_key[(key[0] + 1, 2 * key[1] + QUADRANTS[q][0],
                                 2 * key[2] + QUADRANTS[q][1])].shape[1] for q in kids)
            expected = 2 * finest if 2 * finest // side <= VISIBLE else finest
            self.assertEqual(by_key[key].shape[1], expected, key)
            checked += 1
        self.assertGreater(checked, len(self.visible_children))
        # Every leaf at PRISM's resolution holds its raster samples; together, every sample but
        # those of the leaves the merge replaced.
        raster = check_import.Raster(self.dem)
        n = PATCH_SIZE
        coverage = np.zeros((raster.height, raster.width), dtype=np.int32)
        stats = {"samples": 0, "horizontal": 0.0, "vertical": 0.0}
        replaced = np.zeros_like(coverage, dtype=bool)
        kept = 0
        for key, folder in merged.items():
            if key[0] != self.depth:
                continue
            c0, r0 = key[1] * (n - 1), key[2] * (n - 1)
            if folder in children:  # replaced: B's detail below it
                replaced[r0:r0 + n, c0:c0 + n] = True
                continue
            patch = check_import.Patch(patches_dir, folder, key)
            patch.expand(n)
            check_import.check_leaf(patch, key, raster, n, failures, stats, coverage)
            kept += 1
        failures.assert_none(self)
        self.assertGreater(kept, 0)
        self.assertTrue(replaced.any())
        missing = ~np.isnan(raster.heights) & (coverage == 0) & ~replaced
        self.assertFalse(missing.any(), np.argwhere(missing)[:5])
        # Untouched patches: the same files.
        after = digest(model)
        untouched = [name for name in before
                     if name.startswith("Patches/") and name.count("/") == 2 and
                     name.split("/")[1] in merged.values()]
        self.assertGreater(len(untouched), 0)
        for name in untouched:
            self.assertEqual(after.get(name), before[name], name)
        # One second file per kept hierarchy (the current one and revision 2; revision 1's went
        # with it), each named by its hierarchy.
        hierarchies = [n for n in os.listdir(patches_dir) if n == "patchhierarchy.xml" or
                       (n.startswith("vsm-revision-") and n.endswith(".xml"))]
        self.assertEqual(sorted(hierarchies), ["patchhierarchy.xml", "vsm-revision-2.xml"])
        named = {os.path.basename(hidden_file(model, h)) for h in hierarchies}
        present = {n for n in os.listdir(patches_dir) if n.startswith("vsm-hidden-")}
        self.assertEqual(present, named)
        self.assertEqual(len(present), 2)
        out = harness.vsm("validate", model)
        self.assertEqual(out.returncode, 0, out.stdout[-2000:] + out.stderr[-2000:])
        print("hidden: after 2 merges, %d leaves at PRISM's resolution hold their %d samples "
              "exactly; %d untouched files the same bytes" % (kept, stats["samples"],
                                                               len(untouched)))


    def test_f_an_import_job_makes_hidden_levels(self):
        """POST /v1/models with "visible_texels_per_quad": 4 gives the model the CLI gives (the
        same patches, the same ones hidden), and the job says what it was asked."""
        root = os.path.join(ARGS.work, "vsmd-import")
        shutil.rmtree(root, ignore_errors=True)
        os.makedirs(root)
        shutil.copy(self.dem, os.path.join(root, "prism.tif"))
        daemon = harness.Daemon(root=root)
        try:
            job = daemon.submit({"id": "prism", "source": {
                "import": "prism.tif", "patch_size": PATCH_SIZE,
                "visible_texels_per_quad": VISIBLE}}, path="/v1/models")
            self.assertEqual(job["params"]["visible_texels_per_quad"], VISIBLE)
            job = daemon.wait_job(job["id"])
            self.assertEqual(job["state"], "succeeded", job)
        finally:
            self.assertEqual(daemon.stop(timeout=30), 0)
        self.assert_the_imports_levels(os.path.join(root, "prism"))

    def test_g_a_restore_brings_back_the_hidden_levels(self):
        """A merge, then a restore of the import (revision 1) by the real vsmd: the same
        patches, the same ones hidden, each hidden leaf's positions the import's bytes, both
        hierarchy files readable."""
        root = os.path.join(ARGS.work, "vsmd-restore")
        shutil.rmtree(root, ignore_errors=True)
        os.makedirs(root)
        shutil.copytree(self.opc, os.path.join(root, "prism"))
        harness.import_dem(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"),
                           os.path.join(root, "jack"), PATCH_SIZE)

        def state(daemon):
            status, _, tree = daemon.get_json("/v1/models/prism/hierarchy")
            self.assertEqual(status, 200, tree)
            return {node["key"]: bool(node.get("hidden")) for node in harness.walk(tree["root"])}

        daemon = harness.Daemon(root=root)
        try:
            before = state(daemon)
            leaves = [k for k in before if int(k.split("_")[0]) == self.depth][:8]
            positions = {k: daemon.request("GET", "/v1/models/prism/patches/%s/positions" % k)[2]
                         for k in leaves}
            job = daemon.wait_job(daemon.submit({"type": "merge", "target": "prism",
                                                 "source": "jack"})["id"])
            self.assertEqual(job["state"], "succeeded", job)
            self.assertNotEqual(state(daemon), before)
            job = daemon.wait_job(daemon.submit({}, path="/v1/models/prism/revisions/1/restore")
                                  ["id"])
            self.assertEqual(job["state"], "succeeded", job)
            self.assertEqual(state(daemon), before)
            for key, data in positions.items():
                self.assertEqual(
                    daemon.request("GET", "/v1/models/prism/patches/%s/positions" % key)[2], data)
        finally:
            self.assertEqual(daemon.stop(timeout=30), 0)
        model = os.path.join(root, "prism")
        self.assert_the_imports_levels(model)
        out = harness.vsm("validate", model)
        self.assertEqual(out.returncode, 0, out.stdout[-2000:] + out.stderr[-2000:])


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
