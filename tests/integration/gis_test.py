"""Heights for GIS clients end to end (issue 29): the real vsmd on 127.0.0.1:0 (harness.py) over
Jacksboro and PRISM imported by the real `vsm`, checked against the source rasters read by GDAL's
Python bindings (never vsm's sampler), and the real GDAL utilities as the OGC API client:

- point queries (Open Topo Data's form, GET and POST, GeoJSON bodies) at DEM pixel centres equal
  the raster's values (within the float32 rounding of the stored positions, 1 mm);
- `vsm export` and /coverage at the DEM's own grid equal the raster at every pixel (1 mm), as a
  float32 COG (tiled 256, DEFLATE, NaN no-data);
- `gdalinfo` and `gdal_translate OGCAPI:http://.../ogcapi/collections/jack` read the coverage;
- a profile across Jacksboro merged into PRISM (a merge job) follows the detail, and `?rev=1`
  still answers PRISM's;
- terrain-RGB tiles (MapLibre's raster-dem, Terrarium and Mapbox) hold the raster's heights at
  their pixel centres, and after a merge exactly the tiles over the merged area change their
  ETags and bytes; the others answer 304 to their old tags;
- bad input gets a 400 naming the problem.

    /usr/bin/python3 gis_test.py --vsm <vsm> --vsmd <vsmd> --data <shared/data> --work <dir>
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import unittest
import urllib.parse

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402

gdal.UseExceptions()

ARGS = None
TOKEN = "gis-test-token"
JACK = "jacksboro_fault_dem"
PRISM = "PRISMelevation"
# The float32 rounding of the stored positions (patch-relative, a few km): measured 0.18 mm on
# Jacksboro.
EXACT = 1e-3


class Dem:
    """A source raster as GDAL reads it: heights (row 0 north), geotransform, pixel centres."""

    def __init__(self, path):
        self.heights, self.t = harness.read_raster(path)
        self.rows, self.cols = self.heights.shape

    def centre(self, row, col):
        """(lat, lon) of a pixel's centre."""
        return self.t[3] + (row + 0.5) * self.t[5], self.t[0] + (col + 0.5) * self.t[1]

    def bounds(self):
        """west, south, east, north of the pixel edges."""
        return (self.t[0], self.t[3] + self.rows * self.t[5], self.t[0] + self.cols * self.t[1],
                self.t[3])

    def bilinear(self, lat, lon):
        """(height, relief): bilinear between the four pixel centres around the point, and the
        range of the 4 x 4 pixels around it (a merge resamples the detail onto the target's
        subdivided grid, whose cells straddle the detail's: the surface stays within the relief
        of the detail's neighbouring cells)."""
        x = (lon - self.t[0]) / self.t[1] - 0.5
        y = (lat - self.t[3]) / self.t[5] - 0.5
        c, r = int(np.floor(x)), int(np.floor(y))
        if c < 1 or r < 1 or c + 2 >= self.cols or r + 2 >= self.rows:
            return None, None
        q = self.heights[r:r + 2, c:c + 2]
        fx, fy = x - c, y - r
        h = (q[0, 0] * (1 - fx) * (1 - fy) + q[0, 1] * fx * (1 - fy) + q[1, 0] * (1 - fx) * fy
             + q[1, 1] * fx * fy)
        around = self.heights[r - 1:r + 3, c - 1:c + 3]
        return h, float(np.nanmax(around) - np.nanmin(around))


class GisTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        root = os.path.join(ARGS.work, "root")
        shutil.rmtree(ARGS.work, ignore_errors=True)
        os.makedirs(root)
        harness.import_dem(os.path.join(ARGS.data, JACK + ".tif"), os.path.join(root, "jack"), 65,
                           "--texture", "none")
        harness.import_dem(os.path.join(ARGS.data, PRISM + ".tif"), os.path.join(root, "prism"),
                           65, "--texture", "none")
        # A second PRISM for the terrain-RGB tiles' tags across a merge of its own.
        shutil.copytree(os.path.join(root, "prism"), os.path.join(root, "prism_rgb"))
        cls.jack = Dem(os.path.join(ARGS.data, JACK + ".tif"))
        cls.daemon = harness.Daemon("--token", TOKEN, "--set", "threads.cpu=2", root=root)

    @classmethod
    def tearDownClass(cls):
        code = cls.daemon.stop()
        cls.daemon.cleanup(keep=code != 0)

    def get(self, path):
        status, _, body = self.daemon.request("GET", path)
        return status, body

    def get_json(self, path):
        status, body = self.get(path)
        return status, json.loads(body)

    def elevations(self, model, points, rev=None):
        """Open Topo Data's GET, in requests of at most 400 points (a request line stays within
        vsmd's 16 KiB header bound; larger sets go by POST)."""
        out = []
        for i in range(0, len(points), 400):
            locations = "|".join("%r,%r" % p for p in points[i:i + 400])
            path = "/v1/models/%s/elevation?locations=%s" % (model, locations)
            if rev is not None:
                path += "&rev=%d" % rev
            status, body = self.get_json(path)
            self.assertEqual(status, 200, body)
            self.assertEqual(body["status"], "OK")
            out += body["results"]
        return out

    def test_points_at_pixel_centres_equal_the_raster(self):
        rng = np.random.default_rng(29)
        cells = [(0, 0), (0, self.jack.cols - 1), (self.jack.rows - 1, 0),
                 (self.jack.rows - 1, self.jack.cols - 1)]
        cells += [(int(r), int(c)) for r, c in zip(rng.integers(0, self.jack.rows, 1500),
                                                   rng.integers(0, self.jack.cols, 1500))]
        points = [self.jack.centre(r, c) for r, c in cells]
        results = self.elevations("jack", points)
        self.assertEqual(len(results), len(points))
        worst = 0.0
        for (r, c), (lat, lon), result in zip(cells, points, results):
            self.assertEqual(result["location"], {"lat": lat, "lng": lon})
            self.assertIsNotNone(result["elevation"], "pixel (%d, %d) answered null" % (r, c))
            worst = max(worst, abs(result["elevation"] - self.jack.heights[r, c]))
            self.assertEqual(result["dataset"], "jack")
            self.assertGreater(result["resolution"], 0)
        print("points: %d pixel centres, max |vsm - GDAL| %.6f m" % (len(points), worst))
        self.assertLessEqual(worst, EXACT)

        # POST: a GeoJSON MultiPoint (lon, lat) of 1000 points and Open Topo Data's JSON form
        # answer the same.
        some = points[:1000]
        body = json.dumps({"type": "MultiPoint", "coordinates": [[lon, lat] for lat, lon in some]})
        status, _, answer = self.daemon.request("POST", "/v1/models/jack/elevation", body=body,
                                                headers={"Content-Type": "application/json",
                                                         "Authorization": "Bearer " + TOKEN})
        self.assertEqual(status, 200, answer)
        posted = [r["elevation"] for r in json.loads(answer)["results"]]
        self.assertEqual(posted, [r["elevation"] for r in results[:1000]])
        body = json.dumps({"locations": "|".join("%r,%r" % p for p in some[:3])})
        status, _, answer = self.daemon.request("POST", "/v1/models/jack/elevation", body=body,
                                                headers={"Authorization": "Bearer " + TOKEN})
        self.assertEqual(status, 200, answer)
        self.assertEqual([r["elevation"] for r in json.loads(answer)["results"]], posted[:3])

    def test_open_topo_data_shape_samples_and_outside(self):
        lat0, lon0 = self.jack.centre(10, 10)
        lat1, lon1 = self.jack.centre(300, 390)
        status, body = self.get_json("/v1/models/jack/elevation?locations=%r,%r|%r,%r&samples=7"
                                     % (lat0, lon0, lat1, lon1))
        self.assertEqual(status, 200, body)
        self.assertEqual(len(body["results"]), 7)
        self.assertEqual(body["results"][0]["location"], {"lat": lat0, "lng": lon0})
        self.assertEqual(body["results"][-1]["location"], {"lat": lat1, "lng": lon1})
        self.assertIn("ellipsoid", body["height_reference"])
        # Outside the model: null, as Open Topo Data answers outside its datasets.
        status, body = self.get_json("/v1/models/jack/elevation?locations=10,10")
        self.assertEqual(status, 200, body)
        self.assertIsNone(body["results"][0]["elevation"])

    def test_bad_input_gets_a_clear_400(self):
        w, s, e, n = self.jack.bounds()
        cases = {
            "elevation?locations=95,10": "outside the world",
            "elevation?locations=10,190": "outside the world",
            "elevation?locations=" + "|".join(["36.3,-84.2"] * 1001): "more than 1000",
            "elevation?locations=36.3": "lat,lon",
            "elevation?locations=36.3,-84.2&samples=0": "samples",
            "elevation": "locations",
            "profile?line=36.3,-84.2": "two points",
            "profile?line=36.3,-84.2|36.3,-84.1&samples=100000": "samples",
            "coverage?bbox=%r,%r,%r,%r&width=10&height=10" % (e, s, w, n): "inverted",
            "coverage?bbox=%r,%r,%r,%r&width=5000&height=5000" % (w, s, e, n): "per request",
            "coverage?bbox=%r,%r,%r,%r&crs=EPSG:32616" % (w, s, e, n): "unknown",
            "coverage?bbox=-200,0,10,10&width=4&height=4": "outside the world",
        }
        for query, words in cases.items():
            status, body = self.get_json("/v1/models/jack/" + query)
            self.assertEqual(status, 400, "%s: %r" % (query[:80], body))
            self.assertIn(words, body["error"]["message"], query[:80])
        status, body = self.get_json("/v1/models/nosuch/elevation?locations=1,1")
        self.assertEqual(status, 404, body)

    def check_cog(self, path):
        info = gdal.Info(path, format="json")
        self.assertEqual(info["metadata"]["IMAGE_STRUCTURE"].get("LAYOUT"), "COG")
        self.assertEqual(info["metadata"]["IMAGE_STRUCTURE"].get("COMPRESSION"), "DEFLATE")
        band = info["bands"][0]
        self.assertEqual(band["type"], "Float32")
        self.assertEqual(band["block"], [256, 256])
        self.assertEqual(band["noDataValue"], "NaN")

    def assert_equals_jack(self, path, tolerance, what):
        dataset = gdal.Open(path)
        self.assertEqual((dataset.RasterXSize, dataset.RasterYSize),
                         (self.jack.cols, self.jack.rows))
        t = dataset.GetGeoTransform()
        for a, b in zip(t, self.jack.t):
            self.assertAlmostEqual(a, b, delta=1e-9 + abs(b) * 1e-7)
        values = harness.band_heights(dataset.GetRasterBand(1))
        self.assertEqual(int(np.isnan(values).sum()), 0, what + ": pixels without a height")
        worst = float(np.max(np.abs(values - self.jack.heights)))
        print("%s: %d pixels, max |vsm - source| %.6f m" % (what, values.size, worst))
        self.assertLessEqual(worst, tolerance, what)

    def test_export_at_the_dem_grid_equals_the_raster(self):
        out = os.path.join(ARGS.work, "jack-export.tif")
        w, s, e, n = self.jack.bounds()
        harness.vsm("export", os.path.join(self.daemon.dir, "jack"), out, "--bounds",
                    "%r,%r,%r,%r" % (w, s, e, n), "--resolution", repr(self.jack.t[1]),
                    check=True)
        self.check_cog(out)
        self.assert_equals_jack(out, EXACT, "vsm export")
        bad = harness.vsm("export", os.path.join(self.daemon.dir, "jack"), out, "--crs",
                          "EPSG:32616")
        self.assertEqual(bad.returncode, 2, bad.stderr)

    def test_coverage_at_the_dem_grid_equals_the_raster(self):
        w, s, e, n = self.jack.bounds()
        status, body = self.get("/v1/models/jack/coverage?bbox=%r,%r,%r,%r&width=%d&height=%d"
                                % (w, s, e, n, self.jack.cols, self.jack.rows))
        self.assertEqual(status, 200, body[:300])
        out = os.path.join(ARGS.work, "jack-coverage.tif")
        with open(out, "wb") as f:
            f.write(body)
        self.check_cog(out)
        self.assert_equals_jack(out, EXACT, "/coverage")

    def test_gdal_ogcapi_driver_reads_the_coverage(self):
        env = dict(os.environ, GDAL_DEFAULT_WMS_CACHE_PATH=os.path.join(ARGS.work, "wmscache"))
        url = "OGCAPI:%s/ogcapi/collections/jack" % self.daemon.base
        info = subprocess.run(["gdalinfo", url], capture_output=True, text=True, env=env,
                              timeout=120)
        self.assertEqual(info.returncode, 0, info.stderr)
        self.assertIn("Size is %d, %d" % (self.jack.cols, self.jack.rows), info.stdout)
        self.assertIn('ID["EPSG",4326]', info.stdout)
        out = os.path.join(ARGS.work, "jack-ogcapi.tif")
        translate = subprocess.run(["gdal_translate", "-q", url, out], capture_output=True,
                                   text=True, env=env, timeout=120)
        self.assertEqual(translate.returncode, 0, translate.stderr)
        # The collection's grid is the leaves' own spacing and the model's bounds, both measured
        # from the float32 positions (spacing across a whole leaf): its pixel centres sit a few
        # 1e-9 degrees off the raster's, so the heights agree within 2 mm (1.16 mm measured; 2.5
        # mm when the spacing came from one cell) rather than to float32 rounding.
        self.assert_equals_jack(out, 0.002, "gdal_translate OGCAPI:")
        # The collections list it, and the coverage link names the model version (GDAL caches
        # blocks by URL for days).
        status, body = self.get_json("/ogcapi/collections")
        self.assertEqual(status, 200, body)
        ids = [c["id"] for c in body["collections"]]
        self.assertIn("jack", ids)
        status, body = self.get_json("/ogcapi/collections/jack")
        coverage = [l for l in body["links"]
                    if l["rel"] == "http://www.opengis.net/def/rel/ogc/1.0/coverage"]
        self.assertEqual(coverage[0]["type"], "image/tiff; application=geotiff")
        self.assertIn("?v=%d" % body["model_version"], coverage[0]["href"])
        for path in ("/ogcapi", "/ogcapi/conformance"):
            status, body = self.get_json(path)
            self.assertEqual(status, 200, body)

    def test_profile_follows_a_merged_detail(self):
        # Across Jacksboro, west to east through its middle (away from its border).
        lat = self.jack.centre(self.jack.rows // 2, 0)[0] + self.jack.t[5] * 0.37
        west, east = self.jack.t[0] + 20 * self.jack.t[1], self.jack.t[0] + 380 * self.jack.t[1]
        line = urllib.parse.quote("%r,%r|%r,%r" % (lat, west, lat, east))
        status, before = self.get_json("/v1/models/prism/profile?line=%s&samples=500" % line)
        self.assertEqual(status, 200, before)
        job = self.daemon.submit({"type": "merge", "target": "prism", "source": "jack"})
        job = self.daemon.wait_job(job["id"])
        self.assertEqual(job["state"], "succeeded", job)
        status, after = self.get_json("/v1/models/prism/profile?line=%s&samples=500" % line)
        self.assertEqual(status, 200, after)
        self.assertEqual(len(after["results"]), 500)
        self.assertLess(after["finest_resolution"], before["finest_resolution"])
        off_before, off_after, excess = 0.0, 0.0, -1e9
        for b, a in zip(before["results"], after["results"]):
            h, relief = self.jack.bilinear(a["location"]["lat"], a["location"]["lng"])
            self.assertIsNotNone(a["elevation"])
            # The merged surface interpolates the detail's samples: within the relief of the
            # four pixels around the point.
            excess = max(excess, abs(a["elevation"] - h) - relief)
            off_after = max(off_after, abs(a["elevation"] - h))
            off_before = max(off_before, abs(b["elevation"] - h))
            self.assertGreater(a["depth"], b["depth"])
        print("profile: 500 samples; max |vsm - Jacksboro| %.2f m after the merge, %.2f m before"
              % (off_after, off_before))
        self.assertLessEqual(excess, EXACT)
        self.assertGreater(off_before, 10 * off_after)
        # The distances run from 0 to the length.
        self.assertEqual(after["results"][0]["distance"], 0)
        self.assertAlmostEqual(after["results"][-1]["distance"], after["length"], places=6)
        # The revision before the merge still answers PRISM's heights.
        status, old = self.get_json("/v1/models/prism/profile?line=%s&samples=500&rev=1" % line)
        self.assertEqual(status, 200, old)
        self.assertEqual([r["elevation"] for r in old["results"]],
                         [r["elevation"] for r in before["results"]])

    def test_orthometric_heights_subtract_the_egm96_geoid(self):
        """?height=orthometric: the heights above the ellipsoid less the EGM96 undulation, read
        here from PROJ's grid with GDAL and interpolated between its posts by this test."""
        grid_path = "/usr/share/proj/egm96_15.gtx"
        grid = gdal.Open(grid_path)
        n = grid.ReadAsArray().astype(float)
        t = grid.GetGeoTransform()

        def undulation(lat, lon):
            x = ((lon - (t[0] + t[1] / 2)) / t[1]) % n.shape[1]
            y = (lat - (t[3] + t[5] / 2)) / t[5]
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            fx, fy = x - x0, y - y0
            x1 = (x0 + 1) % n.shape[1]
            return ((1 - fy) * ((1 - fx) * n[y0, x0] + fx * n[y0, x1])
                    + fy * ((1 - fx) * n[y0 + 1, x0] + fx * n[y0 + 1, x1]))

        points = [self.jack.centre(r, c) for r, c in ((5, 5), (100, 200), (300, 17))]
        locations = "|".join("%r,%r" % p for p in points)
        status, ell = self.get_json("/v1/models/jack/elevation?locations=" + locations)
        self.assertEqual(status, 200, ell)
        status, orth = self.get_json("/v1/models/jack/elevation?height=orthometric&locations="
                                     + locations)
        self.assertEqual(status, 200, orth)
        self.assertIn("EGM96", orth["height_reference"])
        self.assertIn("ellipsoid", ell["height_reference"])
        for (lat, lon), e, o in zip(points, ell["results"], orth["results"]):
            # EGM96 over Tennessee: about -30 m (the geoid below the ellipsoid).
            self.assertAlmostEqual(o["elevation"], e["elevation"] - undulation(lat, lon), places=3)
            self.assertLess(undulation(lat, lon), -20)
        line = urllib.parse.quote("%r,%r|%r,%r" % (points[0] + points[1]))
        status, profile = self.get_json("/v1/models/jack/profile?samples=5&height=orthometric"
                                        "&line=" + line)
        self.assertEqual(status, 200, profile)
        self.assertIn("EGM96", profile["height_reference"])
        status, body = self.get("/v1/models/jack/elevation?height=geoid&locations=36.3,-84.2")
        self.assertEqual(status, 400)
        self.assertIn("orthometric", body.decode())

    # ---- terrain-RGB --------------------------------------------------------------------------

    def test_terrain_rgb_tiles_hold_the_raster_heights_at_their_pixel_centres(self):
        import math
        status, tj = self.get_json("/v1/models/jack/terrain-rgb/tiles.json")
        self.assertEqual(status, 200, tj)
        self.assertEqual((tj["scheme"], tj["tileSize"], tj["encoding"], tj["minzoom"]),
                         ("xyz", 256, "terrarium", 0))
        w, s, e, n = self.jack.bounds()
        for got, want in zip(tj["bounds"], (w, s, e, n)):
            self.assertAlmostEqual(got, want, delta=1e-3)
        # The first level whose pixels are as fine as Jacksboro's 90 m at its southern edge.
        self.assertGreaterEqual(tj["maxzoom"], 11)
        self.assertLessEqual(tj["maxzoom"], 12)
        z = 12
        lat0, lon0 = self.jack.centre(self.jack.rows // 2, self.jack.cols // 2)
        x, y = slippy_tile(lon0, lat0, z)
        template = tj["tiles"][0]
        self.assertTrue(template.startswith("/v1/models/jack/terrain-rgb/{z}/{x}/{y}.png?v="))
        tiles = {}
        for encoding in ("terrarium", "mapbox"):
            path = template.replace("{z}/{x}/{y}", "%d/%d/%d" % (z, x, y))
            if encoding == "mapbox":
                path += "&encoding=mapbox"
            status, headers, body = self.daemon.request("GET", path)
            self.assertEqual(status, 200, body[:200])
            self.assertEqual(headers["content-type"], "image/png")
            tiles[encoding] = decode_dem_png(body, encoding)
            self.assertEqual(tiles[encoding].shape, (256, 256))
        west, south, east, north = slippy_rect(x, y, z)
        worst = 0.0
        for j in range(0, 256, 5):
            for i in range(0, 256, 5):
                lon = west + (i + 0.5) / 256 * (east - west)
                # Pixel rows are even in Mercator y, not in latitude.
                merc_n = math.asinh(math.tan(math.radians(north)))
                merc_s = math.asinh(math.tan(math.radians(south)))
                lat = math.degrees(math.atan(math.sinh(merc_n - (j + 0.5) / 256
                                                       * (merc_n - merc_s))))
                h, relief = self.jack.bilinear(lat, lon)
                got = tiles["terrarium"][j, i]
                # The surface interpolates the DEM's samples: within the relief of the four
                # pixels around the point (and the encoding's 1/256 m).
                worst = max(worst, abs(got - h) - relief)
                self.assertLessEqual(abs(tiles["mapbox"][j, i] - got), 0.05 + 1 / 256)
        print("terrain-rgb 12/%d/%d: worst excess over the local relief %.4f m" % (x, y, worst))
        self.assertLessEqual(worst, 1 / 256 + EXACT)

    def test_terrain_rgb_tags_change_only_over_a_merge(self):
        z = 8
        w, s, e, n = self.jack.bounds()
        x0, y0 = slippy_tile(w, n, z)
        x1, y1 = slippy_tile(e, s, z)
        status, tj = self.get_json("/v1/models/prism_rgb/terrain-rgb/tiles.json")
        self.assertEqual(status, 200, tj)

        def fetch(version):
            out = {}
            for x in range(x0 - 5, x1 + 6):
                for y in range(y0 - 5, y1 + 6):
                    path = "/v1/models/prism_rgb/terrain-rgb/%d/%d/%d.png?v=%d" % (z, x, y, version)
                    status, headers, body = self.daemon.request("GET", path)
                    if status == 404:  # beyond PRISM
                        continue
                    self.assertEqual(status, 200, body[:200])
                    out[(x, y)] = (headers["etag"], body)
            return out

        before = fetch(tj["model_version"])
        job = self.daemon.submit({"type": "merge", "target": "prism_rgb", "source": "jack"})
        job = self.daemon.wait_job(job["id"])
        self.assertEqual(job["state"], "succeeded", job)
        status, tj2 = self.get_json("/v1/models/prism_rgb/terrain-rgb/tiles.json")
        self.assertGreater(tj2["model_version"], tj["model_version"])
        self.assertGreater(tj2["maxzoom"], tj["maxzoom"])  # Jacksboro's 90 m beside PRISM's 4 km
        after = fetch(tj2["model_version"])
        self.assertEqual(set(before), set(after))
        over, changed, far = 0, 0, 0
        for key, (etag, body) in after.items():
            old_etag, old_body = before[key]
            # A tag names its bytes: the same tag, the same tile; different bytes, another tag.
            self.assertEqual(etag == old_etag, body == old_body, key)
            changed += etag != old_etag
            tw, ts, te, tn = slippy_rect(key[0], key[1], z)
            if tw <= e and w <= te and ts <= n and s <= tn:
                over += 1
                self.assertNotEqual(etag, old_etag, "tile %r over Jacksboro kept its tag" % (key,))
            # PRISM's leaves are 64 pixels of 0.042 deg (2.7 deg): a tile more than two leaves
            # away from Jacksboro is sampled from none that the merge rewrote.
            if te < w - 5.4 or tw > e + 5.4 or tn < s - 5.4 or ts > n + 5.4:
                far += 1
                self.assertEqual(etag, old_etag, "tile %r far from Jacksboro changed" % (key,))
                path = "/v1/models/prism_rgb/terrain-rgb/%d/%d/%d.png" % (z, key[0], key[1])
                status, _, _ = self.daemon.request("GET", path, headers={"If-None-Match": etag})
                self.assertEqual(status, 304)
        # The revision before the merge still answers the tiles as they were.
        for key, (etag, body) in after.items():
            if etag != before[key][0]:
                path = "/v1/models/prism_rgb/terrain-rgb/%d/%d/%d.png?rev=%d" % (
                    z, key[0], key[1], tj["model_version"])
                status, headers, old_body = self.daemon.request("GET", path)
                self.assertEqual(status, 200, old_body[:200])
                self.assertEqual(old_body, before[key][1], key)
                self.assertEqual(headers["etag"], before[key][0], key)
        print("terrain-rgb level %d: %d tiles, %d over Jacksboro, %d changed, %d far ones kept"
              % (z, len(after), over, changed, far))
        self.assertGreater(over, 0)
        self.assertGreater(far, 0)
        self.assertLess(changed, len(after))

    def test_terrain_rgb_bad_input_gets_a_clear_answer(self):
        for path, status, words in [
                ("/v1/models/jack/terrain-rgb/25/0/0.png", 400, "deepest level"),
                ("/v1/models/jack/terrain-rgb/3/8/0.png", 400, "outside the Web Mercator"),
                ("/v1/models/jack/terrain-rgb/3/x/0.png", 400, "non-negative integer"),
                ("/v1/models/jack/terrain-rgb/3/2/3.png?encoding=png", 400, "terrarium"),
                ("/v1/models/jack/terrain-rgb/3/2/3.png?nodata=99999", 400, "nodata"),
                ("/v1/models/jack/terrain-rgb/tiles.json?nodata=abc", 400, "nodata"),
                ("/v1/models/jack/terrain-rgb/3/0/0.png", 404, "does not meet"),
                ("/v1/models/nothing/terrain-rgb/tiles.json", 404, "nothing")]:
            got, body = self.get(path)
            self.assertEqual(got, status, (path, body))
            self.assertIn(words, body.decode() if isinstance(body, bytes) else body, path)


def slippy_tile(lon, lat, z):
    """(x, y) of the Web Mercator tile holding a point (the OpenStreetMap wiki's formulas)."""
    import math
    n = 2 ** z
    return (int((lon + 180) / 360 * n),
            int((1 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2 * n))


def slippy_rect(x, y, z):
    """west, south, east, north of a tile."""
    import math
    n = 2 ** z

    def lat(row):
        return math.degrees(math.atan(math.sinh(math.pi * (1 - 2 * row / n))))

    return x / n * 360 - 180, lat(y + 1), (x + 1) / n * 360 - 180, lat(y)


def decode_dem_png(body, encoding):
    """Heights of a terrain-RGB PNG, read with GDAL (rows north first)."""
    path = "/vsimem/dem-tile.png"
    gdal.FileFromMemBuffer(path, body)
    try:
        rgb = gdal.Open(path).ReadAsArray().astype(float)
    finally:
        gdal.Unlink(path)
    n = rgb[0] * 65536 + rgb[1] * 256 + rgb[2]
    return n / 256 - 32768 if encoding == "terrarium" else n / 10 - 10000


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    harness.run_tests(rest)


if __name__ == "__main__":
    main()
