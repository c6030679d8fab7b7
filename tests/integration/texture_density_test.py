#!/usr/bin/python3
"""Imagery at its own resolution (issue 28), judged from the stored tiles alone by
texel_density.py (GDAL and the import checker's OPC reader; none of vsm's code):

(a) import: a crop of PRISM with the NASA image 3 and 4 times finer (texel_density.make_pair; 3x
    is not aligned with the texels, 4x is): density >= 0.8 texel per image pixel and high-pass
    correlation >= 0.75;
(b) the control: the 4x pair imported with --texels-per-quad 1 (the layout before) fails both, so
    the checker can fail;
(c) a merge of two textured models, each side of the seam on its own: A = the PRISM crop with its
    image 2x finer, B = Jacksboro (3") with its own image 2x finer than B. In the merged model A's
    leaves outside B (B's box and a margin left out) against A's image, and the deepest leaves
    (B's area) against B's image, each with density >= 0.8 and r >= 0.75; the control, B imported
    at one texel per quad, fails the correlation on B's side;
(d) memory: an import with tiles of 4096 texels (--texels-per-quad 16, 64 MiB a tile) peaks below
    TILE_BOUND tiles' worth of RSS.

Run by ctest:  texture_density_test.py --vsm build/server/cli/vsm --data ../shared/data --work <dir>
"""

import argparse
import os
import subprocess
import shutil
import sys
import unittest

from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from texel_density import leaves_by_key, make_pair, measure  # noqa: E402

gdal.UseExceptions()

N = 65
WINDOW = (-90.0, 39.0, -82.0, 33.0)  # a crop of PRISM around Jacksboro (-84.2 E, 36.4 N)
TILE_BOUND = 10  # LargeTiles: peak RSS in 4096-texel RGBA tiles (seen: 7)
DENSITY = 0.8
CORRELATION = 0.75
ARGS = None


class TextureDensity(unittest.TestCase):
    def setUp(self):
        shutil.rmtree(ARGS.work, ignore_errors=True)
        os.makedirs(ARGS.work)
        self.prism = os.path.join(ARGS.data, "PRISMelevation.tif")
        self.nasa = os.path.join(ARGS.data, "conus_visible_earth.tif")

    def assert_keeps(self, what, m):
        print("%s: %s" % (what, m), flush=True)
        self.assertGreaterEqual(m.density, DENSITY, what)
        self.assertGreaterEqual(m.r, CORRELATION, what)

    def test_import_keeps_the_images_resolution(self):
        for factor in (3, 4):
            dem, image = make_pair(self.prism, self.nasa, ARGS.work, "prism", factor, WINDOW)
            opc = os.path.join(ARGS.work, "model-%d" % factor)
            harness.import_dem(dem, opc, N, "--texture", image)
            harness.vsm("validate", opc, check=True)
            self.assert_keeps("import, image %dx finer" % factor, measure(opc, dem, image, N))
        # (b) The control.
        opc = os.path.join(ARGS.work, "model-4-one-per-quad")
        harness.import_dem(dem, opc, N, "--texture", image, "--texels-per-quad", "1")
        m = measure(opc, dem, image, N)
        print("control, one texel per quad: %s" % m, flush=True)
        self.assertLess(m.density, DENSITY)
        self.assertLess(m.r, CORRELATION)

    def test_a_merge_keeps_each_sides_resolution(self):
        dem_a, image_a = make_pair(self.prism, self.nasa, ARGS.work, "prism", 2, WINDOW)
        dem_b, image_b = make_pair(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), self.nasa,
                                   ARGS.work, "jacksboro", 2)
        a, b, merged = (os.path.join(ARGS.work, name) for name in ("a", "b", "merged"))
        harness.import_dem(dem_a, a, N, "--texture", image_a)
        harness.import_dem(dem_b, b, N, "--texture", image_b)
        harness.vsm("merge", a, b, "--out", merged, check=True)
        harness.vsm("validate", merged, check=True)
        a_depth = max(k[0] for k in leaves_by_key(a))
        deepest = max(k[0] for k in leaves_by_key(merged))
        self.assertGreater(deepest, a_depth)
        gt = gdal.Open(dem_b).GetGeoTransform()
        ds = gdal.Open(dem_b)
        margin = 3 * gdal.Open(dem_a).GetGeoTransform()[1]  # three of A's samples
        b_box = (gt[0] - margin, gt[3] + margin, gt[0] + ds.RasterXSize * gt[1] + margin,
                 gt[3] + ds.RasterYSize * gt[5] - margin)
        self.assert_keeps("merge, A's side", measure(merged, dem_a, image_a, N, depth=a_depth,
                                                     exclude=b_box))
        self.assert_keeps("merge, B's side", measure(merged, dem_a, image_b, N, depth=deepest,
                                                     levels=deepest - a_depth))
        # The control: B at one texel per quad. The merged tiles have A's two texels per quad,
        # but B's side holds B's coarser texels: its detail is lost, and the check sees it.
        coarse_b, coarse = (os.path.join(ARGS.work, name) for name in ("b1", "merged-b1"))
        harness.import_dem(dem_b, coarse_b, N, "--texture", image_b, "--texels-per-quad", "1")
        harness.vsm("merge", a, coarse_b, "--out", coarse, check=True)
        m = measure(coarse, dem_a, image_b, N, depth=deepest, levels=deepest - a_depth)
        print("control, B at one texel per quad: %s" % m, flush=True)
        self.assertLess(m.r, CORRELATION)


class LargeTiles(unittest.TestCase):
    def test_an_import_with_the_largest_tiles_holds_a_few_of_them(self):
        """Tiles of 4096 texels (64 MiB each in memory) stream through the import: a 513 x 513 crop
        of PRISM at --texels-per-quad 16 (four leaves and the root) peaks below TILE_BOUND tiles'
        worth (before the tiles streamed, the coordinates of one tile alone were 268 MB a worker)."""
        work = os.path.join(ARGS.work, "large-tiles")
        shutil.rmtree(work, ignore_errors=True)
        os.makedirs(work)
        dem = os.path.join(work, "dem.tif")
        gdal.Translate(dem, os.path.join(ARGS.data, "PRISMelevation.tif"),
                       srcWin=[300, 100, 513, 513])
        opc = os.path.join(work, "model")
        # This import's own peak (wait4: its rusage alone; vsm execs vsm-heavy in place).
        log = os.path.join(work, "import.log")
        with open(log, "w") as stderr:
            process = subprocess.Popen(
                [harness.VSM, "import", dem, opc, "--patch-size", "257", "--texture",
                 os.path.join(ARGS.data, "conus_visible_earth.tif"), "--texels-per-quad", "16"],
                stdout=subprocess.DEVNULL, stderr=stderr)
            try:
                _, status, usage = os.wait4(process.pid, 0)
            finally:
                process.returncode = 0  # reaped above: Popen must not wait for it again
        with open(log) as f:
            self.assertEqual(os.waitstatus_to_exitcode(status), 0, f.read()[-2000:])
        peak = usage.ru_maxrss  # KiB
        tiles = sorted(os.listdir(os.path.join(opc, "Images", "Diffuse")))
        self.assertEqual(len(tiles), 5, tiles)
        self.assertEqual(gdal.Open(os.path.join(opc, "Images", "Diffuse", tiles[0])).RasterXSize,
                         4096)
        print("import with 4096-texel tiles: peak RSS %.0f MB" % (peak / 1024), flush=True)
        self.assertLess(peak * 1024, TILE_BOUND * 4096 * 4096 * 4)
        harness.vsm("validate", opc, check=True)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
