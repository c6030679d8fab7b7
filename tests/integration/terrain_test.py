#!/usr/bin/python3
"""Quantized-mesh terrain end to end: the real vsmd on 127.0.0.1:0 (harness.py)
over PRISM and Jacksboro imported by the real `vsm` at --patch-size 65, and an organized point
cloud in its own frame, driven over real HTTP; every tile is read by the decoder below, written
from the quantized-mesh-1.0 spec (github.com/CesiumGS/quantized-mesh), not from vsm's encoder,
and checked against the source rasters read by GDAL (numpy for the maths):

- layer.json: the fields CesiumTerrainProvider reads; `available` levels closed under parents;
  every available tile meets the DEM; level 0 both tiles;
- tiles at levels 0..13 over the data (PRISM; Jacksboro after merging it into PRISM) and their
  neighbours, with and without gzip and extensions: header min/max heights hold every vertex's
  height, the bounding sphere every vertex (ECEF, own WGS 84 formulas); edge lists are exactly
  the vertices on each edge; neighbours' shared edges match (positions, and heights within both
  tiles' quantisation); oct-encoded normals are unit vectors within 10 degrees of normals from
  the DEM (GDAL's raster, the same finite differences); heights at vertices match the DEM
  sampled bilinearly within the relief of the DEM cells around them (the model's surface is a
  piecewise-linear interpolation of the same samples) where the tile samples the finest data;
- Jacksboro warped to UTM 16N and imported (a projected DEM) is terrain too, with those heights;
- the metadata extension's `available` equals layer.json's for the children;
- after the merge (a job): tiles over Jacksboro change ETag, tiles far from it keep theirs,
  `available` grows (deeper levels over Jacksboro);
- 304 on If-None-Match, 400 for coordinates outside the scheme or malformed, a flat tile at 0 m
  outside the model, 404 with a JSON error for the point cloud (not a height field).

    /usr/bin/python3 terrain_test.py --vsm <vsm> --vsmd <vsmd> --data <shared/data> --work <dir>
"""

import argparse
import gzip
import json
import math
import os
import re
import shutil
import struct
import sys
import threading
import time
import unittest

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402

gdal.UseExceptions()

ARGS = None
TOKEN = "terrain-test-token"
AUTH = {"Authorization": "Bearer " + TOKEN}
CESIUM_ACCEPT = ("application/vnd.quantized-mesh;extensions=octvertexnormals-metadata,"
                 "application/octet-stream;q=0.9,*/*;q=0.01")
PLAIN_ACCEPT = "application/vnd.quantized-mesh,application/octet-stream;q=0.9"
PRISM = "PRISMelevation"
JACK = "jacksboro_fault_dem"

# ---- WGS 84 (own formulas) ---------------------------------------------------------------------

A = 6378137.0
F = 1 / 298.257223563
B = A * (1 - F)
E2 = F * (2 - F)


def ecef(lon, lat, h):
    lon, lat = math.radians(lon), math.radians(lat)
    n = A / math.sqrt(1 - E2 * math.sin(lat) ** 2)
    return np.array([(n + h) * math.cos(lat) * math.cos(lon), (n + h) * math.cos(lat) * math.sin(lon),
                     (n * (1 - E2) + h) * math.sin(lat)])


def tile_rect(z, x, y):
    span = 180.0 / (1 << z)
    return -180 + x * span, -90 + y * span, -180 + (x + 1) * span, -90 + (y + 1) * span


def tile_of(z, lon, lat):
    span = 180.0 / (1 << z)
    return z, int((lon + 180) // span), int((lat + 90) // span)


# ---- quantized-mesh-1.0 reader, from the spec ---------------------------------------------------

def zigzag(v):
    return (v >> 1) ^ (-(v & 1))


def decode_tile(data):
    """A dict of the tile's parts; asserts the layout holds exactly."""
    at = 0
    header = struct.unpack_from("<3d2f4d3d", data, at)
    at += 88
    t = {"center": header[0:3], "min": header[3], "max": header[4], "sphere": header[5:9],
         "horizon": header[9:12]}
    (n,) = struct.unpack_from("<I", data, at)
    at += 4
    arrays = []
    for _ in range(3):
        raw = struct.unpack_from("<%dH" % n, data, at)
        at += 2 * n
        value, out = 0, []
        for r in raw:
            value += zigzag(r)
            out.append(value)
        arrays.append(out)
    t["u"], t["v"], t["h"] = arrays
    index_size = 4 if n > 65536 else 2
    at += (-at) % index_size
    (triangles,) = struct.unpack_from("<I", data, at)
    at += 4
    fmt = "I" if index_size == 4 else "H"
    codes = struct.unpack_from("<%d%s" % (triangles * 3, fmt), data, at)
    at += index_size * triangles * 3
    highest, indices = 0, []
    for code in codes:
        indices.append(highest - code)
        if code == 0:
            highest += 1
    t["indices"] = indices
    for edge in ("west", "south", "east", "north"):
        (count,) = struct.unpack_from("<I", data, at)
        at += 4
        t[edge] = list(struct.unpack_from("<%d%s" % (count, fmt), data, at))
        at += index_size * count
    t["extensions"] = {}
    while at < len(data):
        ext_id, length = struct.unpack_from("<BI", data, at)
        at += 5
        t["extensions"][ext_id] = data[at:at + length]
        at += length
    assert at == len(data), (at, len(data))
    return t


def oct_decode(x, y):
    fx, fy = x / 255.0 * 2 - 1, y / 255.0 * 2 - 1
    fz = 1 - abs(fx) - abs(fy)
    if fz < 0:
        ox = fx
        fx = (1 - abs(fy)) * (1 if ox >= 0 else -1)
        fy = (1 - abs(ox)) * (1 if fy >= 0 else -1)
    v = np.array([fx, fy, fz])
    return v / np.linalg.norm(v)


def vertices(t, key):
    """[(lon, lat, height)] of the decoded tile's vertices."""
    west, south, east, north = tile_rect(*key)
    lo, hi = t["min"], t["max"]
    return [(west + (east - west) * u / 32767.0, south + (north - south) * v / 32767.0,
             lo + (hi - lo) * h / 32767.0) for u, v, h in zip(t["u"], t["v"], t["h"])]


# ---- the DEMs ------------------------------------------------------------------------------------

class Dem:
    def __init__(self, path):
        self.a, self.gt = harness.read_raster(path)
        self.h, self.w = self.a.shape

    def bounds(self):
        gt = self.gt
        return (gt[0], gt[3] + gt[5] * self.h, gt[0] + gt[1] * self.w, gt[3])

    def cell(self, lon, lat):
        """(col, row) in pixel-centre units (sample (c, r) at c, r)."""
        return (lon - self.gt[0]) / self.gt[1] - 0.5, (lat - self.gt[3]) / self.gt[5] - 0.5

    def bilinear(self, lon, lat):
        """(value, relief of the 4 x 4 samples around) or None outside or by no-data."""
        c, r = self.cell(lon, lat)
        c0, r0 = int(math.floor(c)), int(math.floor(r))
        if c0 < 1 or r0 < 1 or c0 + 2 >= self.w or r0 + 2 >= self.h:
            return None
        block = self.a[r0 - 1:r0 + 3, c0 - 1:c0 + 3]
        if np.isnan(block).any():
            return None
        fc, fr = c - c0, r - r0
        q = self.a[r0:r0 + 2, c0:c0 + 2]
        value = (q[0, 0] * (1 - fc) * (1 - fr) + q[0, 1] * fc * (1 - fr) + q[1, 0] * (1 - fc) * fr
                 + q[1, 1] * fc * fr)
        return value, float(block.max() - block.min())

    def normal(self, lon, lat, d):
        """The DEM's normal (ECEF) by central differences over +-d degrees, or None."""
        s = [self.bilinear(lon + dl, lat + dp) for dl, dp in ((d, 0), (-d, 0), (0, d), (0, -d))]
        if any(v is None for v in s):
            return None
        e, w, n, so = (ecef(lon + dl, lat + dp, v[0]) for (dl, dp), v in
                       zip(((d, 0), (-d, 0), (0, d), (0, -d)), s))
        c = np.cross(e - w, n - so)
        return c / np.linalg.norm(c)


def write_cloud(path, size=17):
    """An organized point cloud in a local frame (metres near the origin): a gentle hill."""
    lines = ["# .PCD v0.7", "VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F",
             "COUNT 1 1 1", "WIDTH %d" % size, "HEIGHT %d" % size, "VIEWPOINT 0 0 0 1 0 0 0",
             "POINTS %d" % (size * size), "DATA ascii"]
    for j in range(size):
        for i in range(size):
            lines.append("%g %g %g" % (i * 0.5, j * 0.5, math.sin(i * 0.3) * math.cos(j * 0.2)))
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


# ---- the test ----------------------------------------------------------------------------------

# Places: inside PRISM far from Jacksboro (Kansas), and Jacksboro's centre.
FAR = (-98.0, 38.5)
JACK_CENTRE = (-84.25, 36.30)


class Terrain(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        root = os.path.join(ARGS.work, "root")
        shutil.rmtree(ARGS.work, ignore_errors=True)
        os.makedirs(root)
        for name in (PRISM, JACK):
            harness.import_dem(os.path.join(ARGS.data, name + ".tif"), os.path.join(root, name), 65,
                               "--texture", "none")
        # Jacksboro in a projected CRS (UTM 16N, 90 m pixels, bilinear), as a projected DEM.
        utm = os.path.join(ARGS.work, "jack_utm.tif")
        gdal.Warp(utm, os.path.join(ARGS.data, JACK + ".tif"), dstSRS="EPSG:32616", xRes=90,
                  yRes=90, resampleAlg="bilinear", dstNodata=-32768)
        harness.import_dem(utm, os.path.join(root, "jack_utm"), 65, "--texture", "none")
        cloud = os.path.join(ARGS.work, "cloud.pcd")
        write_cloud(cloud)
        harness.import_dem(cloud, os.path.join(root, "cloud"), 9, "--texture", "none")
        cls.dems = {PRISM: Dem(os.path.join(ARGS.data, PRISM + ".tif")),
                    JACK: Dem(os.path.join(ARGS.data, JACK + ".tif"))}
        cls.daemon = harness.Daemon("--token", TOKEN, "--set", "threads.cpu=2", root=root)
        cls.stats = {"tiles": 0, "normals": 0, "normal_max_deg": 0.0, "heights": 0,
                     "height_max_excess": -1e9, "hop_cameras": 0}

    @classmethod
    def tearDownClass(cls):
        code = cls.daemon.stop()
        cls.daemon.cleanup(keep=code != 0)
        print("\nterrain: %(tiles)d tiles decoded, %(normals)d normals compared (max %(normal_max_deg).2f"
              " deg), %(heights)d heights compared, horizon point below the horizon for"
              " %(hop_cameras)d cameras" % cls.stats, file=sys.stderr)

    # -- helpers --

    def get(self, path, headers=None):
        return self.daemon.request("GET", path, headers=headers or {})

    def layer(self, model=PRISM):
        """layer.json, plain; fetched gzipped too, which must decompress to the same bytes."""
        path = "/v1/models/%s/terrain/layer.json" % model
        status, headers, body = self.get(path)
        self.assertEqual(status, 200, body[:300])
        self.assertIsNone(headers.get("Content-Encoding"))
        self.assertIn("Accept-Encoding", headers.get("Vary", ""))
        status, zipped_headers, zipped = self.get(path, {"Accept-Encoding": "gzip"})
        self.assertEqual(status, 200, zipped[:300])
        self.assertEqual(zipped_headers.get("Content-Encoding"), "gzip")
        self.assertIn("Accept-Encoding", zipped_headers.get("Vary", ""))
        self.assertNotEqual(zipped_headers["ETag"], headers["ETag"])
        self.assertEqual(gzip.decompress(zipped), body)
        self.assertLess(len(zipped), len(body))
        return json.loads(body), headers

    def tile(self, key, accept=CESIUM_ACCEPT, gz=False, model=PRISM, status=200):
        headers = {"Accept": accept}
        if gz:
            headers["Accept-Encoding"] = "gzip"
        code, h, body = self.get("/v1/models/%s/terrain/%d/%d/%d.terrain" % ((model,) + key),
                                 headers)
        self.assertEqual(code, status, body[:300])
        if status != 200:
            return None, h, body
        self.assertEqual(h["Content-Type"], "application/vnd.quantized-mesh")
        self.assertIn("Accept-Encoding", h.get("Vary", ""))
        self.assertTrue(h.get("ETag"))
        if gz:
            self.assertEqual(h.get("Content-Encoding"), "gzip")
            body = gzip.decompress(body)
        else:
            self.assertIsNone(h.get("Content-Encoding"))
        return decode_tile(body), h, body

    def check_tile(self, t, key, layer=None, normals=True):
        """The spec's invariants of one decoded tile (see the module's docstring)."""
        Terrain.stats["tiles"] += 1
        n = len(t["u"])
        self.assertEqual(n, 65 * 65)
        self.assertEqual(len(t["indices"]), 64 * 64 * 6)
        self.assertLessEqual(t["min"], t["max"])
        verts = vertices(t, key)
        centre, radius = np.array(t["sphere"][:3]), t["sphere"][3]
        for (lon, lat, h), hq in zip(verts, t["h"]):
            self.assertTrue(0 <= hq <= 32767)
            self.assertTrue(t["min"] - 1e-6 <= h <= t["max"] + 1e-6)
            self.assertLessEqual(np.linalg.norm(ecef(lon, lat, h) - centre), radius * (1 + 1e-9) + 1e-6)
        self.check_horizon(t, verts)
        for name, coord, value in (("west", "u", 0), ("south", "v", 0), ("east", "u", 32767),
                                   ("north", "v", 32767)):
            self.assertEqual(sorted(t[name]), [i for i in range(n) if t[coord][i] == value], name)
        self.assertTrue(all(0 <= i < n for i in t["indices"]))
        for k in range(0, len(t["indices"]), 3):
            a, b, c = t["indices"][k:k + 3]
            area = ((t["u"][b] - t["u"][a]) * (t["v"][c] - t["v"][a])
                    - (t["v"][b] - t["v"][a]) * (t["u"][c] - t["u"][a]))
            self.assertGreater(area, 0, "triangle %d not counter-clockwise" % (k // 3))
        if normals:
            self.assertIn(1, t["extensions"])
            oct_bytes = t["extensions"][1]
            self.assertEqual(len(oct_bytes), 2 * n)
        if layer is not None and 4 in t["extensions"]:
            meta = t["extensions"][4]
            (length,) = struct.unpack_from("<I", meta, 0)
            self.assertEqual(length + 4, len(meta))
            available = json.loads(meta[4:].decode())["available"]
            z, x, y = key
            expected = set()
            if z + 1 < len(layer["available"]):
                for r in layer["available"][z + 1]:
                    for cy in (2 * y, 2 * y + 1):
                        for cx in (2 * x, 2 * x + 1):
                            if r["startX"] <= cx <= r["endX"] and r["startY"] <= cy <= r["endY"]:
                                expected.add((cx, cy))
            got = set()
            for level in available[:1]:
                for r in level:
                    for cy in range(r["startY"], r["endY"] + 1):
                        for cx in range(r["startX"], r["endX"] + 1):
                            got.add((cx, cy))
            self.assertEqual(got, expected, key)

    def check_horizon(self, t, verts):
        """The horizon occlusion point (ellipsoid-scaled ECEF) culls only what is hidden: from
        random cameras, whenever the point is below the horizon (CesiumJS's
        EllipsoidalOccluder.isScaledSpacePointVisible, written from its horizon-culling article),
        every vertex is too (vertices below the ellipsoid taken at height 0, as CesiumJS does)."""
        radii = np.array([A, A, B])
        hop = np.array(t["horizon"])
        self.assertTrue(np.isfinite(hop).all())
        self.assertGreaterEqual(np.linalg.norm(hop), 1.0)
        pts = np.array([ecef(lon, lat, max(h, 0.0)) for lon, lat, h in verts[::7]]) / radii
        rng = np.random.default_rng(14)
        occluded_cameras = 0
        for _ in range(300):
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            cam = d * (1 + 10 ** rng.uniform(-4.5, 0.5))  # 40 m .. 20000 km up (scaled units)
            vh2 = cam.dot(cam) - 1

            def occluded(q):
                vt = q - cam
                vtdc = -(vt @ cam)
                return (vtdc > vh2) & (vtdc * vtdc / np.einsum("...i,...i", vt, vt) > vh2)

            if occluded(hop):
                occluded_cameras += 1
                self.assertTrue(occluded(pts).all(), "a vertex visible from %s though the horizon "
                                "occlusion point is not" % (cam * radii))
        Terrain.stats["hop_cameras"] = Terrain.stats.get("hop_cameras", 0) + occluded_cameras

    def check_against_dem(self, t, key, dem, heights=True, normals=True):
        """Normals within 10 degrees of the DEM's; heights within the local relief."""
        west, south, east, north = tile_rect(*key)
        d = (east - west) / 64
        for k, (lon, lat, h) in enumerate(vertices(t, key)):
            if normals and 1 in t["extensions"]:
                ref = dem.normal(lon, lat, d)
                if ref is not None and dem.bilinear(lon, lat) is not None:
                    ext = t["extensions"][1]
                    nv = oct_decode(ext[2 * k], ext[2 * k + 1])
                    self.assertAlmostEqual(float(np.linalg.norm(nv)), 1.0, places=9)
                    angle = math.degrees(math.acos(max(-1.0, min(1.0, float(np.dot(nv, ref))))))
                    Terrain.stats["normals"] += 1
                    Terrain.stats["normal_max_deg"] = max(Terrain.stats["normal_max_deg"], angle)
                    self.assertLess(angle, 10.0, "normal at %.5f %.5f of %s" % (lon, lat, key))
            if heights:
                ref = dem.bilinear(lon, lat)
                if ref is not None:
                    value, relief = ref
                    tolerance = relief + (t["max"] - t["min"]) / 32767.0 + 0.5
                    Terrain.stats["heights"] += 1
                    Terrain.stats["height_max_excess"] = max(Terrain.stats["height_max_excess"],
                                                             abs(h - value) - tolerance)
                    self.assertLessEqual(abs(h - value), tolerance,
                                         "height at %.5f %.5f of %s" % (lon, lat, key))

    def check_neighbours(self, a, ka, b, kb):
        """Tiles a (west or south) and b (east or north) share an edge: same positions and
        heights within both tiles' quantisation."""
        if ka[1] + 1 == kb[1]:
            edge_a, edge_b, along = "east", "west", "v"
        else:
            self.assertEqual(ka[2] + 1, kb[2])
            edge_a, edge_b, along = "north", "south", "u"
        va, vb = vertices(a, ka), vertices(b, kb)
        ea = sorted((a[along][i], va[i]) for i in a[edge_a])
        eb = sorted((b[along][i], vb[i]) for i in b[edge_b])
        self.assertEqual(len(ea), len(eb))
        tolerance = (a["max"] - a["min"] + b["max"] - b["min"]) / 32767.0 + 1e-6
        for (qa, pa), (qb, pb) in zip(ea, eb):
            self.assertEqual(qa, qb)
            self.assertAlmostEqual(pa[0], pb[0], places=9)
            self.assertAlmostEqual(pa[1], pb[1], places=9)
            self.assertLessEqual(abs(pa[2] - pb[2]), tolerance, (ka, kb, pa, pb))
        if 1 in a["extensions"] and 1 in b["extensions"]:
            for i, j in zip(sorted(a[edge_a], key=lambda i: a[along][i]),
                            sorted(b[edge_b], key=lambda j: b[along][j])):
                na = oct_decode(a["extensions"][1][2 * i], a["extensions"][1][2 * i + 1])
                nb = oct_decode(b["extensions"][1][2 * j], b["extensions"][1][2 * j + 1])
                self.assertGreater(float(np.dot(na, nb)), math.cos(math.radians(2)), (ka, kb))

    def check_layer(self, layer, dems):
        for field, value in (("tilejson", "2.1.0"), ("format", "quantized-mesh-1.0"),
                             ("version", "1.0.0"), ("scheme", "tms"), ("projection", "EPSG:4326")):
            self.assertEqual(layer[field], value, field)
        # The tiles' URL names the model version the layer is of (not CesiumJS's "{version}").
        self.assertEqual(layer["tiles"], ["{z}/{x}/{y}.terrain?v=%d" % layer["model_version"]])
        self.assertEqual(layer["extensions"], ["octvertexnormals", "metadata"])
        # CesiumJS takes availability from the tiles' metadata (each names its children) only
        # with this; with `available` alone it fails on tiles that carry the metadata extension.
        self.assertEqual(layer["metadataAvailability"], 1)
        self.assertEqual(layer["minzoom"], 0)
        self.assertEqual(layer["maxzoom"], len(layer["available"]) - 1)
        self.assertEqual(layer["available"][0], [{"startX": 0, "startY": 0, "endX": 1, "endY": 0}])
        w, s, e, n = layer["bounds"]
        bw, bs, be, bn = dems[PRISM].bounds()
        # The model's vertices are the pixel centres: inside the raster, half a pixel in.
        half = dems[PRISM].gt[1] / 2
        for got, want in ((w, bw + half), (s, bs + half), (e, be - half), (n, bn - half)):
            self.assertAlmostEqual(got, want, delta=half * 1.01)
        levels = []
        for z, ranges in enumerate(layer["available"]):
            tiles = set()
            for r in ranges:
                for y in range(r["startY"], r["endY"] + 1):
                    for x in range(r["startX"], r["endX"] + 1):
                        tiles.add((x, y))
            levels.append(tiles)
            if z > 0:
                self.assertTrue(tiles, "level %d empty" % z)
                for x, y in tiles:
                    self.assertIn((x // 2, y // 2), levels[z - 1], "parent of %d/%d/%d" % (z, x, y))
                    tw, ts, te, tn = tile_rect(z, x, y)
                    self.assertTrue(any(tw <= db[2] and db[0] <= te and ts <= db[3] and db[1] <= tn
                                        for db in (d.bounds() for d in dems.values())),
                                    "%d/%d/%d meets no DEM" % (z, x, y))
        return levels

    # -- the scenario (one test: the merge divides it into before and after) --

    def test_saved_footprints_spare_the_next_daemon_reading_every_patch(self):
        # The first layer of a process reads every patch for its footprints (minutes at 10^6
        # patches); the writer saves them beside the model, and the next daemon reads only the
        # root (its height field check) when nothing changed. A damaged file is ignored (a
        # warning), every patch read again and the file saved afresh.
        root = os.path.join(ARGS.work, "saved-root")
        shutil.rmtree(root, ignore_errors=True)
        os.makedirs(root)
        shutil.copytree(os.path.join(ARGS.work, "root", JACK), os.path.join(root, JACK))
        saved = os.path.join(root, JACK, "Patches", "vsm-terrain-footprints.bin")
        if os.path.exists(saved):  # the class's daemon saved them already
            os.remove(saved)
        patches = len(self.daemon.keys(JACK))
        self.assertGreater(patches, 4)
        path = "/v1/models/%s/terrain/layer.json" % JACK
        layers, files = [], []
        for round in ("first", "saved", "damaged"):
            daemon = harness.Daemon("--token", TOKEN, root=root)
            try:
                status, _, body = daemon.request("GET", path)
                self.assertEqual(status, 200, body[:300])
                layers.append(json.loads(body))
            finally:
                code = daemon.stop()
            self.assertEqual(code, 0, daemon.log()[-2000:])
            log = daemon.log()
            read = re.search(r"read (\d+) of (\d+) patches", log)
            self.assertIsNotNone(read, log[-2000:])
            self.assertEqual(int(read.group(2)), patches)
            if round == "saved":
                self.assertEqual(int(read.group(1)), 1, "the root's check only")
            else:
                self.assertEqual(int(read.group(1)), patches + 1, "every patch, the root twice")
            if round == "damaged":
                self.assertIn("saved terrain footprints: checksum mismatch", log)
            with open(saved, "rb") as f:
                files.append(f.read())
            if round == "saved":
                with open(saved, "r+b") as f:  # a bit flipped in a footprint
                    f.seek(len(files[-1]) // 2)
                    byte = f.read(1)[0]
                    f.seek(len(files[-1]) // 2)
                    f.write(bytes([byte ^ 0x10]))
        self.assertEqual(layers[1], layers[0])
        self.assertEqual(layers[2], layers[0])
        self.assertEqual(files[1], files[0], "not saved again when nothing was read")
        self.assertEqual(files[2], files[0], "saved afresh after the damage: the same bytes")

        # A save that fails (the disk full as the file is created): a warning, the layer served
        # all the same, nothing left behind, and the model as it was.
        os.remove(saved)
        hierarchy = os.path.join(root, JACK, "Patches", "patchhierarchy.xml")
        with open(hierarchy, "rb") as f:
            before = f.read()
        arm = os.path.join(ARGS.work, "footprints.arm")
        report = os.path.join(ARGS.work, "footprints.faults")
        for f in (arm, report):
            if os.path.exists(f):
                os.remove(f)
        daemon = harness.Daemon("--token", TOKEN, root=root,
                                env=harness.fault_env(ARGS.lib, root, arm=arm, report=report))
        try:
            with open(arm, "w") as f:
                f.write("create ENOSPC")
            status, _, body = daemon.request("GET", path)
            self.assertEqual(status, 200, body[:300])
            self.assertEqual(json.loads(body), layers[0])
        finally:
            code = daemon.stop()
        self.assertEqual(code, 0, daemon.log()[-2000:])
        with open(report) as f:
            self.assertIn("vsm-terrain-footprints.bin", f.read(), "the fault hit the save")
        self.assertIn("terrain footprints not saved", daemon.log())
        leftovers = [n for n in os.listdir(os.path.join(root, JACK, "Patches"))
                     if "vsm-terrain-footprints" in n]
        self.assertEqual(leftovers, [])
        with open(hierarchy, "rb") as f:
            self.assertEqual(f.read(), before)

    def test_terrain(self):
        prism, jack = self.dems[PRISM], self.dems[JACK]

        # Errors first: the point cloud, bad coordinates.
        for path in ("/v1/models/cloud/terrain/layer.json", "/v1/models/cloud/terrain/0/0/0.terrain"):
            status, _, body = self.get(path)
            self.assertEqual(status, 404, body[:300])
            error = json.loads(body)["error"]
            self.assertEqual(error["code"], "not_found")
            self.assertIn("no terrain", error["message"])
            self.assertIn("georeference", error["message"])
        for bad in ("0/2/0", "0/0/1", "3/16/0", "25/0/0", "x/0/0", "1/-1/0", "1/0/0x",
                    "99999999999/0/0"):
            status, _, body = self.get("/v1/models/%s/terrain/%s.terrain" % (PRISM, bad))
            self.assertEqual(status, 400, (bad, body[:300]))
            self.assertEqual(json.loads(body)["error"]["code"], "invalid_argument")
        status, _, _ = self.get("/v1/models/nope/terrain/layer.json")
        self.assertEqual(status, 404)

        # Before anything built PRISM's layer: concurrent first requests (the CPU pool's threads
        # build it once and wait for each other) all answer the same tile.
        key = tile_of(6, *FAR)
        results = [None] * 8

        def fetch(k):
            results[k] = self.daemon.request(
                "GET", "/v1/models/%s/terrain/%d/%d/%d.terrain" % ((PRISM,) + key),
                headers={"Accept": CESIUM_ACCEPT})
        threads = [threading.Thread(target=fetch, args=(k,)) for k in range(len(results))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120)
        self.assertEqual({r[0] for r in results}, {200}, [r[2][:200] for r in results])
        self.assertEqual(len({r[2] for r in results}), 1)
        self.assertEqual(len({r[1]["ETag"] for r in results}), 1)
        built = [line for line in self.daemon.log().splitlines()
                 if "model=%s terrain layer of version" % PRISM in line]
        self.assertEqual(len(built), 1, built)

        # A projected DEM is a height field too (vsm import takes it to ECEF through PROJ): its
        # tiles hold the geographic DEM's heights within the relief (the warp resampled it).
        utm_layer, _ = self.layer("jack_utm")
        self.assertGreaterEqual(utm_layer["maxzoom"], 11)
        self.assertEqual(utm_layer["metadataAvailability"], 1)
        key = tile_of(utm_layer["maxzoom"] - 1, *JACK_CENTRE)
        t, _, _ = self.tile(key, model="jack_utm")
        self.check_tile(t, key, utm_layer)
        self.check_against_dem(t, key, jack, normals=False)

        layer, _ = self.layer()
        levels_before = self.check_layer(layer, {PRISM: prism})
        self.assertGreaterEqual(layer["maxzoom"], 6)

        # Level 0 and a coarse level: tiles valid; outside the model flat at 0.
        for key in ((0, 0, 0), (0, 1, 0), tile_of(3, *FAR)):
            t, _, _ = self.tile(key)
            self.check_tile(t, key, layer)
        t, _, _ = self.tile((0, 1, 0))
        self.assertEqual((t["min"], t["max"]), (0.0, 0.0))
        t, _, _ = self.tile((5, 10, 5))  # the Pacific south of the equator
        self.assertEqual((t["min"], t["max"]), (0.0, 0.0))
        t, _, _ = self.tile((0, 0, 0))
        self.assertGreater(t["max"], 1000)

        # PRISM at the levels of its finest data: a 2 x 2 block of neighbours, against the DEM.
        etags_before = {}
        for z in (6, layer["maxzoom"]):
            _, x, y = tile_of(z, *FAR)
            block = {}
            for dx in (0, 1):
                for dy in (0, 1):
                    key = (z, x + dx, y + dy)
                    t, h, _ = self.tile(key)
                    self.check_tile(t, key, layer)
                    self.check_against_dem(t, key, prism)
                    block[key] = t
                    etags_before[key] = h["ETag"]
            self.check_neighbours(block[(z, x, y)], (z, x, y), block[(z, x + 1, y)], (z, x + 1, y))
            self.check_neighbours(block[(z, x, y)], (z, x, y), block[(z, x, y + 1)], (z, x, y + 1))
            self.check_neighbours(block[(z, x + 1, y)], (z, x + 1, y), block[(z, x + 1, y + 1)],
                                  (z, x + 1, y + 1))

        # Representations: without extensions, gzip; the same mesh in each.
        key = tile_of(layer["maxzoom"], *FAR)
        full, h_full, raw_full = self.tile(key)
        plain, h_plain, raw_plain = self.tile(key, accept=PLAIN_ACCEPT)
        self.assertEqual(plain["extensions"], {})
        self.check_tile(plain, key, normals=False)
        self.assertEqual(raw_full[:len(raw_plain)], raw_plain)
        zipped, h_zip, raw_zip = self.tile(key, gz=True)
        self.assertEqual(raw_zip, raw_full)
        self.assertNotEqual(h_zip["ETag"], h_full["ETag"])
        self.assertNotEqual(h_plain["ETag"], h_full["ETag"])
        # 304, also for the gzipped one, with the tag of its own representation.
        for gz, tag in ((False, h_full["ETag"]), (True, h_zip["ETag"])):
            headers = {"Accept": CESIUM_ACCEPT, "If-None-Match": tag}
            if gz:
                headers["Accept-Encoding"] = "gzip"
            status, h, body = self.get("/v1/models/%s/terrain/%d/%d/%d.terrain" % ((PRISM,) + key),
                                       headers)
            self.assertEqual(status, 304)
            self.assertEqual(body, b"")
            self.assertEqual(h["ETag"], tag)

        # Over Jacksboro before the merge: PRISM's data only.
        jack_keys = [tile_of(z, *JACK_CENTRE) for z in (7, 11)]
        for key in jack_keys:
            t, h, _ = self.tile(key)
            self.check_tile(t, key, layer)
            etags_before[key] = h["ETag"]
        far_key = tile_of(5, *FAR)
        _, h, _ = self.tile(far_key)
        etags_before[far_key] = h["ETag"]

        # The merge (a job).
        code, _, body = self.daemon.request(
            "POST", "/v1/jobs", body=json.dumps({"type": "merge", "target": PRISM, "source": JACK}),
            headers={**AUTH, "Content-Type": "application/json"})
        self.assertEqual(code, 202, body[:300])
        job = json.loads(body)
        deadline = time.monotonic() + 600
        while job["state"] in ("queued", "running"):
            self.assertLess(time.monotonic(), deadline, job)
            time.sleep(0.1)
            job = self.daemon.get_json("/v1/jobs/" + job["id"])[2]
        self.assertEqual(job["state"], "succeeded", job)

        layer_after, _ = self.layer()
        levels_after = self.check_layer(layer_after, {PRISM: prism, JACK: jack})
        self.assertGreater(layer_after["maxzoom"], layer["maxzoom"])
        for z, tiles in enumerate(levels_before):
            self.assertLessEqual(tiles, levels_after[z])
        # The new levels are where the merge added patches: around Jacksboro (the merge subdivides
        # the PRISM patches it meets, 64 PRISM samples wide, filling beyond Jacksboro from PRISM),
        # and every tile over Jacksboro's inside is available down to the deepest level.
        jw, js, je, jn = jack.bounds()
        margin = 64 * prism.gt[1]
        for z in range(layer["maxzoom"] + 1, layer_after["maxzoom"] + 1):
            for x, y in levels_after[z]:
                tw, ts, te, tn = tile_rect(z, x, y)
                self.assertTrue(tw <= je + margin and jw - margin <= te and ts <= jn + margin
                                and js - margin <= tn, (z, x, y))
            _, x0, y0 = tile_of(z, jw + 0.01, js + 0.01)
            _, x1, y1 = tile_of(z, je - 0.01, jn - 0.01)
            for x in range(x0, x1 + 1):
                for y in range(y0, y1 + 1):
                    self.assertIn((x, y), levels_after[z], (z, x, y))
            self.assertNotIn(tile_of(z, *FAR)[1:], levels_after[z])
        self.assertGreaterEqual(layer_after["maxzoom"], 12)  # 3 arc-seconds: ~70 m east-west

        # ETags: changed over Jacksboro, kept far from it.
        for key in jack_keys:
            _, h, _ = self.tile(key)
            self.assertNotEqual(h["ETag"], etags_before[key], key)
        for key in [k for k in etags_before if k[0] >= 5 and k not in jack_keys]:
            _, h, _ = self.tile(key)
            self.assertEqual(h["ETag"], etags_before[key], key)

        # Over Jacksboro at its finest levels: a 2 x 2 block, against Jacksboro's DEM.
        for z in (layer_after["maxzoom"] - 1, layer_after["maxzoom"]):
            _, x, y = tile_of(z, *JACK_CENTRE)
            block = {}
            for dx in (0, 1):
                for dy in (0, 1):
                    key = (z, x + dx, y + dy)
                    t, _, _ = self.tile(key, gz=(dx == 1))
                    self.check_tile(t, key, layer_after)
                    self.check_against_dem(t, key, jack)
                    block[key] = t
            self.check_neighbours(block[(z, x, y)], (z, x, y), block[(z, x + 1, y)], (z, x + 1, y))
            self.check_neighbours(block[(z, x, y)], (z, x, y), block[(z, x, y + 1)], (z, x, y + 1))
        self.assertGreater(Terrain.stats["normals"], 1000)
        self.assertGreater(Terrain.stats["heights"], 1000)

        # The revision before the merge still answers its own layer.
        status, _, body = self.get("/v1/models/%s/terrain/layer.json?rev=1" % PRISM)
        self.assertEqual(status, 200, body[:300])
        old = json.loads(body)
        self.assertEqual(old["available"], layer["available"])
        self.assertEqual(old["tiles"], ["{z}/{x}/{y}.terrain?v=1&rev=1"])


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--lib", required=True, help="the fault library (tests/fault)")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
