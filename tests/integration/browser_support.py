"""What the browser tests share (viewer_test, demo_viewer_test, terrain_browser_test,
tunnel_viewer_test): browser_check.js driven from Python, screenshots read and judged, and the
geodesy and projection that put DEM points on the screen.

Each test calls configure() with its parsed command line (--web-tools, --chromium,
--screenshots) before its cases run."""

import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
# From configure(): the prefix holding playwright-core, the browser ("" or None: browser_check.js's
# default, /usr/bin/chromium) and where screenshots are kept.
WEB_TOOLS = None
CHROMIUM = None
SCREENSHOTS = None
# The depth palette of core/tiles/README.md (kDepthPalette), sRGB.
PALETTE = ["30123b", "4145ab", "4675ed", "39a2fc", "1bcfd4", "24eca6", "61fc6c", "a4fc3b",
           "d1e834", "f3c63a", "fe9b2d", "f36315", "d93806", "b11901", "7a0402", "4a0000"]
BACKGROUND = (0x10, 0x14, 0x18)
# DEM points (dem_points) lie every SAMPLE_STEP DEM samples, with SAMPLE_CLEAR samples of data all
# around (no point on the edge of the model).
SAMPLE_STEP = 12
SAMPLE_CLEAR = 4

# WGS 84 (the importer puts geographic rasters into WGS 84 ECEF metres).
WGS84_A = 6378137.0
WGS84_F = 1 / 298.257223563


def configure(args):
    """Takes --web-tools, --chromium and --screenshots from a parsed command line."""
    global WEB_TOOLS, CHROMIUM, SCREENSHOTS
    WEB_TOOLS = args.web_tools
    CHROMIUM = getattr(args, "chromium", None)
    SCREENSHOTS = args.screenshots


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


def pixel_centres(heights, transform, count, seed, box=None, exclude=None):
    """`count` random pixels of a DEM with data on all 8 sides, whose centres lie in `box` (W, S,
    E, N; anywhere when None) and outside `exclude` (W, S, E, N): (lon, lat of their centres,
    GDAL's height, the pixel's relief: its largest difference to its 8 neighbours)."""
    import numpy
    rows, cols = heights.shape
    rng = numpy.random.default_rng(seed)
    i0, i1, j0, j1 = 1, cols - 2, 1, rows - 2
    if box is not None:
        w, s, e, n = box
        i0 = max(i0, int((w - transform[0]) / transform[1]))
        i1 = min(i1, int((e - transform[0]) / transform[1]))
        j0 = max(j0, int((n - transform[3]) / transform[5]))
        j1 = min(j1, int((s - transform[3]) / transform[5]))
        assert i0 < i1 and j0 < j1, box
    out = []
    while len(out) < count:
        j, i = int(rng.integers(j0, j1 + 1)), int(rng.integers(i0, i1 + 1))
        block = heights[j - 1:j + 2, i - 1:i + 2]
        if not numpy.isfinite(block).all():
            continue
        lon = transform[0] + (i + 0.5) * transform[1]
        lat = transform[3] + (j + 0.5) * transform[5]
        if box is not None and not (box[0] <= lon <= box[2] and box[1] <= lat <= box[3]):
            continue
        if exclude is not None and (exclude[0] <= lon <= exclude[2]
                                    and exclude[1] <= lat <= exclude[3]):
            continue
        out.append((lon, lat, heights[j, i], float(numpy.abs(block - heights[j, i]).max())))
    return out


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
    if CHROMIUM:
        env["VSM_CHROMIUM"] = CHROMIUM
    command = ["node", os.path.join(HERE, "browser_check.js"), WEB_TOOLS, base_url + page,
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
    screenshot = os.path.join(SCREENSHOTS, name + ".png")
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


def assert_not_blank(test, pixels, name):
    """Fails `test` unless the screenshot shows something: many colours, over 5 % of it drawn
    (far from BACKGROUND), not almost all background; {colour: count} of it."""
    counts = colour_counts(pixels)
    background = (BACKGROUND[0] << 16) | (BACKGROUND[1] << 8) | BACKGROUND[2]
    total = pixels.shape[0] * pixels.shape[1]
    # Pixels far from the background colour (antialiasing and UI included).
    diff = abs(pixels.astype(int) - BACKGROUND).sum(axis=2)
    drawn = int((diff > 24).sum())
    print("%s: %d x %d, %d distinct colours, %.1f %% drawn"
          % (name, pixels.shape[1], pixels.shape[0], len(counts), 100.0 * drawn / total),
          file=sys.stderr)
    test.assertGreater(len(counts), 50, "%s: blank (%d colours)" % (name, len(counts)))
    test.assertGreater(drawn, total * 0.05, "%s: almost nothing drawn" % name)
    test.assertLess(counts.get(background, 0), total * 0.97)
    return counts
