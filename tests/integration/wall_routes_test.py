#!/usr/bin/python3
"""Issue 33 item 7 over real HTTP: the routes of a merged vertical rock face.

surfaces.py's `face` (a vertical wall in a local frame, z up, facing -y: A at 0.25 m, B 4x finer
with a 0.3 m Gaussian bump and a 4 cm groove) is written as organized PCD files and imported by
the real `vsm import` (17 x 17 patches, no texture) into a data root; the real vsmd serves both
models and merges B into A through POST /v1/jobs. Then, for the merged wall, over HTTP and
against the surface's closed form (surfaces.py: coords, f_A, f_B), never against vsm's code:

- GET /v1/models/{m}: the finest resolution is B's real 3D spacing (within 15 %), not a spacing
  projected onto a horizontal plane (which would be about half of it on a wall); revision 1 (A)
  says A's; the bounds are the wall's (16 x 16 m, upright, a bump's depth thick).
- GET /v1/models/{m}/hierarchy: every leaf over B is at A's depth + k (2^k >= A's spacing / B's),
  and some of A's leaves away from B are left at A's depth; GET /v1/models/{m}/lod?box=(around
  the bump's top)&resolution=(B's spacing) ends in a leaf of that depth holding the bump's top,
  and at A's spacing stops at A's depth.
- GET /v1/models/{m}/patches/{p}/positions of every leaf over B (.aara, X-VSM-Local2Global): each
  vertex over B (shrunk by one A sample) lies within 1 cm of B's true surface along the normal,
  each comes from a leaf of the new finest depth, and the bump's highest vertex reads at least
  90 % of its 0.3 m.
- GET /v1/models/{m}/3dtiles/tileset.json?compress=none and the float32 GLB of the leaf holding
  the bump's top: decoded with numpy (JSON and BIN chunks, accessors, node transforms, glTF's
  y-up turned back to z-up, the tile transforms): its vertices are the leaf's own (within float32
  rounding), on B's true surface within 1 cm, inside the tile's bounding volume, and read the
  bump; the default (meshopt) GLB's quantized POSITION, through its node's translation and scale,
  spans the same box within one quantization step.
- GET /v1/models/{m}/diff?from=1&to=2: the gained volume is the bump's, 0.3 * 2 pi 0.4^2 m^3,
  within 10 %; the changed area is the closed form's (where |f_B - f_A| exceeds the diff's
  epsilon: the bump and the groove) within 15 %, every changed leaf meets B, and the largest
  displacement is the bump's top, in the leaf that holds it.
- GET /v1/models/{m}/terrain/layer.json: 404 with a JSON error saying the model has no terrain
  because it is not georeferenced (quantized-mesh stays height-field-only).
- GET and POST /v1/models/{m}/ray (issue 29: a ray query for models that are not height
  fields): rays shot horizontally (and tilted) at the wall hit it where the PCD points the test
  wrote say, read back and interpolated bilinearly here, cell by cell (vsm's surface of a grid):
  on the detail model B and on revision 1 (A) within 0.01 mm, on the merged wall over B within
  1 cm of B's surface (the bump included: 0.3 m nearer than A there) and away from B within
  0.01 mm of A's; the normal is the cell's, facing the ray; the leaf named is a leaf of the
  hierarchy holding the point, at the finest depth over B. Rays going away, stopped short or
  beside the wall miss; malformed rays are 400s, an unknown model or revision 404, a POST
  without the token 401.

Run by ctest (routes.wall):
    wall_routes_test.py --vsmd build/server/vsmd --vsm build/server/cli/vsm --work <dir>"""

import argparse
import json
import math
import os
import shutil
import struct
import sys
import time
import unittest

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
import surfaces  # noqa: E402

ARGS = None
TOKEN = "wall-routes-test-token"
TARGET = "wall"
DETAIL = "detail"
PATCH = 17
# B's vertices off its true surface (m), as surface_check.py's on-B.
ON_B_TOLERANCE = 0.01
BUMP_FRACTION = 0.9
RESOLUTION_TOLERANCE = 0.15
VOLUME_TOLERANCE = 0.10
AREA_TOLERANCE = 0.15
# The full Gaussian's volume along the normal.
BUMP_VOLUME = surfaces.BUMP_HEIGHT * 2 * math.pi * surfaces.BUMP_SIGMA ** 2
# The merge job's status is asked at most this often, POLL_SECONDS apart: a bound that only ends
# a hang (the merge takes seconds).
POLLS = 2400
POLL_SECONDS = 0.25
# A box "holds" the bump's top within this (m): the leaves' vertices sample the bump near, not at,
# its top, so their boxes may end a little short of it along the normal.
TOUCH = 0.01
# A ray's hit against a grid's bilinear surface computed here from its PCD points (m): float32
# positions relative to vsm's patch origins round to well under this.
ON_GRID_TOLERANCE = 1e-5


class PcdWall:
    """The surface vsm makes of one of the wall's PCD files, from its points alone: on this wall
    x = u and z = v exactly (the plane y = 0 facing -y; surfaces.py's Face), so a column of the
    organized cloud has one x, a row one z, and each grid cell's bilinear surface is y(x, z),
    bilinear in x and z over the cell's rectangle."""

    def __init__(self, points):
        self.p = points
        self.x = points[0, :, 0]
        self.z = points[:, 0, 2]
        assert np.all(np.diff(self.x) > 0) and np.all(np.diff(self.z) > 0)

    def inside(self, x, z, margin=0.0):
        return (self.x[0] + margin <= x <= self.x[-1] - margin and
                self.z[0] + margin <= z <= self.z[-1] - margin)

    def cell(self, x, z):
        """The cell holding (x, z): (i, j, s, t), s and t in [0, 1] across it."""
        i = int(np.clip(np.searchsorted(self.x, x) - 1, 0, len(self.x) - 2))
        j = int(np.clip(np.searchsorted(self.z, z) - 1, 0, len(self.z) - 2))
        s = (x - self.x[i]) / (self.x[i + 1] - self.x[i])
        t = (z - self.z[j]) / (self.z[j + 1] - self.z[j])
        return i, j, s, t

    def y(self, x, z):
        i, j, s, t = self.cell(x, z)
        c = self.p[j:j + 2, i:i + 2, 1]
        return ((1 - s) * (1 - t) * c[0, 0] + s * (1 - t) * c[0, 1] + (1 - s) * t * c[1, 0] +
                s * t * c[1, 1])

    def normal(self, x, z):
        """The cell's unit normal at (x, z), facing -y (the side the rays come from)."""
        i, j, s, t = self.cell(x, z)
        c = self.p[j:j + 2, i:i + 2, 1]
        y_x = ((1 - t) * (c[0, 1] - c[0, 0]) + t * (c[1, 1] - c[1, 0])) / (self.x[i + 1] -
                                                                           self.x[i])
        y_z = ((1 - s) * (c[1, 0] - c[0, 0]) + s * (c[1, 1] - c[0, 1])) / (self.z[j + 1] -
                                                                           self.z[j])
        n = np.array([y_x, -1.0, y_z])
        return n / np.linalg.norm(n)

    def crossing(self, origin, d, t_end):
        """Where origin + t d (t in [0, t_end], starting in front of the wall and ending behind
        it) crosses the surface, by bisection: y(t) - surface y at (x(t), z(t)) rises through 0
        once (the rays here are far steeper than the surface's slopes)."""
        def g(t):
            p = origin + t * d
            return p[1] - self.y(p[0], p[2])
        lo, hi = 0.0, t_end
        assert g(lo) < 0 < g(hi), (origin, d)
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if g(mid) < 0:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)


# ---- an independent reader of GLB and 3D Tiles (numpy) ------------------------------------------

COMPONENTS = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
# glTF is y-up, 3D Tiles z-up: a runtime turns content by (x, y, z) -> (x, -z, y).
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def decode_glb(data):
    """(glTF JSON, BIN chunk bytes) of a GLB (glTF 2.0's binary container)."""
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data), (magic, version, length)
    json_length, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON", json_type
    gltf = json.loads(data[20:20 + json_length])
    at = 20 + json_length
    bin_chunk = b""
    if at < length:
        bin_length, bin_type = struct.unpack_from("<I4s", data, at)
        assert bin_type == b"BIN\0", bin_type
        bin_chunk = data[at + 8:at + 8 + bin_length]
    return gltf, bin_chunk


def read_accessor(gltf, bin_chunk, index):
    """An accessor of plain (uncompressed) views as an array (count, width), not normalized."""
    accessor = gltf["accessors"][index]
    view = gltf["bufferViews"][accessor["bufferView"]]
    assert view["buffer"] == 0 and "extensions" not in view, view
    dtype = np.dtype(COMPONENTS[accessor["componentType"]])
    width = WIDTHS[accessor["type"]]
    stride = view.get("byteStride", dtype.itemsize * width)
    assert stride == dtype.itemsize * width, "interleaved views are not read here"
    offset = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    values = np.frombuffer(bin_chunk, dtype=dtype, count=accessor["count"] * width, offset=offset)
    return values.reshape(accessor["count"], width)


def node_matrix(node):
    """A glTF node's local 4x4 (row-major here): its matrix, or T * R * S."""
    if "matrix" in node:
        return np.array(node["matrix"], dtype=float).reshape(4, 4).T
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    rotation = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = rotation * np.array(node.get("scale", (1.0, 1.0, 1.0)))[None, :]
    m[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return m


def mesh_nodes(gltf):
    """(mesh index, the node's world matrix within the glTF scene) for every node with a mesh."""
    def visit(index, parent):
        node = gltf["nodes"][index]
        m = parent @ node_matrix(node)
        if "mesh" in node:
            yield node["mesh"], m
        for child in node.get("children", []):
            yield from visit(child, m)

    scene = gltf["scenes"][gltf.get("scene", 0)]
    for root in scene["nodes"]:
        yield from visit(root, np.eye(4))


def transform(m, points):
    return points @ m[:3, :3].T + m[:3, 3]


def tiles(tile, parent=None):
    """(tile, world matrix: the product of the tile transforms, row-major) for every tile."""
    world = np.eye(4) if parent is None else parent
    if "transform" in tile:
        world = world @ np.array(tile["transform"], dtype=float).reshape(4, 4).T
    yield tile, world
    for child in tile.get("children", []):
        yield from tiles(child, world)


def key_of(uri):
    """The patch key of a content URI: "4_6_7.glb?v=3&compress=none" -> "4_6_7"."""
    return uri.partition("?")[0][:-len(".glb")]


def depth_of(key):
    return int(key.split("_")[0])


def box_contains(box, p, margin=0.0):
    return all(box["min"][i] - margin <= p[i] <= box["max"][i] + margin for i in range(3))


def boxes_meet(box, lo, hi):
    return all(box["min"][i] <= hi[i] and lo[i] <= box["max"][i] for i in range(3))


class WallRoutes(unittest.TestCase):
    daemon = None

    @classmethod
    def setUpClass(cls):
        cls.surface = surfaces.make("face")
        work = ARGS.work
        shutil.rmtree(work, ignore_errors=True)
        clouds = os.path.join(work, "clouds")
        cls.surface.write(clouds)
        cls.pcd = {which: PcdWall(surfaces.read_pcd(os.path.join(clouds, which + ".pcd")))
                   for which in "AB"}
        root = os.path.join(work, "root")
        os.makedirs(root)
        start = time.monotonic()
        for cloud, model in (("A.pcd", TARGET), ("B.pcd", DETAIL)):
            harness.vsm("import", os.path.join(clouds, cloud), os.path.join(root, model),
                        "--patch-size", PATCH, "--texture", "none", check=True)
        imported = time.monotonic()
        cls.daemon = harness.Daemon("--token", TOKEN, "--set", "threads.cpu=2", root=root)
        job = cls.daemon.submit({"type": "merge", "target": TARGET, "source": DETAIL})
        for _ in range(POLLS):
            status, _, job = cls.daemon.get_json("/v1/jobs/" + job["id"])
            assert status == 200, (status, job)
            if job["state"] in harness.FINAL_STATES:
                break
            time.sleep(POLL_SECONDS)
        assert job["state"] == "succeeded", "the merge job: %r\n%s" % (job, cls.daemon.log())
        merged = time.monotonic()
        print("\nimports %.1f s, merge job %.1f s: %s" % (imported - start, merged - imported,
                                                        json.dumps(job.get("result"))),
              file=sys.stderr)

        status, _, revisions = cls.daemon.get_json("/v1/models/%s/revisions" % TARGET)
        assert status == 200, revisions
        numbers = [r["revision"] for r in revisions["revisions"]]
        assert len(numbers) == 2, revisions
        cls.before, cls.after = numbers
        status, _, cls.tree = cls.daemon.get_json("/v1/models/%s/hierarchy" % TARGET)
        assert status == 200, cls.tree
        status, _, cls.old_tree = cls.daemon.get_json("/v1/models/%s/hierarchy?rev=%d"
                                                      % (TARGET, cls.before))
        assert status == 200, cls.old_tree

        # What the surface says, in closed form.
        s = cls.surface
        a, b = s.a, s.b
        cls.margin = max(a.du, a.dv)
        b_points = s.grid_points("B")
        # B's real spacing: the mean 3D distance between grid neighbours.
        cls.b_spacing = float(np.mean(np.concatenate([
            np.linalg.norm(b_points[:, 1:] - b_points[:, :-1], axis=-1).ravel(),
            np.linalg.norm(b_points[1:, :] - b_points[:-1, :], axis=-1).ravel()])))
        # A's depth: its bottom patches of PATCH - 1 cells cover its grid; the merge adds k levels,
        # 2^k >= A's spacing / B's.
        cells = max(a.nu, a.nv) - 1
        cls.a_depth = math.ceil(math.log2(cells / (PATCH - 1)))
        cls.finest_depth = cls.a_depth + math.ceil(math.log2(a.du / b.du - 1e-9))
        top_f = s.f_b(np.array(s.bump_u), np.array(s.bump_v))
        cls.bump_top = s.point(np.array(s.bump_u), np.array(s.bump_v), top_f)
        # B's region in space, grown by one A sample (its bump's height included).
        cls.b_lo = b_points.reshape(-1, 3).min(axis=0) - cls.margin
        cls.b_hi = b_points.reshape(-1, 3).max(axis=0) + cls.margin

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is not None:
            code = cls.daemon.stop()
            cls.daemon.cleanup(keep=code != 0)

    # ---- helpers ------------------------------------------------------------------------------

    def get(self, path, status=200, headers=None, timeout=60):
        code, answer_headers, body = self.daemon.request("GET", path, headers=headers,
                                                         timeout=timeout)
        self.assertEqual(code, status, "GET %s: %r" % (path, body[:400]))
        return answer_headers, body

    def get_json(self, path, status=200, timeout=60):
        return json.loads(self.get(path, status, timeout=timeout)[1])

    def leaves(self):
        return [node for node in harness.walk(self.tree["root"]) if node["leaf"]]

    def positions(self, key):
        """A patch's defined vertices in global coordinates (n, 3), from its .aara and its
        X-VSM-Local2Global (row by row, as OPC's Local2Global)."""
        headers, data = self.get("/v1/models/%s/patches/%s/positions" % (TARGET, key))
        name, sizes, payload = harness.decode_aara(data)
        self.assertEqual((name, tuple(sizes)), ("V3f", (PATCH, PATCH)), key)
        local = np.frombuffer(payload, dtype="<f4").reshape(-1, 3).astype(np.float64)
        local = local[~np.isnan(local).any(axis=1)]
        m = np.array([float(v) for v in headers["X-VSM-Local2Global"].split(",")]).reshape(4, 4)
        return transform(m, local)

    def bump_leaf(self):
        """The leaf whose box holds the bump's top (the deepest, should several)."""
        holding = [n for n in self.leaves() if box_contains(n["box"], self.bump_top, TOUCH)]
        self.assertTrue(holding, "no leaf's box holds the bump's top %s" % self.bump_top)
        return max(holding, key=lambda n: depth_of(n["key"]))

    # ---- the checks -----------------------------------------------------------------------------

    def test_model_finest_resolution_is_the_detail_spacing_in_3d(self):
        info = self.get_json("/v1/models/%s" % TARGET)
        old = self.get_json("/v1/models/%s?rev=%d" % (TARGET, self.before))
        finest = info["resolution"]["finest"]
        a_spacing = self.surface.a.du
        print("finest resolution %.5f m (B's 3D spacing %.5f m, B's grid step %.5f m); before the "
              "merge %.5f m; depth %d -> %d" % (finest, self.b_spacing, self.surface.b.du,
                                                old["resolution"]["finest"], old["depth"],
                                                info["depth"]), file=sys.stderr)
        self.assertLessEqual(abs(finest / self.b_spacing - 1), RESOLUTION_TOLERANCE,
                             (finest, self.b_spacing))
        self.assertLessEqual(abs(old["resolution"]["finest"] / a_spacing - 1),
                             RESOLUTION_TOLERANCE, (old["resolution"], a_spacing))
        self.assertEqual(info["depth"], self.finest_depth)
        self.assertEqual(old["depth"], self.a_depth)
        # The bounds: the wall upright, 16 x 16 m along x and z, thin along y (its undulation
        # and the bump), as A's and B's true points span them.
        points = np.concatenate([self.surface.grid_points(w).reshape(-1, 3) for w in "AB"])
        lo, hi = points.min(axis=0), points.max(axis=0)
        bounds = info["bounds"]
        print("bounds %s; the points' %s .. %s" % (bounds, lo.round(4).tolist(),
                                                  hi.round(4).tolist()), file=sys.stderr)
        for i in range(3):
            self.assertAlmostEqual(bounds["min"][i], lo[i], delta=ON_B_TOLERANCE)
            self.assertAlmostEqual(bounds["max"][i], hi[i], delta=ON_B_TOLERANCE)

    def test_hierarchy_and_lod_reach_the_new_depth_at_the_bump(self):
        depth_over_b = set()
        depth_elsewhere = set()
        for leaf in self.leaves():
            meets = boxes_meet(leaf["box"], self.b_lo, self.b_hi)
            (depth_over_b if meets else depth_elsewhere).add(depth_of(leaf["key"]))
        old_depths = {depth_of(n["key"]) for n in harness.walk(self.old_tree["root"]) if n["leaf"]}
        print("leaf depths: over B %s, elsewhere %s; before the merge %s" %
              (sorted(depth_over_b), sorted(depth_elsewhere), sorted(old_depths)), file=sys.stderr)
        self.assertEqual(old_depths, {self.a_depth})
        # Over B only the finest depth; away from it some of A's leaves are left as they were
        # (the merge refines around B, not the whole wall).
        self.assertEqual(depth_over_b, {self.finest_depth})
        self.assertIn(self.a_depth, depth_elsewhere)
        self.assertEqual(depth_of(self.bump_leaf()["key"]), self.finest_depth)

        # The cut for a small box around the bump's top at B's spacing: it ends in the leaf of
        # the finest depth holding the top; at A's spacing it stops at A's depth.
        p = self.bump_top
        box = ",".join("%.6f" % v for v in np.concatenate([p - 0.05, p + 0.05]))
        fine = self.get_json("/v1/models/%s/lod?box=%s&resolution=%.6f"
                             % (TARGET, box, self.b_spacing))
        coarse = self.get_json("/v1/models/%s/lod?box=%s&resolution=%.6f"
                               % (TARGET, box, 1.01 * self.surface.a.du))
        holding = [q for q in fine["patches"] if box_contains(q["box"], p, TOUCH)]
        print("lod at %.4f m: %s; at %.4f m: %s" %
              (self.b_spacing, [q["key"] for q in fine["patches"]], 1.01 * self.surface.a.du,
               [q["key"] for q in coarse["patches"]]), file=sys.stderr)
        self.assertTrue(holding, fine)
        for q in holding:
            self.assertEqual(depth_of(q["key"]), self.finest_depth, q)
            self.assertTrue(q["leaf"], q)
        self.assertEqual({depth_of(q["key"]) for q in fine["patches"]}, {self.finest_depth})
        self.assertTrue(coarse["patches"])
        self.assertEqual({depth_of(q["key"]) for q in coarse["patches"]}, {self.a_depth})

    def test_leaf_positions_over_the_detail_lie_on_its_true_surface(self):
        s = self.surface
        over = [n for n in self.leaves() if boxes_meet(n["box"], self.b_lo, self.b_hi)]
        checked, worst, depths = 0, 0.0, set()
        near_top = []
        for leaf in over:
            points = self.positions(leaf["key"])
            d_b, u, v = s.distance_b(points)
            d_a, _, _ = s.distance_a(points)
            inside = s.b.inside(u, v, self.margin)
            if inside.any():
                depths.add(depth_of(leaf["key"]))
            if inside.any():
                err = np.abs(d_b[inside])
                bad = err > ON_B_TOLERANCE
                self.assertFalse(bad.any(), "leaf %s: %d of %d vertices over B off its surface "
                                 "by more than 1 cm (max %.4f m)" %
                                 (leaf["key"], int(bad.sum()), int(inside.sum()), err.max()))
                checked += int(inside.sum())
                worst = max(worst, float(err.max()))
            near = (u - s.bump_u) ** 2 + (v - s.bump_v) ** 2 <= surfaces.BUMP_SIGMA ** 2
            near_top.extend(d_a[near].tolist())
        bump = max(near_top) if near_top else 0.0
        b_u, b_v = s.b.mesh()
        expected = int(s.b.inside(b_u, b_v, self.margin).sum())
        print("positions: %d leaves over B, %d vertices over B checked (B has %d samples there), "
              "max off B's surface %.4f m, leaf depths %s; the bump reads %.4f m of %.2f m" %
              (len(over), checked, expected, worst, sorted(depths), bump, surfaces.BUMP_HEIGHT),
              file=sys.stderr)
        # At B's density (shared border vertices counted once per leaf: a little more).
        self.assertGreaterEqual(checked, 0.9 * expected)
        self.assertEqual(depths, {self.finest_depth})
        self.assertGreaterEqual(bump, BUMP_FRACTION * surfaces.BUMP_HEIGHT)

    def test_3d_tiles_serve_the_wall_as_a_wall(self):
        s = self.surface
        leaf = self.bump_leaf()
        tileset = self.get_json("/v1/models/%s/3dtiles/tileset.json?compress=none" % TARGET)
        self.assertEqual(tileset["asset"]["version"], "1.1")
        found = [(tile, world) for tile, world in tiles(tileset["root"])
                 if key_of(tile["content"]["uri"]) == leaf["key"]]
        self.assertEqual(len(found), 1, leaf["key"])
        tile, world = found[0]
        uri = tile["content"]["uri"]
        _, data = self.get("/v1/models/%s/3dtiles/%s" % (TARGET, uri))
        gltf, bin_chunk = decode_glb(data)
        self.assertNotIn("extensionsRequired", gltf)
        points = []
        for mesh, m in mesh_nodes(gltf):
            for primitive in gltf["meshes"][mesh]["primitives"]:
                accessor = gltf["accessors"][primitive["attributes"]["POSITION"]]
                self.assertEqual(accessor["componentType"], 5126)
                local = read_accessor(gltf, bin_chunk, primitive["attributes"]["POSITION"])
                points.append(transform(world @ Y_UP_TO_Z_UP @ m, local.astype(np.float64)))
        self.assertTrue(points, "GLB %s has no mesh" % uri)
        points = np.concatenate(points)

        # The leaf's own vertices (float32 relative to the tile's centre: well under 0.1 mm).
        grid = self.positions(leaf["key"])
        nearest = np.array([np.linalg.norm(grid - p, axis=1).min() for p in points])
        # On B's true surface, the bump read, inside the tile's volume.
        d_b, u, v = s.distance_b(points)
        d_a, _, _ = s.distance_a(points)
        inside = s.b.inside(u, v, self.margin)
        near = (u - s.bump_u) ** 2 + (v - s.bump_v) ** 2 <= surfaces.BUMP_SIGMA ** 2
        box = np.array(tile["boundingVolume"]["box"], dtype=float)
        corners = np.array([box[:3] + a * box[3:6] + b * box[6:9] + c * box[9:12]
                            for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
        corners = transform(world, corners)
        extent = points.max(axis=0) - points.min(axis=0)
        print("GLB %s: %d vertices, extent %s m, farthest from the leaf's vertices %.2e m, max off "
              "B's surface %.4f m, the bump reads %.4f m" %
              (uri, len(points), extent.round(3).tolist(), nearest.max(),
               np.abs(d_b[inside]).max(), d_a[near].max() if near.any() else 0.0),
              file=sys.stderr)
        self.assertGreaterEqual(len(points), 0.9 * len(grid))
        self.assertLess(nearest.max(), 1e-4)
        self.assertTrue(inside.all(), "the bump's leaf lies over B")
        self.assertLessEqual(np.abs(d_b).max(), ON_B_TOLERANCE + 1e-5)
        self.assertTrue(near.any())
        self.assertGreaterEqual(d_a[near].max(), BUMP_FRACTION * surfaces.BUMP_HEIGHT)
        self.assertTrue(np.all(points >= corners.min(axis=0) - 1e-4))
        self.assertTrue(np.all(points <= corners.max(axis=0) + 1e-4))
        # Upright: the leaf spans its metre along x and z alike (not flattened onto a plane).
        self.assertGreater(extent[2], 0.9 * extent[0])

        # The default content (KHR_mesh_quantization + EXT_meshopt_compression, not decoded here):
        # the quantized POSITION's min and max through its node's translation and scale span the
        # float32 mesh's box within one step.
        compressed_uri = uri.replace("&compress=none", "").replace("?compress=none", "")
        self.assertNotEqual(compressed_uri, uri)
        _, data = self.get("/v1/models/%s/3dtiles/%s" % (TARGET, compressed_uri))
        gltf, _ = decode_glb(data)
        self.assertIn("KHR_mesh_quantization", gltf["extensionsRequired"])
        (mesh, m), = list(mesh_nodes(gltf))
        accessor = gltf["accessors"][gltf["meshes"][mesh]["primitives"][0]["attributes"]
                                     ["POSITION"]]
        self.assertEqual(accessor["componentType"], 5123)
        step = float(np.abs(m[:3, :3]).max())
        ends = transform(world @ Y_UP_TO_Z_UP @ m,
                         np.array([accessor["min"], accessor["max"]], dtype=float))
        lo, hi = ends.min(axis=0), ends.max(axis=0)
        print("compressed GLB: step %.2e m, box %s .. %s (float32 %s .. %s)" %
              (step, lo.round(4).tolist(), hi.round(4).tolist(),
               points.min(axis=0).round(4).tolist(), points.max(axis=0).round(4).tolist()),
              file=sys.stderr)
        self.assertLess(np.abs(lo - points.min(axis=0)).max(), step + 1e-5)
        self.assertLess(np.abs(hi - points.max(axis=0)).max(), step + 1e-5)

    def test_diff_measures_the_bump_near_the_bump(self):
        s = self.surface
        # A wait for the answer (seconds under load), not a verdict on speed.
        diff = self.get_json("/v1/models/%s/diff?from=%d&to=%d" % (TARGET, self.before,
                                                                   self.after), timeout=300)
        totals = diff["totals"]
        # The closed form's changed area: where |f_B - f_A| (the bump and the groove) exceeds
        # the diff's epsilon, over B (on the base: a plane, so the area on the surface along N).
        step = s.b.du / 8
        grid = surfaces.Grid(s.b.u0 + step / 2, step, int((s.b.u1 - s.b.u0) / step),
                             s.b.v0 + step / 2, step, int((s.b.v1 - s.b.v0) / step))
        u, v = grid.mesh()
        change = s.f_b(u, v) - s.f_a(u, v)
        area = float((np.abs(change) > diff["epsilon"]).sum()) * step * step
        changed = [p for p in diff["patches"] if p["leaf"] and p["changed_area"] > 0]
        outside = [p["key"] for p in changed if not boxes_meet(p["box"], self.b_lo, self.b_hi)]
        top = max(diff["patches"], key=lambda p: p["max"] if p["leaf"] and p["max"] is not None
                  else -math.inf)
        print("diff %d -> %d: gained %.4f m^3 (the bump's %.4f), lost %.4f m^3, changed %.3f m^2 "
              "(closed form %.3f m^2), d %.4f .. %.4f m, %d changed leaves, largest d in %s; "
              "totals %s" % (self.before, self.after, totals["volume_gained"], BUMP_VOLUME,
                             totals["volume_lost"], totals["changed_area"], area, totals["min"],
                             totals["max"], len(changed), top["key"], json.dumps(totals)),
              file=sys.stderr)
        self.assertLessEqual(abs(totals["volume_gained"] / BUMP_VOLUME - 1), VOLUME_TOLERANCE,
                             totals)
        self.assertLessEqual(abs(totals["changed_area"] / area - 1), AREA_TOLERANCE, totals)
        self.assertEqual(outside, [])
        self.assertGreaterEqual(totals["max"], BUMP_FRACTION * surfaces.BUMP_HEIGHT)
        self.assertTrue(box_contains(top["box"], self.bump_top, TOUCH), top)
        self.assertEqual(top["max"], totals["max"])

    # ---- rays (issue 29) -------------------------------------------------------------------------

    def cast(self, rays, model=TARGET, query=""):
        """POSTs `rays` ((origin, direction[, max_distance]) each) to model's /ray: the results."""
        body = {"rays": [dict({"origin": list(map(float, r[0])),
                               "direction": list(map(float, r[1]))},
                              **({"max_distance": r[2]} if len(r) > 2 else {}))
                         for r in rays]}
        status, headers, answer = self.daemon.json("POST", "/v1/models/%s/ray%s" % (model, query),
                                                   body)
        self.assertEqual(status, 200, answer)
        self.assertEqual(answer["status"], "OK")
        self.assertEqual(answer["model"], model)
        self.assertEqual(int(headers["X-VSM-Model-Version"]), answer["model_version"])
        self.assertEqual(len(answer["results"]), len(rays))
        return [r["hit"] for r in answer["results"]]

    def leaf_of(self, hit, tree):
        """The hierarchy node of the leaf a hit names, checked: a leaf holding the point."""
        nodes = {n["key"]: n for n in harness.walk(tree["root"])}
        self.assertIn(hit["patch"], nodes, hit)
        node = nodes[hit["patch"]]
        self.assertTrue(node["leaf"], hit)
        self.assertEqual(hit["depth"], depth_of(hit["patch"]))
        self.assertAlmostEqual(hit["resolution"], node["resolution"], places=9)
        self.assertTrue(box_contains(node["box"], hit["point"], 1e-4), (hit, node["box"]))
        return node

    def check_horizontal_hits(self, hits, targets, wall, tolerance, normal_tolerance):
        """Hits of rays along +y from y = -5 at (x, z) = targets: on `wall` at (x, z), the
        distance from the origin, the cell's normal."""
        worst, worst_normal = 0.0, 0.0
        for hit, (x, z) in zip(hits, targets):
            self.assertIsNotNone(hit, (x, z))
            y = wall.y(x, z)
            point = np.array(hit["point"])
            worst = max(worst, float(np.abs(point - [x, y, z]).max()))
            self.assertLessEqual(np.abs(point - [x, y, z]).max(), tolerance, (x, z, hit, y))
            self.assertAlmostEqual(hit["distance"], point[1] + 5, delta=1e-9)
            off = float(np.linalg.norm(np.array(hit["normal"]) - wall.normal(x, z)))
            worst_normal = max(worst_normal, off)
            self.assertLessEqual(off, normal_tolerance, (x, z, hit))
        return worst, worst_normal

    def test_rays_hit_the_detail_scan_and_the_wall_before_the_merge_where_their_points_say(self):
        rng = np.random.default_rng(29)
        s = self.surface
        for model, query, which, tree in (
                (DETAIL, "", "B", self.get_json("/v1/models/%s/hierarchy" % DETAIL)),
                (TARGET, "?rev=%d" % self.before, "A", self.old_tree)):
            wall = self.pcd[which]
            grid = s.b if which == "B" else s.a
            targets = [(rng.uniform(grid.u0 + 0.01, grid.u1 - 0.01),
                        rng.uniform(grid.v0 + 0.01, grid.v1 - 0.01)) for _ in range(150)]
            hits = self.cast([((x, -5, z), (0, 1, 0)) for x, z in targets], model, query)
            worst, _ = self.check_horizontal_hits(hits, targets, wall, ON_GRID_TOLERANCE, 1e-3)
            for hit in hits:
                self.leaf_of(hit, tree)
            # Tilted rays, their crossing found here by bisection on the cells' surface.
            rays, expected = [], []
            for _ in range(60):
                x = rng.uniform(grid.u0 + 1.2, grid.u1 - 1.2)
                z = rng.uniform(grid.v0 + 1.2, grid.v1 - 1.2)
                d = np.array([rng.uniform(-0.3, 0.3), 1.0, rng.uniform(-0.3, 0.3)])
                origin = np.array([x, -1.5, z]) - 1.5 * np.array([d[0], 0, d[2]])
                t = wall.crossing(origin, d, 3.0)
                rays.append((origin, d))
                expected.append((origin + t * d, t * np.linalg.norm(d)))
            tilted = self.cast(rays, model, query)
            worst_tilted = 0.0
            for hit, (point, distance), (origin, d) in zip(tilted, expected, rays):
                self.assertIsNotNone(hit, (origin, d))
                off = float(np.linalg.norm(np.array(hit["point"]) - point))
                worst_tilted = max(worst_tilted, off)
                self.assertLessEqual(off, ON_GRID_TOLERANCE, (hit, point))
                self.assertAlmostEqual(hit["distance"], distance, delta=ON_GRID_TOLERANCE)
                self.assertLess(np.dot(hit["normal"], d), 0, hit)
            print("rays at %s%s (%s's PCD): 150 horizontal hits within %.2e m, 60 tilted within "
                  "%.2e m" % (model, query, which, worst, worst_tilted), file=sys.stderr)

    def test_rays_hit_the_merged_detail_and_its_bump_and_the_wall_around_it(self):
        s = self.surface
        a, b = self.pcd["A"], self.pcd["B"]
        margin = 2 * s.b.du
        # Over B, away from its groove (whose kinks B's lattice resolves and the merged grid,
        # not aligned with it, cuts by up to a centimetre), the bump's top included.
        rng = np.random.default_rng(33)
        over_b = [(s.bump_u, s.bump_v)]
        while len(over_b) < 100:
            x, z = rng.uniform(s.b.u0, s.b.u1), rng.uniform(s.b.v0, s.b.v1)
            if b.inside(x, z, 3 * margin) and abs(x - s.groove_u) > 3 * s.b.du:
                over_b.append((x, z))
        # Away from B (by one A sample): A's surface, left or subdivided as it was.
        away = []
        while len(away) < 100:
            x, z = rng.uniform(0.01, 15.99), rng.uniform(0.01, 15.99)
            if not (s.b.u0 - self.margin <= x <= s.b.u1 + self.margin and
                    s.b.v0 - self.margin <= z <= s.b.v1 + self.margin):
                away.append((x, z))
        hits = self.cast([((x, -5, z), (0, 1, 0)) for x, z in over_b + away])
        on_b = self.check_horizontal_hits(hits[:len(over_b)], over_b, b, ON_B_TOLERANCE, 0.2)
        on_a = self.check_horizontal_hits(hits[len(over_b):], away, a, ON_GRID_TOLERANCE, 1e-3)
        for hit in hits:
            self.leaf_of(hit, self.tree)
        depths_b = {h["depth"] for h in hits[:len(over_b)]}
        depths_a = {h["depth"] for h in hits[len(over_b):]}
        self.assertEqual(depths_b, {self.finest_depth})
        self.assertIn(self.a_depth, depths_a)

        # The bump: 0.3 m nearer than the wall before the merge, at its top.
        before = self.cast([((s.bump_u, -5, s.bump_v), (0, 1, 0))], query="?rev=%d" % self.before)
        bump = before[0]["distance"] - hits[0]["distance"]
        print("rays at the merged wall: 100 over B within %.4f m of B's PCD surface (normals "
              "within %.3f), 100 away within %.2e m of A's (normals within %.1e); at the bump's top "
              "%.4f m nearer than before the merge (the bump: %.2f m)"
              % (on_b[0], on_b[1], on_a[0], on_a[1], bump, surfaces.BUMP_HEIGHT), file=sys.stderr)
        self.assertGreaterEqual(bump, BUMP_FRACTION * surfaces.BUMP_HEIGHT)
        self.assertLessEqual(bump, surfaces.BUMP_HEIGHT + ON_B_TOLERANCE)

    def test_rays_that_go_away_stop_short_or_pass_beside_miss(self):
        x, z = 3.0, 12.0
        y = self.pcd["A"].y(x, z)
        hits = self.cast([
            ((x, -5, z), (0, -1, 0)),            # in front, going away
            ((x, 5, z), (0, 1, 0)),              # behind, going away
            ((x, -5, z), (0, 1, 0), 4.5 + y),    # stopped short of the wall
            ((x, -5, z), (0, 1, 0), 5.5 + y),    # reaching it
            ((x, 5, z), (0, -1, 0)),             # from behind: the back of the wall
            ((16.5, -5, z), (0, 1, 0)),          # beside the wall
            ((x, -5, 16.5), (0, 1, 0)),          # above it
            ((x, -0.5, z), (1, 0, 0)),           # along it, in front of its relief
        ])
        self.assertEqual([h is None for h in hits],
                         [True, True, True, False, False, True, True, True], hits)
        self.assertAlmostEqual(hits[3]["point"][1], y, delta=ON_GRID_TOLERANCE)
        self.assertAlmostEqual(hits[4]["point"][1], y, delta=ON_GRID_TOLERANCE)
        self.assertAlmostEqual(hits[4]["distance"], 5 - y, delta=ON_GRID_TOLERANCE)
        # Facing the ray from behind: the normal turns with it.
        self.assertLessEqual(np.linalg.norm(np.array(hits[4]["normal"]) +
                                            self.pcd["A"].normal(x, z)), 1e-3)
        # GET answers the same as POST.
        answer = self.get_json("/v1/models/%s/ray?origin=%r,-5,%r&direction=0,2,0" % (TARGET, x, z))
        self.assertEqual(answer["results"][0]["hit"]["point"], hits[3]["point"])

    def test_malformed_rays_are_400s_and_unknown_models_404s(self):
        base = "/v1/models/%s/ray" % TARGET
        for query, fragment in (
                ("", "origin=x,y,z&direction=dx,dy,dz"),
                ("?origin=1,2,3", "'direction' is missing"),
                ("?origin=1,2&direction=0,1,0", "origin must be 3 numbers"),
                ("?origin=1,2,x&direction=0,1,0", "origin coordinate must be a finite number"),
                ("?origin=1,2,3&direction=0,0,0", "direction must not be zero"),
                ("?origin=1,2,3&direction=nan,1,0", "must be a finite number"),
                ("?origin=1,2,3&direction=1e308,1e308,0", "direction must not be zero"),
                ("?origin=1,2,3&direction=0,1,0&max_distance=-1", "max_distance must be >= 0"),
                ("?origin=1,2,3&direction=0,1,0&max_distance=far", "max_distance must be"),
                ("?origin=1,2,3&direction=0,1,0&rev=first", "rev")):
            status, _, body = self.daemon.request("GET", base + query)
            self.assertEqual(status, 400, (query, body))
            error = json.loads(body)["error"]
            self.assertEqual(error["code"], "invalid_argument")
            self.assertIn(fragment, error["message"], query)
        ray = {"origin": [1, -5, 1], "direction": [0, 1, 0]}
        auth = {"Authorization": "Bearer " + TOKEN, "Content-Type": "application/json"}
        for body, fragment in (
                (b"{\"rays\": [", "JSON"),
                (json.dumps({"rays": []}), "non-empty array"),
                (json.dumps({"rays": [ray], "colour": "red"}), "unknown member 'colour'"),
                (json.dumps({"rays": [ray, dict(ray, colour=1)]}), "ray 2: unknown member"),
                (json.dumps({"rays": [ray, {"origin": [1, 2]}]}), "ray 2: 'origin' must be"),
                (json.dumps({"rays": [dict(ray, direction=[0, 0, 0])]}), "must not be zero"),
                (json.dumps({"rays": [dict(ray, max_distance=-2)]}), "must be >= 0"),
                (json.dumps({"rays": [dict(ray, max_distance="far")]}), "must be a number"),
                (json.dumps({"rays": [ray] * 1001}), "1001 rays, more than the 1000")):
            status, _, answer = self.daemon.request("POST", base, body=body, headers=auth)
            self.assertEqual(status, 400, (body[:80], answer))
            error = json.loads(answer)["error"]
            self.assertEqual(error["code"], "invalid_argument")
            self.assertIn(fragment, error["message"], body[:80])
        status, _, _ = self.daemon.request("POST", base, body=json.dumps({"rays": [ray]}),
                                           headers={"Content-Type": "application/json"})
        self.assertEqual(status, 401)
        for path in ("/v1/models/nothing/ray?origin=1,2,3&direction=0,1,0",
                     base + "?origin=1,2,3&direction=0,1,0&rev=99"):
            status, _, body = self.daemon.request("GET", path)
            self.assertEqual(status, 404, (path, body))
            self.assertEqual(json.loads(body)["error"]["code"], "not_found")

    def test_terrain_is_a_clear_404_for_a_local_frame_wall(self):
        for path in ("terrain/layer.json", "terrain/0/0/0.terrain"):
            status, headers, body = self.daemon.request("GET", "/v1/models/%s/%s" % (TARGET, path))
            print("GET .../%s: %d %s" % (path, status, body[:300]), file=sys.stderr)
            self.assertEqual(status, 404, body[:300])
            self.assertTrue(headers["Content-Type"].startswith("application/json"), headers)
            error = json.loads(body)["error"]
            self.assertEqual(error["code"], "not_found")
            self.assertIn("no terrain", error["message"])
            self.assertIn("georeference", error["message"])


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--work", required=True, help="where the clouds and the data root go")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    harness.run_tests(rest)


if __name__ == "__main__":
    main()
