#!/usr/bin/python3
"""What changed (issue 16) on real data: PRISM imported by the real `vsm` at --patch-size 65 is
revision 1; `vsm merge` of Jacksboro into it makes revision 2; `vsm diff --from 1 --to 2` and the
real vsmd's /diff and /diff.png are checked against GDAL and numpy, never against the code under
test.

    /usr/bin/python3 diff_test.py --vsm <vsm> --vsmd <vsmd> --data <shared/data> --work <dir>

1. Outside Jacksboro's footprint nothing changed: every changed leaf whose box lies outside it
   (boxes from the JSON, turned to lon/lat by GDAL/PROJ) and every GeoTIFF pixel there has |d|
   below 1 mm or below what float32 storage of the patches can make (half an ulp of each local
   coordinate of the leaf and of revision 1's leaves around it, from their boxes: a 131 km fill
   leaf rounds to millimetres).
2. Inside it, at 200 random Jacksboro pixel centres, the GeoTIFF (read bilinearly at the pixel's
   lon/lat) matches the difference computed with GDAL/numpy: Jacksboro's pixel minus PRISM
   interpolated bilinearly there, lowered by the chord's sag of PRISM's 4 km cells in ECEF (the
   model interpolates in ECEF, which lies below the lon/lat interpolation by t(1-t)L^2/2R per
   direction, up to 0.7 m), times cos(PRISM's slope). The tolerance per point is what the
   interpolations can differ by: three piecewise-linear steps (the merge resamples Jacksboro at
   the model's own 66 m vertices, the map samples those cells at its ~75 m pixels, the test reads
   the map bilinearly), each erring by at most M h^2 / 8 (M the curvature, h about Jacksboro's
   pixel), and Jacksboro's second differences at its pixel spacing measure M h^2: so 3/8 of the
   largest second difference (rows, columns, diagonals) at the pixel and its 8 neighbours, plus
   5 cm (the sag's model, float32). A wrong sign or a missing surface errs by |d| (median 56 m).
3. The GeoTIFF is float32, one band, NaN no-data, EPSG:4326 (GDAL opens it so).
4. Over HTTP: /diff equals the CLI's JSON; /diff.png is a PNG of the requested size whose legend
   (text chunk vsm:range, header X-VSM-Diff-Range) is the JSON totals' max |d|; bad parameters are
   400, revisions not kept and unknown models 404.
"""

import argparse
import json
import math
import os
import shutil
import struct
import sys
import time
import unittest
import zlib

import numpy as np
from osgeo import gdal, osr

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import read_raster  # noqa: E402

gdal.UseExceptions()
ARGS = None
SIZE = 4096
POINTS = 200
WGS84_A = 6378137.0
WGS84_E2 = 0.00669437999014


def half_ulp_norm(box):
    """The largest error along a unit direction of float32 coordinates relative to the centre of
    `box` (what vsm stores: Local2Global is a translation to the box's centre)."""
    total = 0.0
    for i in range(3):
        m = (box["max"][i] - box["min"][i]) / 2
        if m > 0:
            total += (2.0 ** (math.floor(math.log2(m)) - 24)) ** 2
    return math.sqrt(total)


def boxes_meet(a, b):
    return all(a["min"][i] <= b["max"][i] and b["min"][i] <= a["max"][i] for i in range(3))


class LonLat:
    """ECEF (EPSG:4978) to lon/lat (EPSG:4326) by PROJ."""

    def __init__(self):
        ecef, geo = osr.SpatialReference(), osr.SpatialReference()
        ecef.ImportFromEPSG(4978)
        geo.ImportFromEPSG(4326)
        geo.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
        self.t = osr.CoordinateTransformation(ecef, geo)

    def extent(self, box, margin=0.01):
        """lon/lat rectangle of a box's 8 corners, grown by `margin` of its size."""
        pts = [self.t.TransformPoint(x, y, z) for x in (box["min"][0], box["max"][0])
               for y in (box["min"][1], box["max"][1]) for z in (box["min"][2], box["max"][2])]
        lon = [p[0] for p in pts]
        lat = [p[1] for p in pts]
        gx, gy = margin * (max(lon) - min(lon)), margin * (max(lat) - min(lat))
        return min(lon) - gx, max(lon) + gx, min(lat) - gy, max(lat) + gy


def bilinear(values, gt, lon, lat):
    """`values` (pixel-centre samples of geotransform gt) interpolated bilinearly at lon/lat."""
    fx = (lon - gt[0]) / gt[1] - 0.5
    fy = (lat - gt[3]) / gt[5] - 0.5
    x0, y0 = int(math.floor(fx)), int(math.floor(fy))
    tx, ty = fx - x0, fy - y0
    v = values[y0:y0 + 2, x0:x0 + 2]
    top = v[0, 0] * (1 - tx) + v[0, 1] * tx
    bottom = v[1, 0] * (1 - tx) + v[1, 1] * tx
    return top * (1 - ty) + bottom * ty, (x0, y0, tx, ty)


def png_info(data):
    """(width, height, {text keyword: value}) of a PNG file, checking every chunk's CRC."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n", data[:8]
    pos, text, size = 8, {}, None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        crc, = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        assert zlib.crc32(kind + body) == crc, kind
        if kind == b"IHDR":
            size = struct.unpack(">II", body[:8])
        elif kind == b"tEXt":
            key, _, value = body.partition(b"\0")
            text[key.decode("latin-1")] = value.decode("latin-1")
        elif kind == b"zTXt":
            key, _, rest = body.partition(b"\0")
            text[key.decode("latin-1")] = zlib.decompress(rest[1:]).decode("latin-1")
        elif kind == b"iTXt":
            key, _, rest = body.partition(b"\0")
            flag = rest[0]
            rest = rest[2:]
            _, _, rest = rest.partition(b"\0")
            _, _, rest = rest.partition(b"\0")
            text[key.decode("latin-1")] = (zlib.decompress(rest) if flag else rest).decode()
        pos += 12 + length
        if kind == b"IEND":
            break
    return size[0], size[1], text


class Diff(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        root = os.path.join(ARGS.work, "root")
        shutil.rmtree(root, ignore_errors=True)
        os.makedirs(root)
        cls.root = root
        cls.model = os.path.join(root, "prism")
        jack = os.path.join(ARGS.work, "jack")
        shutil.rmtree(jack, ignore_errors=True)
        harness.import_dem(os.path.join(ARGS.data, "PRISMelevation.tif"), cls.model, 65)
        harness.import_dem(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), jack, 65)
        harness.vsm("merge", cls.model, jack, check=True)
        out = os.path.join(ARGS.work, "out")
        os.makedirs(out, exist_ok=True)
        cls.json_path = os.path.join(out, "diff.json")
        cls.tif_path = os.path.join(out, "diff.tif")
        cls.png_path = os.path.join(out, "diff.png")
        start = time.monotonic()
        cls.stdout = harness.vsm("diff", cls.model, "--from", "1", "--to", "2",
                                 "--json", cls.json_path, "--geotiff", cls.tif_path,
                                 "--png", cls.png_path, "--size", SIZE, check=True).stdout
        cls.seconds = time.monotonic() - start
        print("\nvsm diff (%.2f s):\n%s" % (cls.seconds, cls.stdout), file=sys.stderr)
        with open(cls.json_path) as f:
            cls.diff = json.load(f)
        cls.jack, cls.jack_gt = read_raster(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"))
        cls.prism, cls.prism_gt = read_raster(os.path.join(ARGS.data, "PRISMelevation.tif"))
        cls.map, cls.map_gt = read_raster(cls.tif_path)
        gt, (h, w) = cls.jack_gt, cls.jack.shape
        # Jacksboro's footprint (its pixels' area), grown by one of its pixels and one map pixel:
        # cells of the merged model straddling its border interpolate between the two surfaces.
        gx = abs(gt[1]) + abs(cls.map_gt[1])
        gy = abs(gt[5]) + abs(cls.map_gt[5])
        cls.footprint = (gt[0] - gx, gt[0] + w * gt[1] + gx, gt[3] + h * gt[5] - gy, gt[3] + gy)
        cls.daemon = harness.Daemon(root=root)
        # Revision 1's leaves (boxes) over HTTP, for the float32 bounds.
        status, _, hierarchy = cls.daemon.get_json("/v1/models/prism/hierarchy?rev=1")
        assert status == 200, hierarchy
        cls.old_leaves = [node["box"] for node in harness.walk(hierarchy["root"]) if node["leaf"]]

    @classmethod
    def tearDownClass(cls):
        cls.daemon.stop()

    def outside(self, extent):
        x0, x1, y0, y1 = self.footprint
        return extent[1] < x0 or extent[0] > x1 or extent[3] < y0 or extent[2] > y1

    def storage_bound(self, box):
        """float32 rounding of a leaf of revision 2 and of revision 1's leaves meeting it."""
        old = max(half_ulp_norm(b) for b in self.old_leaves if boxes_meet(b, box))
        return half_ulp_norm(box) + old

    def test_1_nothing_changed_outside_jacksboro(self):
        lonlat = LonLat()
        leaves = [p for p in self.diff["patches"] if p["leaf"]]
        self.assertEqual(sum(p["removed"] for p in self.diff["patches"]), 0)
        outside = []
        for p in leaves:
            extent = lonlat.extent(p["box"])
            if self.outside(extent):
                outside.append((p, extent, max(1e-3, self.storage_bound(p["box"]))))
        self.assertGreater(len(outside), 10)
        self.assertLess(len(outside), len(leaves))
        worst = max(p["max_abs"] / bound for p, _, bound in outside)
        below_1mm = sum(p["max_abs"] < 1e-3 for p, _, _ in outside)
        print("outside Jacksboro: %d of %d changed leaves, %d with |d| < 1 mm, max |d| %.4f m, "
              "largest |d| / bound %.3f" % (len(outside), len(leaves), below_1mm,
                                            max(p["max_abs"] for p, _, _ in outside), worst),
              file=sys.stderr)
        for p, _, bound in outside:
            self.assertLessEqual(p["max_abs"], bound, p["key"])
            self.assertEqual(p["changed_area"], 0.0, p["key"])
        inside = [p for p in leaves if not self.outside(lonlat.extent(p["box"]))]
        self.assertGreater(max(p["max_abs"] for p in inside), 10.0)

        # The GeoTIFF: each pixel outside the footprint within the bound of the leaves over it.
        gt, (h, w) = self.map_gt, self.map.shape
        bound = np.full((h, w), 1e-3)
        for _, (lon0, lon1, lat0, lat1), b in outside:
            c0, c1 = int((lon0 - gt[0]) / gt[1]), int(math.ceil((lon1 - gt[0]) / gt[1]))
            r0, r1 = int((lat1 - gt[3]) / gt[5]), int(math.ceil((lat0 - gt[3]) / gt[5]))
            window = bound[max(r0, 0):max(r1, 0), max(c0, 0):max(c1, 0)]
            np.maximum(window, b, out=window)
        lon = gt[0] + (np.arange(w) + 0.5) * gt[1]
        lat = gt[3] + (np.arange(h) + 0.5) * gt[5]
        x0, x1, y0, y1 = self.footprint
        out_mask = ~(((lon > x0) & (lon < x1))[None, :] & ((lat > y0) & (lat < y1))[:, None])
        valid = np.isfinite(self.map) & out_mask
        values = np.abs(self.map[valid])
        print("GeoTIFF outside Jacksboro: %d pixels, %.1f %% below 1 mm, max |d| %.4f m" %
              (values.size, 100.0 * np.mean(values < 1e-3), values.max()), file=sys.stderr)
        self.assertGreater(values.size, 1000000)
        self.assertTrue(np.all(values <= bound[valid]))

    def test_2_inside_jacksboro_the_difference_of_the_rasters(self):
        rng = np.random.default_rng(16)
        jack, gt = self.jack, self.jack_gt
        h, w = jack.shape
        # Second differences along rows, columns and both diagonals, at every pixel.
        second = np.zeros_like(jack)
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            s = np.abs(np.roll(jack, (dy, dx), (0, 1)) - 2 * jack + np.roll(jack, (-dy, -dx), (0, 1)))
            second = np.maximum(second, s)
        errors, ratios, tols = [], [], []
        while len(errors) < POINTS:
            r, c = int(rng.integers(3, h - 3)), int(rng.integers(3, w - 3))
            window = jack[r - 2:r + 3, c - 2:c + 3]
            if not np.all(np.isfinite(window)):
                continue
            lon = gt[0] + (c + 0.5) * gt[1]
            lat = gt[3] + (r + 0.5) * gt[5]
            prism, (_, _, tx, ty) = bilinear(self.prism, self.prism_gt, lon, lat)
            # Metres per degree (WGS 84 radii of curvature) and PRISM's bilinear gradient.
            phi = math.radians(lat)
            n = WGS84_A / math.sqrt(1 - WGS84_E2 * math.sin(phi) ** 2)
            m = n * (1 - WGS84_E2) / (1 - WGS84_E2 * math.sin(phi) ** 2)
            lx = math.radians(abs(self.prism_gt[1])) * n * math.cos(phi)
            ly = math.radians(abs(self.prism_gt[5])) * m
            fx = (lon - self.prism_gt[0]) / self.prism_gt[1] - 0.5
            fy = (lat - self.prism_gt[3]) / self.prism_gt[5] - 0.5
            x0, y0 = int(math.floor(fx)), int(math.floor(fy))
            p = self.prism[y0:y0 + 2, x0:x0 + 2]
            gx = ((1 - ty) * (p[0, 1] - p[0, 0]) + ty * (p[1, 1] - p[1, 0])) / lx
            gy = ((1 - tx) * (p[1, 0] - p[0, 0]) + tx * (p[1, 1] - p[0, 1])) / ly
            cos_slope = 1 / math.sqrt(1 + gx * gx + gy * gy)
            # The model's PRISM cell is bilinear in ECEF: below the lon/lat interpolation by the
            # chords' sag (radius sqrt(m n)).
            sag = (tx * (1 - tx) * lx * lx + ty * (1 - ty) * ly * ly) / (2 * math.sqrt(m * n))
            expected = (jack[r, c] - (prism - sag)) * cos_slope
            got, _ = bilinear(self.map, self.map_gt, lon, lat)
            self.assertTrue(math.isfinite(got), (lon, lat))
            tol = 0.375 * second[r - 1:r + 2, c - 1:c + 2].max() + 0.05
            errors.append(abs(got - expected))
            ratios.append(abs(got - expected) / tol)
            tols.append(tol)
            self.assertLessEqual(abs(got - expected), tol,
                                 "at %.6f, %.6f: diff %.3f m, GDAL %.3f m (Jacksboro %.2f, PRISM "
                                 "%.2f, sag %.3f, cos %.4f)" % (lon, lat, got, expected,
                                                                jack[r, c], prism, sag, cos_slope))
        print("inside Jacksboro, %d points: max error %.3f m, median %.3f m, tolerance %.3f .. "
              "%.3f m (median %.3f), largest error / tolerance %.3f" %
              (POINTS, max(errors), float(np.median(errors)), min(tols), max(tols),
               float(np.median(tols)), max(ratios)), file=sys.stderr)

    def test_3_geotiff_is_wgs84_float32_with_nan_nodata(self):
        ds = gdal.Open(self.tif_path)
        self.assertEqual(ds.RasterCount, 1)
        band = ds.GetRasterBand(1)
        self.assertEqual(band.DataType, gdal.GDT_Float32)
        self.assertTrue(math.isnan(band.GetNoDataValue()))
        srs = ds.GetSpatialRef()
        srs.AutoIdentifyEPSG()
        self.assertEqual(srs.GetAuthorityCode(None), "4326")
        self.assertEqual(max(ds.RasterXSize, ds.RasterYSize), SIZE)
        # It covers Jacksboro.
        gt = ds.GetGeoTransform()
        x0, x1, y0, y1 = self.footprint
        self.assertLess(gt[0], x0)
        self.assertGreater(gt[0] + ds.RasterXSize * gt[1], x1)
        self.assertGreater(gt[3], y1)
        self.assertLess(gt[3] + ds.RasterYSize * gt[5], y0)

    def test_4_http(self):
        start = time.monotonic()
        # The diff along the normal takes seconds on this model (2.4 s of CPU, the CLI's 18 s on a
        # loaded machine): a wait for the answer, not a verdict on its speed.
        status, _, body = self.daemon.get_json("/v1/models/prism/diff?from=1&to=2", timeout=300)
        seconds = time.monotonic() - start
        self.assertEqual(status, 200, body)
        # The CLI's, less its map's georeference (the route draws none).
        self.assertEqual(body, {k: v for k, v in self.diff.items() if k != "map"})
        totals = body["totals"]
        self.assertEqual(totals["max_abs"], max(abs(totals["min"]), abs(totals["max"])))

        start = time.monotonic()
        status, headers, png = self.daemon.request(
            "GET", "/v1/models/prism/diff.png?from=1&to=2&size=700", timeout=300)
        png_seconds = time.monotonic() - start
        self.assertEqual(status, 200, png[:300])
        self.assertEqual(headers["Content-Type"], "image/png")
        width, height, text = png_info(png)
        self.assertEqual(max(width, height), 700)
        self.assertAlmostEqual(float(text["vsm:range"]), totals["max_abs"], delta=1e-6)
        self.assertAlmostEqual(float(headers["X-VSM-Diff-Range"]), totals["max_abs"], delta=1e-6)
        self.assertIn("%.6g" % totals["max_abs"], text["Description"])
        print("HTTP: /diff %.2f s, /diff.png (700) %.2f s, %d x %d, %d bytes, legend '%s'" %
              (seconds, png_seconds, width, height, len(png), text["Description"]),
              file=sys.stderr)

        for query, code in (("", 400), ("?from=1", 400), ("?to=2", 400), ("?from=0&to=2", 400),
                            ("?from=x&to=2", 400), ("?from=1&to=99", 404)):
            status, _, answer = self.daemon.request("GET", "/v1/models/prism/diff" + query)
            self.assertEqual(status, code, (query, answer[:200]))
            self.assertIn(b'"error"', answer)
        for size in ("0", "4097", "x"):
            status, _, _ = self.daemon.request(
                "GET", "/v1/models/prism/diff.png?from=1&to=2&size=" + size)
            self.assertEqual(status, 400, size)
        status, _, _ = self.daemon.request("GET", "/v1/models/nothing/diff?from=1&to=2")
        self.assertEqual(status, 404)


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
