#!/usr/bin/python3
"""CesiumJS terrain from vsmd (issue 14): headless Chromium (browser_check.js, as viewer.browser)
loads client-examples/web/terrain.html, which streams the merged model (PRISM with Jacksboro, the
`tiles.model` fixture) from the real vsmd on 127.0.0.1:0 through CesiumJS's own
CesiumTerrainProvider (GET /v1/models/merged/terrain/layer.json and its quantized-mesh tiles,
with vertex normals and metadata), with the NASA image (converted to PNG by GDAL, served beside
the viewer) draped over it as a SingleTileImageryProvider:

- the whole model: no terrain or imagery tile error, no console error, no failed request, nothing
  off 127.0.0.1, terrain tiles fetched;
- sampleTerrainMostDetailed at 100 PRISM pixel centres (outside the merged area) and 100
  Jacksboro pixel centres against GDAL's value of the source raster there: every height within
  the pixel's own relief (the largest difference to its 8 neighbours, at least 1 m; the terrain's
  vertices need not sit on pixel centres), and the median error under a tenth of the typical
  relief between neighbours;
- a close view of the Jacksboro area, lit by the sun, kept as a screenshot (terrain-jacksboro.png)
  with the same view over the flat ellipsoid (terrain-jacksboro-flat.png): the terrain's shading
  varies several times more than the flat globe's over the same pixels.

Run by ctest:
    terrain_browser_test.py --vsmd build/server/vsmd --model build/.../tiles/merged
        --data ../shared/data --viewer build/viewer --web-tools build/web-tools
        --screenshots build/.../screenshots"""

import argparse
import os
import shutil
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import browser_support  # noqa: E402
import harness  # noqa: E402
from browser_support import assert_not_blank, load_page, pixel_centres  # noqa: E402
from harness import Daemon  # noqa: E402

ARGS = None
MODEL = "merged"
PAGE_SECONDS = 90
SAMPLES = 100
# Jacksboro's close view: from the south-west of its centre, 14 km up, looking north-east and down,
# at 8:00 local summer time (the sun low in the east-north-east, so slopes shade strongly).
JACKSBORO_VIEW = "-84.30,36.18,14000,35,-40"
JACKSBORO_TIME = "2026-06-21T12:00:00Z"


def bounds(heights, transform, margin_pixels=0):
    rows, cols = heights.shape
    w = transform[0] - margin_pixels * transform[1]
    n = transform[3] - margin_pixels * transform[5]
    return (w, n + (rows + 2 * margin_pixels) * transform[5],
            w + (cols + 2 * margin_pixels) * transform[1], n)


class Terrain(unittest.TestCase):
    daemon = None

    @classmethod
    def setUpClass(cls):
        from osgeo import gdal
        gdal.UseExceptions()

        def prepare(root):
            shutil.copytree(ARGS.model, os.path.join(root, MODEL))

        os.makedirs(ARGS.screenshots, exist_ok=True)
        # The viewer as built, with the NASA image as a PNG beside it (browsers read no TIFF).
        cls.site = tempfile.mkdtemp(prefix="vsm-terrain-site-")
        shutil.copytree(ARGS.viewer, cls.site, dirs_exist_ok=True)
        image = os.path.join(ARGS.data, "conus_visible_earth.tif")
        gdal.Translate(os.path.join(cls.site, "conus.png"), image, format="PNG")
        t = gdal.Open(image).GetGeoTransform()
        size = gdal.Open(image)
        cls.image_rect = "%r,%r,%r,%r" % (t[0], t[3] + size.RasterYSize * t[5],
                                          t[0] + size.RasterXSize * t[1], t[3])
        cls.daemon = Daemon("--set", "threads.cpu=2", "--viewer-dir", cls.site,
                            "--log-level", "warn", prepare=prepare)
        cls.base_url = cls.daemon.base

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is not None:
            code = cls.daemon.stop()
            cls.daemon.cleanup(keep=code != 0)
        shutil.rmtree(cls.site, ignore_errors=True)

    def page(self, query, name, steps=None):
        report, pixels = load_page(self, self.base_url, "/viewer/terrain.html?" + query,
                                   "vsmTerrain", name, PAGE_SECONDS, steps)
        state = report["state"]
        self.assertIsNone(state["error"], state["error"])
        self.assertTrue(state["ready"])
        self.assertEqual(state["failed"], 0, state["errors"])
        self.assertEqual(report["consoleErrors"], [])
        return report, pixels

    def test_cesium_loads_the_terrain_with_the_image_and_samples_the_dems(self):
        import numpy
        prism, prism_t = harness.read_raster(os.path.join(ARGS.data, "PRISMelevation.tif"))
        jack, jack_t = harness.read_raster(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"))
        # PRISM's pixels away from the merged area (there the surface is Jacksboro's).
        points = {
            "prism": pixel_centres(prism, prism_t, SAMPLES, 1,
                                   exclude=bounds(jack, jack_t, margin_pixels=60)),
            "jacksboro": pixel_centres(jack, jack_t, SAMPLES, 2),
        }
        steps = [{"name": name, "run": "return await window.vsmSample(%s);"
                  % [[p[0], p[1]] for p in pts]} for name, pts in points.items()]
        steps.append({"name": "requests", "run": "return performance.getEntriesByType('resource')"
                      ".map((e) => e.name).filter((n) => n.includes('/terrain/'));"})
        report, pixels = self.page("model=%s&imagery=/viewer/conus.png&rect=%s"
                                   % (MODEL, self.image_rect), "terrain-whole", steps)
        assert_not_blank(self, pixels, "terrain-whole")
        done = {step["name"]: step["value"] for step in report["steps"]}
        tiles = [u for u in done["requests"] if ".terrain" in u]
        self.assertTrue(any(u.endswith("layer.json") for u in done["requests"]))
        self.assertGreater(len(tiles), 4, done["requests"])
        for name, pts in points.items():
            got = numpy.array(done[name], dtype=float)
            expected = numpy.array([p[2] for p in pts])
            relief = numpy.array([max(1.0, p[3]) for p in pts])
            error = numpy.abs(got - expected)
            worst = int(numpy.argmax(error / relief))
            print("\n%s: %d samples, error median %.2f m, max %.2f m; relief median %.2f m"
                  % (name, len(pts), numpy.median(error), error.max(), numpy.median(relief)),
                  file=sys.stderr)
            self.assertTrue((error <= relief).all(),
                            "%s: at %r Cesium says %.2f m, GDAL %.2f m (relief %.2f m)"
                            % (name, pts[worst][:2], got[worst], expected[worst], relief[worst]))
            self.assertLess(numpy.median(error), 0.1 * numpy.median(relief) + 0.5, name)

    def test_a_close_lit_view_of_jacksboro_shows_its_relief(self):
        import numpy
        view = "model=%s&at=%s&time=%s&imagery=/viewer/conus.png&rect=%s" % (
            MODEL, JACKSBORO_VIEW, JACKSBORO_TIME, self.image_rect)
        _, relief = self.page(view, "terrain-jacksboro")
        _, flat = self.page(view + "&flat=1", "terrain-jacksboro-flat")

        def shading_spread(pixels):
            """Spread of the luminance over the middle of the screen (the ground), smoothed over
            4 x 4 pixels (noise and antialiasing out)."""
            rows, cols = pixels.shape[:2]
            middle = pixels[rows // 3:rows * 5 // 6, cols // 6:cols * 5 // 6].astype(float)
            luminance = middle @ numpy.array([0.2126, 0.7152, 0.0722])
            r, c = (luminance.shape[0] // 4) * 4, (luminance.shape[1] // 4) * 4
            blocks = luminance[:r, :c].reshape(r // 4, 4, c // 4, 4).mean(axis=(1, 3))
            return float(blocks.std())

        terrain_spread, flat_spread = shading_spread(relief), shading_spread(flat)
        print("\njacksboro: luminance spread %.2f with the terrain, %.2f flat"
              % (terrain_spread, flat_spread), file=sys.stderr)
        self.assertGreater(terrain_spread, 3 * flat_spread + 2.0)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--model", required=True, help="the merged OPC (copied into the data root)")
    parser.add_argument("--data", required=True, help="../shared/data")
    parser.add_argument("--viewer", required=True, help="the built viewer (build.sh --cesium)")
    parser.add_argument("--web-tools", required=True, help="prefix holding playwright-core")
    parser.add_argument("--screenshots", required=True)
    parser.add_argument("--chromium", default=None)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    browser_support.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
