#!/usr/bin/python3
"""The browser check of issue 6: headless Chromium (Debian's /usr/bin/chromium, driven by npm
`playwright-core` through browser_check.js, with exactly the flags CI uses) loads the 3D Tiles
view of the real merged model (PRISM with Jacksboro: the `tiles.model` fixture) from the real
vsmd on 127.0.0.1:0, which also serves the built viewer (--viewer-dir, built by
client-examples/web/build.sh --cesium: the `viewer.site` fixture), in

- the project's viewer (three.js + 3d-tiles-renderer), /viewer/?model=merged in level-of-detail
  false colour: every requested tile loaded, zero failures, the screenshot not blank (many
  distinct colours, and the palette colours of several depths among its pixels);
- CesiumJS, /viewer/cesium.html?model=merged (no imagery, no terrain, no ion): zero tile
  failures, tiles loaded, the screenshot not blank.

No request may leave 127.0.0.1. The screenshots stay in --screenshots (CI artefacts).

Run by ctest:
    viewer_test.py --vsmd build/server/vsmd --model build/.../tiles/merged \\
        --viewer build/viewer --web-tools build/web-tools --screenshots build/.../screenshots"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import server_test as base  # noqa: E402  (the Daemon harness)
from server_test import Daemon  # noqa: E402

ARGS = None
MODEL = "merged"
HERE = os.path.dirname(os.path.abspath(__file__))
# The depth palette of core/tiles/README.md (kDepthPalette), sRGB.
PALETTE = ["30123b", "4145ab", "4675ed", "39a2fc", "1bcfd4", "24eca6", "61fc6c", "a4fc3b",
           "d1e834", "f3c63a", "fe9b2d", "f36315", "d93806", "b11901", "7a0402", "4a0000"]
BACKGROUND = (0x10, 0x14, 0x18)
# The viewer's panel (title, mode switch, the palette as a legend) lies in the top rows; colours
# of the model are counted below them.
PANEL_ROWS = 100
# Per page: every wait in browser_check.js ends by then (the test's whole budget is ~3 minutes).
PAGE_SECONDS = 75


def read_png(path):
    """(height, width, 3) uint8 array of a PNG, read with GDAL (as other checks read rasters)."""
    from osgeo import gdal
    gdal.UseExceptions()
    dataset = gdal.Open(path)
    import numpy
    bands = [dataset.GetRasterBand(i + 1).ReadAsArray() for i in range(min(3, dataset.RasterCount))]
    return numpy.dstack(bands).astype(numpy.uint8)


def colour_counts(pixels):
    """{0xRRGGBB: count} of an image."""
    import numpy
    flat = pixels.reshape(-1, 3).astype(numpy.uint32)
    keys = (flat[:, 0] << 16) | (flat[:, 1] << 8) | flat[:, 2]
    values, counts = numpy.unique(keys, return_counts=True)
    return dict(zip(values.tolist(), counts.tolist()))


class Browser(unittest.TestCase):
    daemon = None

    @classmethod
    def setUpClass(cls):
        def prepare(root):
            shutil.copytree(ARGS.model, os.path.join(root, MODEL))

        os.makedirs(ARGS.screenshots, exist_ok=True)
        cls.daemon = Daemon("--set", "threads.cpu=2", "--viewer-dir", ARGS.viewer,
                            "--log-level", "warn", prepare=prepare)
        cls.base_url = "http://127.0.0.1:%d" % cls.daemon.port

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is not None:
            code = cls.daemon.stop()
            cls.daemon.cleanup(keep=code != 0)

    def load(self, page, state, name):
        """Runs browser_check.js on `page`; (its report, the screenshot's pixels)."""
        screenshot = os.path.join(ARGS.screenshots, name + ".png")
        if os.path.exists(screenshot):
            os.remove(screenshot)
        env = dict(os.environ)
        if ARGS.chromium:
            env["VSM_CHROMIUM"] = ARGS.chromium
        result = subprocess.run(
            ["node", os.path.join(HERE, "browser_check.js"), ARGS.web_tools,
             self.base_url + page, state, screenshot, str(PAGE_SECONDS)],
            capture_output=True, text=True, timeout=PAGE_SECONDS + 60, env=env)
        self.assertEqual(result.returncode, 0, result.stderr[-3000:])
        report = json.loads(result.stdout.strip().splitlines()[-1])
        print("\n%s: %s" % (name, json.dumps(report)[:1500]), file=sys.stderr)
        self.assertFalse(report.get("timedOut"), "page did not settle in %d s: %s"
                         % (PAGE_SECONDS, json.dumps(report)[:3000]))
        self.assertEqual(report["offHost"], [], "requests left the server")
        self.assertEqual(report["failedRequests"], [])
        self.assertTrue(os.path.exists(screenshot))
        return report, read_png(screenshot)

    def assert_not_blank(self, pixels, name):
        counts = colour_counts(pixels)
        background = (BACKGROUND[0] << 16) | (BACKGROUND[1] << 8) | BACKGROUND[2]
        total = pixels.shape[0] * pixels.shape[1]
        # Pixels far from the background colour (antialiasing and UI included).
        diff = abs(pixels.astype(int) - BACKGROUND).sum(axis=2)
        drawn = int((diff > 24).sum())
        print("%s: %d x %d, %d distinct colours, %.1f %% drawn"
              % (name, pixels.shape[1], pixels.shape[0], len(counts), 100.0 * drawn / total),
              file=sys.stderr)
        self.assertGreater(len(counts), 50, "%s: blank (%d colours)" % (name, len(counts)))
        self.assertGreater(drawn, total * 0.05, "%s: almost nothing drawn" % name)
        self.assertLess(counts.get(background, 0), total * 0.97)
        return counts

    def test_viewer_loads_every_tile_in_false_colour(self):
        report, pixels = self.load("/viewer/?model=%s&mode=lod" % MODEL, "vsmViewer", "viewer-lod")
        state = report["state"]
        self.assertIsNotNone(state, report)
        self.assertEqual(state["failed"], 0, state["errors"])
        self.assertEqual(report["consoleErrors"], [])
        self.assertTrue(state["rootLoaded"])
        self.assertGreater(state["loaded"], 0)
        self.assertEqual(state["pending"], 0)
        # Every tile the renderer asked for came in (none still loading, none lost).
        self.assertEqual(state["loaded"], state["requested"], state)
        self.assert_not_blank(pixels, "viewer-lod")
        counts = colour_counts(pixels[PANEL_ROWS:])
        # Unlit palette colours: the model shows in the exact colours of depths the renderer loaded
        # (seen whole, PRISM is one depth; Jacksboro's deeper levels cover a few pixels), and the
        # renderer refined below the root.
        shown = [d for d in range(len(PALETTE)) if counts.get(int(PALETTE[d], 16), 0) >= 50]
        print("viewer-lod: depths loaded %s, palette colours shown for depths %s"
              % (state["depths"], shown), file=sys.stderr)
        loaded = {int(d) for d in state["depths"]}
        self.assertGreaterEqual(len(loaded), 2, state["depths"])
        self.assertGreaterEqual(len(shown), 1, (state["depths"], shown))
        self.assertTrue(set(shown) <= loaded, (shown, loaded))
        shown_pixels = sum(counts.get(int(PALETTE[d], 16), 0) for d in shown)
        self.assertGreater(shown_pixels, (pixels.shape[0] - PANEL_ROWS) * pixels.shape[1] * 0.05)

    def test_viewer_texture_mode_draws_the_model(self):
        report, pixels = self.load("/viewer/?model=%s&mode=texture" % MODEL, "vsmViewer",
                                   "viewer-texture")
        state = report["state"]
        self.assertEqual(state["failed"], 0, state["errors"])
        self.assertEqual(state["mode"], "texture")
        self.assertEqual(state["loaded"], state["requested"], state)
        self.assert_not_blank(pixels, "viewer-texture")
        counts = colour_counts(pixels[PANEL_ROWS:])
        shown = [d for d in range(len(PALETTE)) if counts.get(int(PALETTE[d], 16), 0) >= 200]
        self.assertLessEqual(len(shown), 1, "texture mode shows the LOD palette: %s" % shown)

    def test_the_viewer_files_are_served_safely_with_types_and_etags(self):
        d = self.daemon
        status, headers, body = d.request("GET", "/viewer")
        self.assertEqual(status, 301)
        self.assertEqual(headers["Location"], "/viewer/")
        status, headers, body = d.request("GET", "/viewer/?model=merged")
        self.assertEqual(status, 200)
        self.assertTrue(headers["Content-Type"].startswith("text/html"))
        self.assertIn(b"importmap", body)
        status, _, _ = d.request("GET", "/viewer/", headers={"If-None-Match": headers["ETag"]})
        self.assertEqual(status, 304)
        for path, kind in (("/viewer/main.js", "text/javascript"),
                           ("/viewer/vendor/three/build/three.module.js", "text/javascript"),
                           ("/viewer/vendor/cesium/Build/Widgets/widgets.css", "text/css")):
            status, headers, _ = d.request("HEAD", path)
            self.assertEqual(status, 200, path)
            self.assertTrue(headers["Content-Type"].startswith(kind), path)
        # Raw targets (http.client sends them as written): no way out of the viewer directory to
        # its neighbour (the build directory's build.ninja, next to <build>/viewer).
        outside = os.path.basename(os.path.abspath(ARGS.viewer))
        self.assertTrue(os.path.exists(os.path.join(ARGS.viewer, "..", "build.ninja")))
        for path in ("/viewer/../build.ninja", "/viewer/%2e%2e/build.ninja",
                     "/viewer/vendor/..%2F..%2Fbuild.ninja", "/viewer/.%2e/build.ninja",
                     "/viewer/../%s/index.html" % outside, "/viewer/nope.js"):
            status, _, body = d.request("GET", path)
            self.assertEqual(status, 404, path)
            self.assertIn(b'"error"', body, path)

    def test_cesium_loads_the_tileset_without_failures(self):
        report, pixels = self.load("/viewer/cesium.html?model=%s" % MODEL, "vsmCesium", "cesium")
        state = report["state"]
        self.assertIsNotNone(state, report)
        self.assertIsNone(state["error"], state)
        self.assertTrue(state["ready"])
        self.assertEqual(state["failed"], 0, state["errors"])
        self.assertGreater(state["loaded"], 0)
        self.assertTrue(state["idle"], state)
        self.assert_not_blank(pixels, "cesium")


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--model", required=True, help="the merged OPC (copied into the data root)")
    parser.add_argument("--viewer", required=True, help="the built viewer (build.sh --cesium)")
    parser.add_argument("--web-tools", required=True, help="prefix holding playwright-core")
    parser.add_argument("--screenshots", required=True, help="where the screenshots are kept")
    parser.add_argument("--chromium", default="", help="the browser (default /usr/bin/chromium)")
    ARGS, rest = parser.parse_known_args()
    base.ARGS = ARGS
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
