#!/usr/bin/python3
"""The default texture of an import is the surface's shaded relief, checked against GDAL's:

`vsm import PRISMelevation.tif <opc> --patch-size 65` (no --texture), then, with none of vsm's
code (GDAL's Python bindings, numpy, the OPC read as docs/OPC.md says):

- the model is complete for PRo3D (check_import.check_pro3d: Images/, a Coordinates.aara and a
  texture tile per patch);
- the leaves' tiles are a hillshade of the DEM: GDAL's own (gdal.DEMProcessing "hillshade", as
  `gdaldem hillshade`: Horn's slope, azimuth 315, altitude 45, z factor 1, edges computed; the
  DEM in bands of rows with metric pixel sizes, see gdal_hillshade) at each inner DEM pixel
  against the mean of the four texels around that pixel (texel (i, j) of bottom patch (x, y)
  covers the quad between samples (64 x + i, 64 y + j) and (64 x + i + 1, 64 y + j + 1); Horn's
  gradient at a pixel is the mean of the four quads' gradients). The Pearson correlation must
  exceed MIN_CORRELATION (vsm shades on the ellipsoid, GDAL on a plane per band: close, not
  equal);
- negative controls, which must fail that threshold by far (below MAX_CONTROL): GDAL's hillshade
  mirrored east-west, and shifted by SHIFT pixels, against the same tiles; and the tiles against
  GDAL's hillshade with the sun in the south-east (azimuth 135);
- the image is where the surface is: a texel is opaque exactly where its quad has at least three
  defined DEM samples (GDAL's no-data), transparent elsewhere;
- every parent texel is the mean of the 2 x 2 child texels it covers (as image textures).

Run by ctest:  relief_test.py --vsm build/server/cli/vsm --data ../shared/data --work <dir>"""

import argparse
import math
import os
import shutil
import sys
import unittest
import xml.etree.ElementTree as ET

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from check_import import QUADRANTS, Failures, check_pro3d, read_hierarchy, read_tile  # noqa: E402

gdal.UseExceptions()

MIN_CORRELATION = 0.98
MAX_CONTROL = 0.5
SHIFT = 5


def gdal_hillshade(dem_path, azimuth, band_rows=16):
    """GDAL's hillshade of a geographic DEM (float, NaN where GDAL gives no value), with the right
    ground distances: GDAL takes one scale for both axes (111120 m per degree is right north-south
    only), so the DEM goes through in bands of `band_rows` rows (plus one overlapping row each
    side), each as a raster in metres, a degree of longitude being 111120 cos(latitude) m at the
    band's middle (within 0.1 % over a band)."""
    dem = gdal.Open(dem_path)
    gt = dem.GetGeoTransform()
    source = dem.GetRasterBand(1)
    nodata = source.GetNoDataValue()
    heights = source.ReadAsArray().astype(np.float32)
    rows, cols = heights.shape
    shade = np.full((rows, cols), np.nan)
    for r0 in range(0, rows, band_rows):
        a, b = max(0, r0 - 1), min(rows, r0 + band_rows + 1)
        lat = gt[3] + (r0 + band_rows / 2) * gt[5]
        metres = gdal.GetDriverByName("MEM").Create("", cols, b - a, 1, gdal.GDT_Float32)
        metres.SetGeoTransform((0, 111120 * math.cos(math.radians(lat)) * gt[1], 0, 0, 0,
                                111120 * gt[5]))
        band = metres.GetRasterBand(1)
        if nodata is not None:
            band.SetNoDataValue(nodata)
        band.WriteArray(heights[a:b])
        out = gdal.DEMProcessing("", metres, "hillshade", format="MEM", azimuth=azimuth,
                                 altitude=45, zFactor=1, scale=1, computeEdges=True)
        result = out.GetRasterBand(1)
        values = result.ReadAsArray().astype(float)
        if result.GetNoDataValue() is not None:
            values[values == result.GetNoDataValue()] = np.nan
        shade[r0:min(rows, r0 + band_rows)] = values[r0 - a:r0 - a + min(band_rows, rows - r0)]
    return shade


def leaves_and_tiles(opc):
    """{(depth, x, y): tile (bands, rows, cols)} and the children of each key, by quadrant."""
    patches_dir, root, children = read_hierarchy(opc)
    tiles, kids = {}, {}
    stack = [(root, (0, 0, 0))]
    while stack:
        folder, key = stack.pop()
        patch = ET.parse(os.path.join(patches_dir, folder, "Patch.xml")).getroot().find("Patch")
        entry = patch.find("Textures")[0].text.strip().replace("\\", "/")
        tiles[key] = read_tile(os.path.join(opc, "Images", entry))
        kids[key] = {}
        for q, child in children.get(folder, {}).items():
            qx, qy = QUADRANTS[q]
            child_key = (key[0] + 1, 2 * key[1] + qx, 2 * key[2] + qy)
            kids[key][q] = child_key
            stack.append((child, child_key))
    return tiles, kids


ARGS = None


class Relief(unittest.TestCase):
    def test_leaf_tiles_are_the_dems_hillshade(self):
        """PRISM's default texture against GDAL's hillshade, with negative controls; parents as
        2 x 2 means."""
        dem_path = os.path.join(ARGS.data, "PRISMelevation.tif")
        opc = os.path.join(ARGS.work, "prism-relief")
        shutil.rmtree(ARGS.work, ignore_errors=True)
        os.makedirs(ARGS.work)
        n = 65
        size = n - 1
        harness.import_dem(dem_path, opc, n)

        failures = Failures()
        checked = check_pro3d(opc, failures)

        heights, _ = harness.read_raster(dem_path)
        defined = (~np.isnan(heights)).astype(float)
        reference = gdal_hillshade(dem_path, 315)
        controls = {"mirrored east-west": reference[:, ::-1],
                    "shifted %d pixels" % SHIFT: np.roll(reference, (SHIFT, SHIFT), axis=(0, 1)),
                    "sun in the south-east": gdal_hillshade(dem_path, 135)}

        tiles, kids = leaves_and_tiles(opc)
        depth = max(key[0] for key in tiles)
        # The leaves' texels as one mosaic: texel (i, j) of leaf (x, y) is quad (64 x + i, 64 y + j)
        # of the DEM, the quad between samples (c, r) and (c + 1, r + 1) (NaN: transparent).
        rows, cols = heights.shape
        grey = np.full((rows - 1, cols - 1), np.nan)
        alpha = np.zeros((rows - 1, cols - 1))
        for key, tile in tiles.items():
            if kids[key]:
                continue
            if key[0] != depth:
                failures.add("leaf %s is not at the bottom depth %d" % (key, depth))
                continue
            if not (np.array_equal(tile[0], tile[1]) and np.array_equal(tile[0], tile[2])):
                failures.add("leaf %s: the relief is not grey" % (key,))
            if np.any((tile[3] != 0) & (tile[3] != 255)):
                failures.add("leaf %s: alpha other than 0 and 255" % (key,))
            x0, y0 = key[1] * size, key[2] * size
            h, w = min(size, rows - 1 - y0), min(size, cols - 1 - x0)
            if h <= 0 or w <= 0:
                continue
            alpha[y0:y0 + h, x0:x0 + w] = tile[3, :h, :w]
            grey[y0:y0 + h, x0:x0 + w] = np.where(tile[3, :h, :w] == 255, tile[0, :h, :w], np.nan)

        # The image is where the surface is: a quad with three or four defined corners is shaded.
        corners = defined[:-1, :-1] + defined[:-1, 1:] + defined[1:, :-1] + defined[1:, 1:]
        wrong = int(np.count_nonzero((alpha == 255) != (corners >= 3)))
        if wrong:
            failures.add("%d leaf texels are opaque where the DEM has no surface or transparent where "
                         "it has" % wrong)

        # At each inner DEM pixel: the mean of the four texels around it against GDAL's value there.
        # Horn's gradient (GDAL's) at a pixel is exactly the mean of the gradients of the four quads
        # around it (each taken across its mid-lines, as vsm does), so the two agree up to the
        # shading's non-linearity and the ellipsoid; a single texel against GDAL's smoother value
        # correlates only about 0.84 on this rough 4 km DEM.
        around = (grey[:-1, :-1] + grey[:-1, 1:] + grey[1:, :-1] + grey[1:, 1:]) / 4
        inner = reference[1:-1, 1:-1]
        use = ~np.isnan(around) & ~np.isnan(inner)
        got, expected = around[use], inner[use]
        correlation = float(np.corrcoef(got, expected)[0, 1])
        if not correlation > MIN_CORRELATION:
            failures.add("correlation with GDAL's hillshade %.3f, not above %.2f" %
                         (correlation, MIN_CORRELATION))
        control_text = []
        for name, control in controls.items():
            values = control[1:-1, 1:-1][use]
            values = np.where(np.isnan(values), np.nanmean(control), values)
            c = float(np.corrcoef(got, values)[0, 1])
            control_text.append("%s %.3f" % (name, c))
            if not c < MAX_CONTROL:
                failures.add("negative control (%s) correlates %.3f: the check cannot tell" % (name, c))

        parent_quadrants = 0
        half = size // 2
        for key, quadrants in kids.items():
            for q, child in quadrants.items():
                qx, qy = QUADRANTS[q]
                c = tiles[child]
                mean = (c[:, 0::2, 0::2] + c[:, 0::2, 1::2] + c[:, 1::2, 0::2] + c[:, 1::2, 1::2]) / 4
                part = tiles[key][:, qy * half:(qy + 1) * half, qx * half:(qx + 1) * half]
                if np.any(np.abs(part - mean) > 0.5 + 1e-9):
                    failures.add("parent %s, quadrant %s: not the mean of its child's texels" % (key, q))
                parent_quadrants += 1

        summary = ("relief: %d patches complete for PRo3D, %d DEM pixels, correlation with GDAL's "
                   "hillshade %.3f (> %.2f); controls %s (< %.2f); %d parent quadrants exact" %
                   (checked, got.size, correlation, MIN_CORRELATION, ", ".join(control_text),
                    MAX_CONTROL, parent_quadrants))
        failures.assert_none(self, summary)


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
