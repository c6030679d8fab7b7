#!/usr/bin/python3
"""`vsm render-lod` on the real merged model (PRISM with Jacksboro, 65 x 65: the `tiles.prepare`
fixture), checked by reading the PNG through GDAL's PNG driver (georeferenced by the .pgw world file
render-lod writes) and the Jacksboro raster's own extent through GDAL:

- only palette colours (core/tiles/README.md, copied here) and transparency occur;
- PRISM alone shows its single bottom depth (5) everywhere;
- merged, deeper depths occur, the deepest one covers Jacksboro's area and only it (plus the
  patches the merge refined along its edge), every depth deeper than PRISM's lies within one PRISM
  bottom patch of Jacksboro, and depth grows towards Jacksboro.

The pictures stay in the work directory (CI artefacts). Run by ctest:
    render_lod_test.py --vsm build/server/cli/vsm --work build/.../tiles --data ../shared/data"""

import argparse
import os
import sys
import unittest

from osgeo import gdal
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402

gdal.UseExceptions()
ARGS = None

# kDepthPalette (core/tiles/lod_render.hpp), as documented in core/tiles/README.md.
PALETTE = ["30123b", "4145ab", "4675ed", "39a2fc", "1bcfd4", "24eca6", "61fc6c", "a4fc3b",
           "d1e834", "f3c63a", "fe9b2d", "f36315", "d93806", "b11901", "7a0402", "4a0000"]
PRISM_DEPTH = 5  # 1405 x 621 cells in 64-cell patches: 32 x 32 bottom patches, depth 5
# One PRISM bottom patch: 64 cells of 2.5 arc-minutes.
PRISM_PATCH_DEGREES = 64 * 2.5 / 60


def render(opc, out, size):
    """`vsm render-lod opc out --size size`, which must succeed: its output."""
    return harness.vsm("render-lod", opc, out, "--size", size, check=True, timeout=300).stdout


def depth_map(png):
    """(depth per pixel, -1 where transparent; geotransform) of a render-lod picture."""
    ds = gdal.Open(png)
    assert ds.GetDriver().ShortName == "PNG"
    assert ds.RasterCount == 4
    rgba = ds.ReadAsArray().astype(np.int64)  # bands x rows x cols
    gt = ds.GetGeoTransform()
    assert gt != (0, 1, 0, 0, 0, 1), "no world file read"
    code = (rgba[0] << 16) | (rgba[1] << 8) | rgba[2]
    depth = np.full(code.shape, -2, dtype=np.int64)
    depth[rgba[3] == 0] = -1
    for d, colour in enumerate(PALETTE):
        depth[(rgba[3] == 255) & (code == int(colour, 16))] = d
    assert not (depth == -2).any(), "colours outside the palette or partial alpha"
    return depth, gt


def pixel_centres(depth, gt):
    cols, rows = np.meshgrid(np.arange(depth.shape[1]), np.arange(depth.shape[0]))
    lon = gt[0] + (cols + 0.5) * gt[1]
    lat = gt[3] + (rows + 0.5) * gt[5]
    return lon, lat


def raster_extent(path):
    ds = gdal.Open(path)
    gt = ds.GetGeoTransform()
    lon0, lat1 = gt[0], gt[3]
    lon1 = lon0 + ds.RasterXSize * gt[1]
    lat0 = lat1 + ds.RasterYSize * gt[5]
    return lon0, lon1, lat0, lat1


class RenderLod(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.jack = raster_extent(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"))
        cls.merged_png = os.path.join(ARGS.work, "render-lod-merged.png")
        cls.stdout = render(os.path.join(ARGS.work, "merged"), cls.merged_png, 4096)
        cls.depth, cls.gt = depth_map(cls.merged_png)
        cls.lon, cls.lat = pixel_centres(cls.depth, cls.gt)

    def test_prism_alone_shows_one_depth(self):
        png = os.path.join(ARGS.work, "render-lod-prism.png")
        render(os.path.join(ARGS.work, "prism"), png, 1024)
        depth, gt = depth_map(png)
        self.assertEqual(set(np.unique(depth)) - {-1}, {PRISM_DEPTH})
        # Georeferenced to PRISM's extent (pixel centres of the raster, within a pixel).
        lon0, lon1, lat0, lat1 = raster_extent(os.path.join(ARGS.data, "PRISMelevation.tif"))
        self.assertAlmostEqual(gt[0], lon0, delta=abs(gt[1]) + 0.05)
        self.assertAlmostEqual(gt[3], lat1, delta=abs(gt[5]) + 0.05)

    def test_deeper_depths_occur(self):
        depths = set(np.unique(self.depth)) - {-1}
        self.assertIn(PRISM_DEPTH, depths)
        self.assertGreater(max(depths), PRISM_DEPTH + 3, depths)
        print("\n" + self.stdout, file=sys.stderr)

    def test_deepest_depth_covers_jacksboro_and_only_it(self):
        lon0, lon1, lat0, lat1 = self.jack
        deepest = self.depth.max()
        mask = self.depth == deepest
        # Inside Jacksboro's extent (pixel centres at least a pixel from its edge): all deepest.
        px, py = abs(self.gt[1]), abs(self.gt[5])
        core = ((self.lon > lon0 + px) & (self.lon < lon1 - px) & (self.lat > lat0 + py)
                & (self.lat < lat1 - py))
        self.assertGreater(core.sum(), 100)
        self.assertEqual(int((self.depth[core] != deepest).sum()), 0)
        # Outside it only near its edge: the merge refines every new bottom patch whose ECEF box
        # meets Jacksboro's, which in lon/lat reaches up to about two of them past the raster's
        # edge. A depth-11 patch is one PRISM cell (2.5' split into 64 vertex steps 6 levels down):
        # allow three, and a pixel.
        margin = 3 * 2.5 / 60
        near = ((self.lon > lon0 - margin - px) & (self.lon < lon1 + margin + px)
                & (self.lat > lat0 - margin - py) & (self.lat < lat1 + margin + py))
        self.assertEqual(int((mask & ~near).sum()), 0)

    def test_every_deeper_depth_lies_near_jacksboro_and_grows_towards_it(self):
        lon0, lon1, lat0, lat1 = self.jack
        deeper = self.depth > PRISM_DEPTH
        margin = PRISM_PATCH_DEGREES
        near = ((self.lon > lon0 - margin) & (self.lon < lon1 + margin)
                & (self.lat > lat0 - margin) & (self.lat < lat1 + margin))
        self.assertEqual(int((deeper & ~near).sum()), 0)
        self.assertLess(deeper.sum(), 0.01 * (self.depth >= 0).sum())
        # Mean distance (degrees) from Jacksboro's centre falls with depth.
        centre = ((lon0 + lon1) / 2, (lat0 + lat1) / 2)
        distance = np.hypot(self.lon - centre[0], self.lat - centre[1])
        means = [distance[self.depth == d].mean() for d in range(PRISM_DEPTH, self.depth.max() + 1)
                 if (self.depth == d).any()]
        self.assertEqual(means, sorted(means, reverse=True), means)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--work", required=True, help="holds prism/ and merged/ (tiles.prepare)")
    parser.add_argument("--data", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
