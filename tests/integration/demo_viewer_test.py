#!/usr/bin/python3
"""The demo, end to end in headless Chromium (issue 15): exactly the demo's set-up
(deploy/demo-setup.sh --no-build: PRISM imported with the NASA image, Jacksboro, the viewer built)
into a fresh directory, then the real vsmd on 127.0.0.1:0 started on it as deploy/demo.sh does
(--data-root <demo>/models --viewer-dir <demo>/viewer), and the viewer driven by browser_check.js
(Debian's chromium, npm playwright-core, the flags CI uses; no request may leave 127.0.0.1):

1. The demo's URL (PRISM, texture mode) loads: every tile, all textured, none failed. The LOD
   legend names each depth of the model with its resolution as GET /v1/models/{m} has it (and
   PRISM's finest is the DEM's own sample spacing, by GDAL), its swatches show the palette.
2. Relief: the untextured surface shaded by the sun (relief mode ignores any texture), seen from
   straight above at height x10 (PRISM's 4 km samples are nearly flat at x1: GDAL's hillshade
   spreads 2 levels of 255), against GDAL's hillshade of the DEM with the same sun and -z 10
   (gdaldem hillshade, azimuth 315, altitude 45, scale 111120 for a geographic DEM): the screen's
   grey (sRGB decoded to linear) at ~5600 projected DEM vertices correlates with the hillshade
   there by at least RELIEF_R; the same screenshot against the hillshade with the sun from the
   opposite side, and mirrored north-south, must not. Then the height control to 4: the
   screenshot changes, the relief's contrast falls as GDAL's does from -z 10 to -z 4 (within
   RELIEF_GAIN), and the correlation with the -z 4 hillshade at those vertices holds.
3. Live: the viewer flown to Jacksboro's area (its fly-to button, from the hierarchy API's
   deepest level); the tiles drawn over Jacksboro's footprint are PRISM's; the page's merge
   button submits the merge (POST /v1/jobs); without a reload (a mark left in the page survives)
   the page sees the job end, reloads the tileset on the `published` event, and the tiles drawn
   over Jacksboro are then deeper than before and than PRISM's deepest level; the job succeeded
   by the API. The revision picker then lists the latest, 2 and 1; picking 1 draws the tiles over
   Jacksboro at PRISM's depths again (?rev=1), still without a reload. Back on the latest, the
   changes mode reads the diff 1 -> 2 (GET /v1/models/{m}/diff) and the tiles over Jacksboro are
   coloured by more than a metre of displacement, with the range in its legend.

Screenshots and the relief numbers (relief-check.json) in --screenshots; the first screenshot of
the textured demo is the README's (copied there by hand: client-examples/web/viewer.png).

    demo_viewer_test.py --vsmd build/server/vsmd --build build --data ../shared/data \\
        --web-tools build/web-tools --work build/.../work/demo --screenshots build/.../screenshots
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
import browser_support  # noqa: E402
from browser_support import (PALETTE, Raster, assert_not_blank, dem_points,  # noqa: E402
                             load_page, overlay_mask, read_png, screen_samples)
from harness import Daemon  # noqa: E402

ARGS = None
HERE = os.path.dirname(os.path.abspath(__file__))
SOURCE = os.path.dirname(os.path.dirname(HERE))
PRISM = "PRISMelevation"
JACKSBORO = "jacksboro_fault_dem"
# Per page and per step: the merge step waits for the merge job (~25 s on 2 busy cores) and the
# new tiles.
PAGE_SECONDS = 150
# The viewer's default sun, and GDAL's (gdaldem hillshade's defaults).
SUN_AZIMUTH, SUN_ALTITUDE = 315.0, 45.0
# Relief check: Pearson correlation of the screen's linear grey with GDAL's hillshade (averaged
# over +-RELIEF_BOX degrees, about a DEM sample: the deepest level drawn) at the projected DEM
# vertices: a 3 x 3 pixel mean on the screen covers some 6 DEM samples of PRISM seen whole.
# Seen (swiftshader, x10): r 0.67; the sun from the opposite side 0.09, mirrored 0.06; at x4 0.48.
RELIEF_R = 0.4
RELIEF_BOX = 0.1
# Exaggeration 10 -> 4: the screen's contrast (standard deviation of the linear grey over the
# points) changes by the factor GDAL's hillshade's does from -z 10 to -z 4, within this share of
# it; and the mean absolute difference of the two screenshots over the model is at least
# EXAGGERATED_DIFF levels.
# Seen: contrast x0.45 (GDAL x0.40), 0.70 levels (the same page twice: 0, a deterministic render).
RELIEF_GAIN = 0.35
EXAGGERATED_DIFF = 0.35


def srgb_to_linear(values):
    """sRGB levels (0..255) to linear light (0..1), the inverse of the page's output encoding."""
    import numpy
    c = numpy.asarray(values, dtype=float) / 255.0
    return numpy.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def hillshade(dem_path, out_path, azimuth, z_factor):
    """GDAL's hillshade of the DEM (geographic: scale 111120 metres a degree) into out_path."""
    from osgeo import gdal
    gdal.UseExceptions()
    gdal.DEMProcessing(out_path, dem_path, "hillshade", azimuth=azimuth, altitude=SUN_ALTITUDE,
                       scale=111120, zFactor=z_factor, computeEdges=True)
    return Raster(out_path)


def boxes_intersect(a, b):
    return all(a["min"][i] <= b["max"][i] and b["min"][i] <= a["max"][i] for i in range(3))


class Demo(unittest.TestCase):
    daemon = None
    numbers = {}

    @classmethod
    def setUpClass(cls):
        shutil.rmtree(ARGS.work, ignore_errors=True)
        os.makedirs(ARGS.screenshots, exist_ok=True)
        cls.demo = os.path.join(ARGS.work, "demo")
        env = dict(os.environ, VSM_BUILD_DIR=ARGS.build, VSM_DEMO_DIR=cls.demo,
                   VSM_NPM_PREFIX=ARGS.web_tools, VSM_DATA=ARGS.data)
        subprocess.run([os.path.join(SOURCE, "deploy", "demo-setup.sh"), "--no-build"],
                       env=env, check=True, timeout=600)
        # As deploy/demo.sh starts it (on port 0, with a port file, two CPU threads for CI).
        cls.daemon = Daemon("--viewer-dir", os.path.join(cls.demo, "viewer"),
                            "--set", "threads.cpu=2", "--log-level", "warn",
                            root=os.path.join(cls.demo, "models"))
        cls.base_url = cls.daemon.base
        cls.dem = Raster(os.path.join(ARGS.data, "PRISMelevation.tif"))

    @classmethod
    def tearDownClass(cls):
        if cls.numbers:
            with open(os.path.join(ARGS.screenshots, "relief-check.json"), "w") as f:
                json.dump(cls.numbers, f, indent=1)
        if cls.daemon is not None:
            code = cls.daemon.stop()
            cls.daemon.kill()
            if code == 0:
                shutil.rmtree(ARGS.work, ignore_errors=True)

    def load(self, page, name, steps=None):
        """The page and its steps in one browser: (report, screenshot pixels)."""
        report, pixels = load_page(self, self.base_url, page, "vsmViewer", name, PAGE_SECONDS,
                                   steps)
        self.assertEqual(report["consoleErrors"], [])
        state = report["state"]
        self.assertEqual(state["failed"], 0, state["errors"])
        self.assertEqual(state["loaded"], state["requested"], state)
        return report, pixels

    def model(self, name):
        status, _, info = self.daemon.get_json("/v1/models/" + name)
        self.assertEqual(status, 200, info)
        return info

    # ---- 1. the demo's URL ---------------------------------------------------------------------

    def test_1_the_demo_url_shows_the_textured_model_and_the_legend(self):
        report, pixels = self.load("/viewer/?model=%s&mode=texture&merge=%s" % (PRISM, JACKSBORO),
                                   "demo")
        state = report["state"]
        self.assertEqual(state["mode"], "texture")
        self.assertGreater(state["loaded"], 1)
        self.assertEqual(state["textured"], state["loaded"], state)
        assert_not_blank(self, pixels, "demo")

        # The legend: every level of the model, named, with its resolution.
        levels = self.model(PRISM)["levels"]
        legend = state["legend"]
        self.assertEqual([e["depth"] for e in legend], [lv["depth"] for lv in levels])
        for entry, level in zip(legend, levels):
            self.assertTrue(entry["text"].startswith("depth %d: " % level["depth"]), entry)
            value, unit = entry["text"].split(": ")[1].split()
            metres = float(value) * {"km": 1000, "m": 1, "cm": 0.01, "mm": 0.001}[unit]
            self.assertAlmostEqual(metres / level["resolution"], 1, delta=0.06, msg=entry)
            # The swatch on the screen in its palette colour (sRGB, unlit HTML).
            s = entry["swatch"]
            colour = pixels[int(s["y"] + s["height"] / 2), int(s["x"] + s["width"] / 2)]
            self.assertEqual("%02x%02x%02x" % tuple(colour), entry["colour"][1:], entry)
            self.assertEqual(entry["colour"][1:], PALETTE[level["depth"]])
        # Resolutions halve per depth, and the finest is the DEM's own sample spacing (GDAL's
        # geotransform at PRISM's mean latitude; ~4.2 km).
        import math
        t = self.dem.transform
        rows = self.dem.bands.shape[1]
        mid = math.radians(t[3] + rows / 2 * t[5])
        spacing = (abs(t[1]) * math.cos(mid) + abs(t[5])) / 2 * 111320
        print("legend: %s; DEM spacing %.0f m" % ([e["text"] for e in legend], spacing),
              file=sys.stderr)
        self.assertAlmostEqual(legend[-1]["resolution"] / spacing, 1, delta=0.15)
        for coarse, fine in zip(legend, legend[1:]):
            self.assertAlmostEqual(coarse["resolution"] / fine["resolution"], 2, delta=0.2)

    # ---- 2. relief -----------------------------------------------------------------------------

    def relief_numbers(self, name, state, pixels, shade, exaggeration=1.0):
        """Screen grey (linear) vs a hillshade at the projected DEM vertices (heights times the
        exaggeration, as the page draws them)."""
        import numpy
        lon, lat, height = dem_points(self.dem)
        inside, got = screen_samples(state, pixels, lon, lat, height * exaggeration)
        self.assertGreater(len(got), 0.8 * len(lon), name)
        grey = srgb_to_linear(got.mean(axis=1))
        expected = shade.box(lon[inside], lat[inside], RELIEF_BOX)[:, 0]
        r = float(numpy.corrcoef(grey, expected)[0, 1])
        numbers = {"points": int(len(grey)), "r": round(r, 4),
                   "grey_spread": round(float(grey.std()), 5),
                   "hillshade_spread": round(float(expected.std()), 3)}
        Demo.numbers[name] = numbers
        print("%s: %s" % (name, numbers), file=sys.stderr)
        return numbers

    def test_2_relief_follows_the_sun_like_a_hillshade_and_the_height_control(self):
        work = ARGS.work
        shade = hillshade(ARGS.dem, os.path.join(work, "shade.tif"), SUN_AZIMUTH, 10)
        against = hillshade(ARGS.dem, os.path.join(work, "shade-opposite.tif"),
                            (SUN_AZIMUTH + 180) % 360, 10)
        shade4 = hillshade(ARGS.dem, os.path.join(work, "shade-z4.tif"), SUN_AZIMUTH, 4)
        lower = os.path.join(ARGS.screenshots, "relief-x4.png")
        steps = [
            {"name": "height 4", "run": "const s = document.getElementById('exaggeration');"
             " s.value = '4'; s.dispatchEvent(new Event('input'));"
             " return window.vsmViewer.exaggeration;"},
            {"name": "settled", "until": "window.vsmViewer.exaggeration === 4"},
            {"name": "screenshot", "screenshot": lower},
        ]
        report, pixels = self.load(
            "/viewer/?model=%s&mode=relief&view=top&error=1&exaggeration=10" % PRISM, "relief",
            steps)
        state = report["state"]
        self.assertEqual(state["mode"], "relief")
        self.assertEqual(state["sun"], {"azimuth": SUN_AZIMUTH, "altitude": SUN_ALTITUDE})
        print("relief: depths loaded %s" % state["depths"], file=sys.stderr)

        numbers = self.relief_numbers("relief", state, pixels, shade, exaggeration=10.0)
        self.assertGreaterEqual(numbers["r"], RELIEF_R, numbers)
        # Negative controls: the sun from the opposite side, and the hillshade mirrored
        # north-south inside PRISM's extent.
        opposite = self.relief_numbers("relief vs sun from the opposite side", state, pixels,
                                       against, exaggeration=10.0)
        self.assertLess(opposite["r"], RELIEF_R, opposite)
        t = self.dem.transform
        north, south = t[3], t[3] + self.dem.bands.shape[1] * t[5]

        class Mirrored:
            @staticmethod
            def box(lon, lat, half):
                return shade.box(lon, north + south - lat, half)

        mirrored = self.relief_numbers("relief vs hillshade mirrored north-south", state, pixels,
                                       Mirrored, exaggeration=10.0)
        self.assertLess(mirrored["r"], RELIEF_R, mirrored)

        # Height x4: the page changed, the relief holds and its contrast falls as GDAL's does.
        import numpy
        after = report["steps"][-1]["state"]
        self.assertEqual(after["exaggeration"], 4)
        self.assertEqual(after["failed"], 0, after["errors"])
        pixels4 = read_png(lower)
        model_area = ~overlay_mask(after, pixels.shape)
        diff = float(numpy.abs(pixels4.astype(float) - pixels.astype(float))[model_area].mean())
        numbers4 = self.relief_numbers("relief x4", after, pixels4, shade4, exaggeration=4.0)
        gain = numbers4["grey_spread"] / numbers["grey_spread"]
        gdal_gain = numbers4["hillshade_spread"] / numbers["hillshade_spread"]
        Demo.numbers["relief x4"].update(mean_abs_difference=round(diff, 2),
                                         gain=round(gain, 3), gdal_gain=round(gdal_gain, 3))
        print("relief x4: screenshots differ by %.2f levels; contrast x%.2f (GDAL x%.2f)"
              % (diff, gain, gdal_gain), file=sys.stderr)
        self.assertGreater(diff, EXAGGERATED_DIFF)
        self.assertGreaterEqual(numbers4["r"], RELIEF_R, numbers4)
        self.assertAlmostEqual(gain / gdal_gain, 1, delta=RELIEF_GAIN)

    # ---- 3. a merge shows without a reload -----------------------------------------------------

    def test_3_a_merge_replaces_the_tiles_over_jacksboro_without_a_reload(self):
        footprint = self.model(JACKSBORO)["bounds"]
        prism_depth = self.model(PRISM)["depth"]
        jobs_before = self.daemon.get_json("/v1/jobs")[2]
        over = ("return window.vsmViewer.shown.filter((t) => t.box && %s)"
                ".map((t) => t.depth);" % " && ".join(
                    "t.box.min[%d] <= %r && %r <= t.box.max[%d]"
                    % (i, footprint["max"][i], footprint["min"][i], i) for i in range(3)))
        steps = [
            {"name": "mark", "run": "window.vsmMark = 'no reload'; return true;"},
            {"name": "fly", "run": "document.querySelector('#fly button[data-model=\"%s\"]')"
             ".click(); return window.vsmViewer.flownTo;" % JACKSBORO},
            {"name": "flown", "until": "window.vsmViewer.flownTo === '%s'" % JACKSBORO},
            {"name": "depths before", "run": over},
            {"name": "screenshot before", "screenshot":
             os.path.join(ARGS.screenshots, "merge-before.png")},
            {"name": "merge", "run": "document.getElementById('merge-source').value = '%s';"
             " document.getElementById('merge').click(); return true;" % JACKSBORO},
            {"name": "published", "until": "window.vsmViewer.reloads >= 1 && Object.values("
             "window.vsmViewer.jobs).some((j) => j.state === 'succeeded')"},
            {"name": "depths after", "run": over},
            {"name": "mark kept", "run": "return window.vsmMark || null;"},
            {"name": "screenshot after", "screenshot":
             os.path.join(ARGS.screenshots, "merge-after.png")},
            # The revision picker: revision 1 (before the merge) is drawn again, no reload.
            {"name": "listed", "until": "window.vsmViewer.revisions.length >= 2"},
            {"name": "pick 1", "run": "const s = document.getElementById('revision');"
             " s.value = '1'; s.dispatchEvent(new Event('change'));"
             " return [...s.options].map((o) => o.value);"},
            {"name": "revision 1", "until": "window.vsmViewer.revision === 1"
             " && window.vsmViewer.reloads >= 2"},
            {"name": "depths at revision 1", "run": over},
            {"name": "mark kept at revision 1", "run": "return window.vsmMark || null;"},
            # The changes mode on the latest revision: the merge's displacement per tile.
            {"name": "pick latest", "run": "const s = document.getElementById('revision');"
             " s.value = ''; s.dispatchEvent(new Event('change')); return true;"},
            {"name": "latest", "until": "window.vsmViewer.revision === null"
             " && window.vsmViewer.reloads >= 3"},
            {"name": "changes mode", "run": "document.querySelector("
             "'input[name=mode][value=changes]').click(); return true;"},
            {"name": "changes read", "until": "window.vsmViewer.changes !== null"},
            {"name": "changes over", "run": over.replace(".map((t) => t.depth)",
                                                         ".map((t) => t.change)")},
            {"name": "changes legend", "run": "const l = document.getElementById("
             "'changes-legend'); return l.hidden ? null : l.textContent;"},
            {"name": "screenshot changes", "screenshot":
             os.path.join(ARGS.screenshots, "merge-changes.png")},
        ]
        report, _ = self.load("/viewer/?model=%s&mode=texture&view=top" % PRISM, "merge", steps)
        done = {s["name"]: s for s in report["steps"]}
        self.assertIn("screenshot after", done, report["steps"])
        before, after = done["depths before"]["value"], done["depths after"]["value"]
        final = done["screenshot after"]["state"]
        print("tiles over Jacksboro: depths %s before, %s after the merge (version %s, %d reloads)"
              % (sorted(before), sorted(after), final["version"], final["reloads"]),
              file=sys.stderr)
        self.assertEqual(done["mark kept"]["value"], "no reload")
        self.assertTrue(before and after, (before, after))
        self.assertLessEqual(max(before), prism_depth)
        self.assertGreater(min(after), max(before))
        self.assertGreater(max(after), prism_depth)
        self.assertEqual(final["failed"], 0, final["errors"])
        self.assertEqual(final["version"], self.model(PRISM)["version"])
        # Picking revision 1 draws the model as before the merge, without a reload.
        self.assertEqual(done["pick 1"]["value"], ["", "2", "1"])
        past = done["depths at revision 1"]["value"]
        print("tiles over Jacksboro at revision 1: depths %s" % sorted(past), file=sys.stderr)
        self.assertTrue(past)
        self.assertLessEqual(max(past), prism_depth)
        self.assertEqual(done["mark kept at revision 1"]["value"], "no reload")
        self.assertEqual(done["depths at revision 1"]["state"]["failed"], 0)
        # The changes mode: the diff 1 -> 2 colours the tiles over Jacksboro by metres of change.
        changes = done["changes read"]["state"]["changes"]
        over_jacksboro = done["changes over"]["value"]
        print("changes mode: %s; tiles over Jacksboro change by %s m"
              % (changes, sorted(round(v, 1) for v in over_jacksboro)), file=sys.stderr)
        self.assertEqual((changes.get("from"), changes.get("to")), (1, 2), changes)
        self.assertGreater(changes["range"], 10.0)
        self.assertTrue(over_jacksboro)
        self.assertGreater(max(abs(v) for v in over_jacksboro), 1.0)
        self.assertIn("changes 1 -> 2", done["changes legend"]["value"] or "")
        # The page's merge went through the API and succeeded there.
        jobs = [j for j in self.daemon.get_json("/v1/jobs")[2]["jobs"]
                if j not in jobs_before["jobs"] and j["type"] == "merge"]
        self.assertEqual([(j["state"], j["params"]["target"], j["params"]["source"])
                          for j in jobs], [("succeeded", PRISM, JACKSBORO)], jobs)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--build", required=True, help="the build directory (vsm, vsm-heavy)")
    parser.add_argument("--data", required=True, help="the shared data")
    parser.add_argument("--web-tools", required=True, help="prefix holding playwright-core")
    parser.add_argument("--work", required=True, help="the demo directory (emptied)")
    parser.add_argument("--screenshots", required=True, help="where the screenshots are kept")
    parser.add_argument("--chromium", default="", help="the browser (default /usr/bin/chromium)")
    ARGS, rest = parser.parse_known_args()
    ARGS.dem = os.path.join(ARGS.data, "PRISMelevation.tif")
    harness.configure(ARGS)
    browser_support.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
