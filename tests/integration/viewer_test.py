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
  failures, tiles loaded, the screenshot not blank;
- a textured real model: PRISM imported with the NASA image draped over it (`vsm import
  PRISMelevation.tif <opc> --texture conus_visible_earth.tif --patch-size 65`, by the
  `tiles.model` fixture), looked at straight down (view=top) in the viewer's texture
  mode (textured tiles unlit) and in CesiumJS (unlit=1): every tile loaded and textured, zero
  failures, and the screenshot shows the image where it belongs. With the camera matrices the page
  reports, some 5600 DEM vertices (lon, lat, height -> WGS 84 ECEF, by our own geodesy) are
  projected to screen pixels; the colour there (3 x 3 pixel mean) is compared with the image
  itself at that lon/lat (bilinear, averaged over +-0.1 degrees, about a texel of the levels
  drawn): per-channel correlation, the median of the largest channel difference, the share of
  points within a few levels, mean colour and spread (`texture_match`, thresholds TEXTURE_*).
  The same check must fail for the same view in false colour, for PRISM imported without an
  image (the `opc.PRISMelevation-65` fixture's, textured with its shaded relief) in texture mode, and for the textured screenshot against
  the image moved by half a degree or mirrored north-south.

No request may leave 127.0.0.1. The screenshots and the numbers of the texture check
(texture-check.json) stay in --screenshots (CI artefacts).

Run by ctest:
    viewer_test.py --vsmd build/server/vsmd --model build/.../tiles/merged \\
        --textured-model build/.../tiles/prism --untextured-model build/.../PRISMelevation-65 \\
        --dem ../shared/data/PRISMelevation.tif --image ../shared/data/conus_visible_earth.tif \\
        --viewer build/viewer --web-tools build/web-tools --screenshots build/.../screenshots"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import Daemon  # noqa: E402

ARGS = None
MODEL = "merged"
HERE = os.path.dirname(os.path.abspath(__file__))
# The depth palette of core/tiles/README.md (kDepthPalette), sRGB.
PALETTE = ["30123b", "4145ab", "4675ed", "39a2fc", "1bcfd4", "24eca6", "61fc6c", "a4fc3b",
           "d1e834", "f3c63a", "fe9b2d", "f36315", "d93806", "b11901", "7a0402", "4a0000"]
BACKGROUND = (0x10, 0x14, 0x18)
# Per page: every wait in browser_check.js ends by then (the test's whole budget is ~5 minutes).
PAGE_SECONDS = 75
# The textured real model (PRISM with the NASA image) and the same DEM imported without an image
# (its shaded relief as texture).
TEXTURED = "prism-textured"
UNTEXTURED = "prism"
# The texture check: a screenshot matches the image when, over the sampled points, every channel
# correlates with the image by at least TEXTURE_R, the median of the largest channel difference
# is at most TEXTURE_MEDIAN levels, at least TEXTURE_SHARE of the points are within TEXTURE_CLOSE
# levels in every channel, the mean colours differ by at most TEXTURE_MEAN levels per channel and
# the spreads (standard deviations) by at most TEXTURE_SPREAD of the image's. Seen (swiftshader,
# both viewers): r >= 0.983 (blue the lowest), median 1.24, 98 % within 24, means within 0.5 and
# spreads within 2 %; the image moved by half a degree (~3 image pixels) fails three of the five
# (r 0.88 in blue, median 5.7, 86 % within 24).
TEXTURE_R = 0.97
TEXTURE_MEDIAN = 4.0
TEXTURE_CLOSE = 24
TEXTURE_SHARE = 0.95
TEXTURE_MEAN = 8.0
TEXTURE_SPREAD = 0.15
# The image is averaged over +-TEXTURE_BOX degrees around each point (about a texel of the levels
# the view loads, 4 DEM quads of 2.5 arc-minutes), and points lie every SAMPLE_STEP DEM samples,
# with SAMPLE_CLEAR samples of data all around (no point on the edge of the model).
TEXTURE_BOX = 0.1
SAMPLE_STEP = 12
SAMPLE_CLEAR = 4
# WGS 84 (the importer puts geographic rasters into WGS 84 ECEF metres).
WGS84_A = 6378137.0
WGS84_F = 1 / 298.257223563


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


def ecef(lon, lat, height):
    """WGS 84 geodetic (degrees, metres) -> ECEF metres, (n, 3)."""
    import numpy
    lam, phi = numpy.radians(lon), numpy.radians(lat)
    e2 = WGS84_F * (2 - WGS84_F)
    n = WGS84_A / numpy.sqrt(1 - e2 * numpy.sin(phi) ** 2)
    return numpy.stack([(n + height) * numpy.cos(phi) * numpy.cos(lam),
                        (n + height) * numpy.cos(phi) * numpy.sin(lam),
                        (n * (1 - e2) + height) * numpy.sin(phi)], axis=-1)


class Raster:
    """A GeoTIFF read with GDAL: bands (bands, rows, cols) as floats and its geotransform."""

    def __init__(self, path):
        from osgeo import gdal
        gdal.UseExceptions()
        dataset = gdal.Open(path)
        self.bands = dataset.ReadAsArray().astype(float)
        if self.bands.ndim == 2:
            self.bands = self.bands[None]
        self.transform = dataset.GetGeoTransform()
        assert self.transform[2] == 0 and self.transform[4] == 0, path  # north up

    def at(self, lon, lat):
        """(n, bands): bilinear between pixel centres (edge pixels extended)."""
        import numpy
        t = self.transform
        x = (lon - t[0]) / t[1] - 0.5
        y = (lat - t[3]) / t[5] - 0.5
        x0, y0 = numpy.floor(x).astype(int), numpy.floor(y).astype(int)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        rows, cols = self.bands.shape[1:]

        def px(i, j):
            return self.bands[:, numpy.clip(j, 0, rows - 1), numpy.clip(i, 0, cols - 1)].T

        return ((1 - fy) * ((1 - fx) * px(x0, y0) + fx * px(x0 + 1, y0))
                + fy * ((1 - fx) * px(x0, y0 + 1) + fx * px(x0 + 1, y0 + 1)))

    def box(self, lon, lat, half):
        """(n, bands): the mean of 5 x 5 bilinear samples over +-half degrees around each point."""
        offsets = [half * (k - 2) / 2 for k in range(5)]
        return sum(self.at(lon + dx, lat + dy) for dx in offsets for dy in offsets) / 25


def dem_points(dem):
    """(lon, lat, height) of DEM vertices every SAMPLE_STEP samples, with data all around."""
    import numpy
    heights = dem.bands[0]
    rows, cols = heights.shape
    c = SAMPLE_CLEAR
    jj, ii = numpy.mgrid[c:rows - c:SAMPLE_STEP, c:cols - c:SAMPLE_STEP]
    jj, ii = jj.ravel(), ii.ravel()
    clear = numpy.array([numpy.isfinite(heights[j - c:j + c + 1, i - c:i + c + 1]).all()
                         for j, i in zip(jj, ii)])
    jj, ii = jj[clear], ii[clear]
    t = dem.transform
    # A sample is the vertex at its pixel centre.
    return t[0] + (ii + 0.5) * t[1], t[3] + (jj + 0.5) * t[5], heights[jj, ii]


def project(camera, points, shape):
    """Screen pixels (x, y) of ECEF points with the page's matrices (three.js/Cesium: column-major
    4 x 4; `world` the tiles' group, identity when absent), scaled to the screenshot's size."""
    import numpy

    def matrix(name):
        return numpy.array(camera[name], dtype=float).reshape(4, 4).T

    m = matrix("projection") @ matrix("view")
    if "world" in camera:
        m = m @ matrix("world")
    clip = numpy.c_[points, numpy.ones(len(points))] @ m.T
    ndc = clip[:, :3] / clip[:, 3:]
    x = (ndc[:, 0] + 1) / 2 * shape[1]
    y = (1 - ndc[:, 1]) / 2 * shape[0]
    return x, y, clip[:, 3] > 0


def overlay_mask(state, shape):
    """(rows, cols) bool: the pixels under the page's overlays (the viewer's panel and legend, as
    it reports them in `overlays`, CSS pixels scaled to the screenshot)."""
    import numpy
    mask = numpy.zeros(shape[:2], dtype=bool)
    camera = state.get("camera") or {}
    scale = shape[1] / camera["width"] if camera.get("width") else 1.0
    for r in state.get("overlays", []):
        x0, y0 = int(r["x"] * scale) - 2, int(r["y"] * scale) - 2
        x1, y1 = int((r["x"] + r["width"]) * scale) + 3, int((r["y"] + r["height"]) * scale) + 3
        mask[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = True
    return mask


def screen_samples(state, pixels, lon, lat, height):
    """Points (lon, lat, height above the ellipsoid) seen in a screenshot, with the page's camera:
    (which of them are on the screen, clear of its border, the page's overlays and Cesium's credit
    (bottom left); their screen colours, (n, 3) means of 3 x 3 pixels)."""
    import numpy
    x, y, front = project(state["camera"], ecef(lon, lat, height), pixels.shape)
    rows, cols = pixels.shape[:2]
    inside = (front & (x >= 2) & (x < cols - 2) & (y >= 2) & (y < rows - 2)
              & ~((x < 200) & (y > rows - 50)))
    covered = overlay_mask(state, pixels.shape)
    xs, ys = numpy.round(x).astype(int), numpy.round(y).astype(int)
    inside[inside] &= ~covered[ys[inside], xs[inside]]
    xs, ys = xs[inside], ys[inside]
    got = numpy.mean([pixels[ys + dy, xs + dx].astype(float)
                      for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
    return inside, got


def browser_check(base_url, page, state, screenshot, seconds, steps=None):
    """Runs browser_check.js on `page` (with a list of steps, see there): its report."""
    if os.path.exists(screenshot):
        os.remove(screenshot)
    env = dict(os.environ)
    if ARGS.chromium:
        env["VSM_CHROMIUM"] = ARGS.chromium
    command = ["node", os.path.join(HERE, "browser_check.js"), ARGS.web_tools, base_url + page,
               state, screenshot, str(seconds)]
    if steps is not None:
        steps_file = screenshot + ".steps.json"
        with open(steps_file, "w") as f:
            json.dump(steps, f)
        command.append(steps_file)
    result = subprocess.run(command, capture_output=True, text=True,
                            timeout=seconds * (2 + len(steps or [])) + 60, env=env)
    if result.returncode != 0:
        raise AssertionError("browser_check.js failed:\n" + result.stderr[-3000:])
    return json.loads(result.stdout.strip().splitlines()[-1])


def load_page(test, base_url, page, state, name, seconds, steps=None):
    """browser_check on `page` (and its steps), the report kept beside the screenshot (name.png
    in --screenshots): the page settled, no request left the server or failed; (the report, the
    screenshot's pixels)."""
    screenshot = os.path.join(ARGS.screenshots, name + ".png")
    report = browser_check(base_url, page, state, screenshot, seconds, steps)
    print("\n%s: %s" % (name, json.dumps(report)[:1500]), file=sys.stderr)
    with open(screenshot + ".json", "w") as f:
        json.dump(report, f)
    test.assertFalse(report.get("timedOut"), "page did not settle in %d s: %s"
                     % (seconds, json.dumps(report)[:3000]))
    test.assertEqual(report["offHost"], [], "requests left the server")
    test.assertEqual(report["failedRequests"], [])
    test.assertTrue(os.path.exists(screenshot))
    return report, read_png(screenshot)


def texture_match(got, expected):
    """Numbers comparing screen colours with image colours ((n, 3) each) and whether they match."""
    import numpy
    worst = numpy.abs(got - expected).max(axis=1)
    r = []
    for c in range(3):
        spread = got[:, c].std() * expected[:, c].std()
        r.append(float(numpy.corrcoef(got[:, c], expected[:, c])[0, 1]) if spread > 0 else 0.0)
    mean_got, mean_expected = got.mean(axis=0), expected.mean(axis=0)
    spread_got, spread_expected = got.std(axis=0), expected.std(axis=0)
    numbers = {
        "points": len(got),
        "r": [round(v, 4) for v in r],
        "median": round(float(numpy.median(worst)), 2),
        "share_close": round(float((worst <= TEXTURE_CLOSE).mean()), 4),
        "mean": [round(float(v), 1) for v in mean_got],
        "image_mean": [round(float(v), 1) for v in mean_expected],
        "spread": [round(float(v), 1) for v in spread_got],
        "image_spread": [round(float(v), 1) for v in spread_expected],
    }
    failed = []
    if min(r) < TEXTURE_R:
        failed.append("correlation")
    if numbers["median"] > TEXTURE_MEDIAN:
        failed.append("median")
    if numbers["share_close"] < TEXTURE_SHARE:
        failed.append("share_close")
    if numpy.abs(mean_got - mean_expected).max() > TEXTURE_MEAN:
        failed.append("mean")
    if (numpy.abs(spread_got - spread_expected) > TEXTURE_SPREAD * spread_expected).any():
        failed.append("spread")
    numbers["failed"] = failed
    return numbers


class Browser(unittest.TestCase):
    daemon = None
    texture_numbers = {}

    @classmethod
    def setUpClass(cls):
        def prepare(root):
            shutil.copytree(ARGS.model, os.path.join(root, MODEL))
            shutil.copytree(ARGS.textured_model, os.path.join(root, TEXTURED))
            shutil.copytree(ARGS.untextured_model, os.path.join(root, UNTEXTURED))

        os.makedirs(ARGS.screenshots, exist_ok=True)
        cls.daemon = Daemon("--set", "threads.cpu=2", "--viewer-dir", ARGS.viewer,
                            "--log-level", "warn", prepare=prepare)
        cls.base_url = cls.daemon.base

    @classmethod
    def tearDownClass(cls):
        if cls.texture_numbers:
            with open(os.path.join(ARGS.screenshots, "texture-check.json"), "w") as f:
                json.dump(cls.texture_numbers, f, indent=1)
        if cls.daemon is not None:
            code = cls.daemon.stop()
            cls.daemon.cleanup(keep=code != 0)

    def load(self, page, state, name):
        """Runs browser_check.js on `page`; (its report, the screenshot's pixels)."""
        return load_page(self, self.base_url, page, state, name, PAGE_SECONDS)

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
        self.assertEqual(state["failed"], 0, self.why(state["errors"]))
        self.assertEqual(report["consoleErrors"], [])
        self.assertTrue(state["rootLoaded"])
        self.assertGreater(state["loaded"], 0)
        self.assertEqual(state["pending"], 0)
        # Every tile the renderer asked for came in (none still loading, none lost).
        self.assertEqual(state["loaded"], state["requested"], state)
        self.assert_not_blank(pixels, "viewer-lod")
        model_area = ~overlay_mask(state, pixels.shape)
        counts = colour_counts(pixels[model_area])
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
        self.assertGreater(shown_pixels, model_area.sum() * 0.05)

    def test_viewer_texture_mode_draws_the_model(self):
        report, pixels = self.load("/viewer/?model=%s&mode=texture" % MODEL, "vsmViewer",
                                   "viewer-texture")
        state = report["state"]
        self.assertEqual(state["failed"], 0, self.why(state["errors"]))
        self.assertEqual(state["mode"], "texture")
        self.assertEqual(state["loaded"], state["requested"], state)
        self.assert_not_blank(pixels, "viewer-texture")
        counts = colour_counts(pixels[~overlay_mask(state, pixels.shape)])
        shown = [d for d in range(len(PALETTE)) if counts.get(int(PALETTE[d], 16), 0) >= 200]
        self.assertLessEqual(len(shown), 1, "texture mode shows the LOD palette: %s" % shown)

    # ---- the textured real model -------------------------------------------------------------

    def screen_colours(self, report, pixels, name):
        """The sampled DEM points seen in a screenshot: (their lon, lat, (n, 3) screen colours)."""
        self.assertIsNotNone(report["state"]["camera"], report["state"])
        lon, lat, height = dem_points(self.dem)
        inside, got = screen_samples(report["state"], pixels, lon, lat, height)
        print("%s: %d of %d DEM points on the screen" % (name, len(got), len(lon)),
              file=sys.stderr)
        # Most of PRISM in view (a camera that misses it would leave too few points to judge).
        self.assertGreater(len(got), 0.8 * len(lon), name)
        self.assertGreater(len(got), 1000, name)
        return lon[inside], lat[inside], got

    def check_texture(self, name, report, pixels, expect_match=True, shift=None):
        """texture_match of a screenshot against the image; `shift(lon, lat)` moves where the image
        is sampled (a misplaced texture). Records the numbers for texture-check.json."""
        lon, lat, got = self.screen_colours(report, pixels, name)
        if shift is not None:
            lon, lat = shift(lon, lat)
        numbers = texture_match(got, self.image.box(lon, lat, TEXTURE_BOX)[:, :3])
        Browser.texture_numbers[name] = numbers
        print("%s: texture check %s" % (name, json.dumps(numbers)), file=sys.stderr)
        if expect_match:
            self.assertEqual(numbers["failed"], [], "%s does not show the image: %s"
                             % (name, numbers))
        else:
            # Clearly not the image: most of the criteria fail, the main two always.
            self.assertIn("correlation", numbers["failed"], numbers)
            self.assertIn("share_close", numbers["failed"], numbers)
        return numbers

    def why(self, errors):
        """The tile errors the page reported, with what the daemon answers for the first failed
        URL now and the daemon log's last lines: enough to tell a flaky load from a server error."""
        if not errors:
            return errors
        url = errors[0].split(": ")[0]
        path = url[url.index("/v1/"):] if "/v1/" in url else url
        status, _, body = self.daemon.request("GET", path)
        return "%s\nGET %s now: %d %s\nvsmd log:\n%s" % (
            errors[:3], path, status, body[:300], "\n".join(self.daemon.log().splitlines()[-20:]))

    @classmethod
    def rasters(cls):
        if not hasattr(cls, "dem"):
            cls.dem = Raster(ARGS.dem)
            cls.image = Raster(ARGS.image)

    def load_viewer_top(self, model, mode, name):
        report, pixels = self.load("/viewer/?model=%s&mode=%s&view=top" % (model, mode),
                                   "vsmViewer", name)
        state = report["state"]
        self.assertEqual(state["failed"], 0, self.why(state["errors"]))
        self.assertEqual(report["consoleErrors"], [])
        self.assertEqual(state["mode"], mode)
        self.assertEqual(state["view"], "top")
        self.assertGreater(state["loaded"], 1)
        self.assertEqual(state["pending"], 0)
        self.assertEqual(state["loaded"], state["requested"], state)
        self.assert_not_blank(pixels, name)
        return report, pixels

    def test_viewer_shows_the_texture_of_a_textured_real_model(self):
        self.rasters()
        report, pixels = self.load_viewer_top(TEXTURED, "texture", "viewer-textured")
        state = report["state"]
        # Every tile the renderer loaded carried the image (PRISM's whole extent is covered).
        self.assertEqual(state["textured"], state["loaded"], state)
        print("viewer-textured: %d tiles, depths %s" % (state["loaded"], state["depths"]),
              file=sys.stderr)
        self.check_texture("viewer-textured", report, pixels)
        # The same screenshot against the image half a degree east (~3 of its pixels, ~45 km)
        # and mirrored north-south inside PRISM's extent: a misplaced texture fails.
        self.check_texture("viewer-textured vs image moved 0.5 deg east", report, pixels,
                           expect_match=False, shift=lambda lon, lat: (lon + 0.5, lat))
        t = self.dem.transform
        north, south = t[3], t[3] + self.dem.bands.shape[1] * t[5]
        self.check_texture("viewer-textured vs image mirrored north-south", report, pixels,
                           expect_match=False, shift=lambda lon, lat: (lon, north + south - lat))

    def test_viewer_false_colour_of_the_textured_model_is_not_the_image(self):
        self.rasters()
        report, pixels = self.load_viewer_top(TEXTURED, "lod", "viewer-textured-lod")
        self.check_texture("viewer-textured-lod", report, pixels, expect_match=False)

    def test_viewer_texture_mode_of_the_model_without_an_image_is_not_the_image(self):
        # Imported without an image, PRISM carries its own shaded relief: every tile is textured,
        # and not with the NASA image.
        self.rasters()
        report, pixels = self.load_viewer_top(UNTEXTURED, "texture", "viewer-untextured")
        self.assertEqual(report["state"]["textured"], report["state"]["loaded"], report["state"])
        self.assertGreater(report["state"]["loaded"], 1)
        self.check_texture("viewer-untextured", report, pixels, expect_match=False)

    def test_cesium_shows_the_texture_of_a_textured_real_model(self):
        self.rasters()
        report, pixels = self.load("/viewer/cesium.html?model=%s&view=top&unlit=1&error=4"
                                   % TEXTURED, "vsmCesium", "cesium-textured")
        state = report["state"]
        self.assertIsNone(state["error"], state)
        self.assertTrue(state["ready"])
        self.assertEqual(state["failed"], 0, self.why(state["errors"]))
        self.assertGreater(state["loaded"], 1)
        self.assertTrue(state["idle"], state)
        self.assert_not_blank(pixels, "cesium-textured")
        self.check_texture("cesium-textured", report, pixels)

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
        self.assertEqual(state["failed"], 0, self.why(state["errors"]))
        self.assertGreater(state["loaded"], 0)
        self.assertTrue(state["idle"], state)
        self.assert_not_blank(pixels, "cesium")


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--model", required=True, help="the merged OPC (copied into the data root)")
    parser.add_argument("--textured-model", required=True,
                        help="PRISM imported with --texture conus_visible_earth.tif")
    parser.add_argument("--untextured-model", required=True, help="PRISM imported without one")
    parser.add_argument("--dem", required=True, help="PRISMelevation.tif")
    parser.add_argument("--image", required=True, help="conus_visible_earth.tif")
    parser.add_argument("--viewer", required=True, help="the built viewer (build.sh --cesium)")
    parser.add_argument("--web-tools", required=True, help="prefix holding playwright-core")
    parser.add_argument("--screenshots", required=True, help="where the screenshots are kept")
    parser.add_argument("--chromium", default="", help="the browser (default /usr/bin/chromium)")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
