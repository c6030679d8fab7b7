#!/usr/bin/python3
"""Issue 28's measure (not a test): how much of a draped image's detail a textured model keeps,
judged from the stored tiles alone, without vsm's code.

    /usr/bin/python3 tests/bench/texture_density.py --vsm build/server/cli/vsm \\
        --data ../shared/data --work /tmp/texture-density [--factors 1,2,4] [--patch-size 65]

The pair, for each factor F: the DEM is a crop of PRISM (2.5', -90..-82 E, 33..39 N); the image is
the bundled NASA image warped by GDAL (cubic) onto the same area at 1/F of the DEM's spacing, with
a fixed-seed texture of +-40 per channel added per pixel so that it has detail at its own scale
(the NASA image alone is 19 km a pixel, smooth at these scales). The image covers the DEM's grid
quads, from its first sample centre to its last, so that at F = 1 a pixel is a quad. `vsm import
dem model --texture image --patch-size N` makes the model; then, with GDAL's Python bindings and
the import checker's OPC reader (tests/integration/check_import.py) only:
- the leaves' tiles are laid out as one mosaic (a leaf's key from its place in the hierarchy;
  texel (i, j) of leaf (x, y) with tiles of T texels covers DEM sample coordinates
  x * (N - 1) + (i + 0.5) * (N - 1) / T);
- density: opaque texels over the DEM's area per image pixel over the same area;
- high-pass correlation: the mosaic sampled bilinearly at every image pixel's centre, both
  reduced to luminance minus its 5 x 5 box mean, Pearson's r over the pixels the tiles cover.
Issue 28 asks for density >= 0.8 and r >= 0.75; one texel per grid quad gives 1/F^2 and less.

Prints one line per factor."""

import argparse
import os
import shutil
import subprocess
import sys

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "integration"))
from check_import import Failures, read_hierarchy, walk  # noqa: E402
from harness import bilinear  # noqa: E402

gdal.UseExceptions()

WINDOW = (-90.0, 39.0, -82.0, 33.0)  # west, north, east, south


def make_pair(data, work, factor):
    """(dem, image) GeoTIFFs of the same area, the image `factor` times finer."""
    dem = os.path.join(work, "dem.tif")
    if not os.path.exists(dem):
        gdal.Translate(dem, os.path.join(data, "PRISMelevation.tif"), projWin=list(WINDOW))
    ds = gdal.Open(dem)
    gt = ds.GetGeoTransform()
    smooth = os.path.join(work, "image-%d-smooth.tif" % factor)
    # The quads' area: the first sample's centre to the last's (west, south, east, north).
    gdal.Warp(smooth, os.path.join(data, "conus_visible_earth.tif"),
              outputBounds=(gt[0] + 0.5 * gt[1], gt[3] + (ds.RasterYSize - 0.5) * gt[5],
                            gt[0] + (ds.RasterXSize - 0.5) * gt[1], gt[3] + 0.5 * gt[5]),
              xRes=gt[1] / factor, yRes=-gt[5] / factor, resampleAlg="cubic")
    src = gdal.Open(smooth)
    rgb = src.ReadAsArray().astype(np.int16)[:3]
    rng = np.random.default_rng(28)
    detail = rng.integers(-40, 41, size=rgb.shape[1:], dtype=np.int16)
    rgb = np.clip(rgb + detail[None, :, :], 0, 255).astype(np.uint8)
    image = os.path.join(work, "image-%d.tif" % factor)
    out = gdal.GetDriverByName("GTiff").Create(image, src.RasterXSize, src.RasterYSize, 3,
                                                gdal.GDT_Byte)
    out.SetGeoTransform(src.GetGeoTransform())
    out.SetProjection(src.GetProjection())
    for b in range(3):
        out.GetRasterBand(b + 1).WriteArray(rgb[b])
    out = None
    return dem, image


def leaves_by_key(opc):
    """{(depth, x, y): folder} of the leaves, keys from their places in the hierarchy (the
    import checker's walk, which also checks each patch's files)."""
    patches, root, children = read_hierarchy(opc)
    failures = Failures()
    walked = walk(patches, root, children, failures)
    if failures.count:
        sys.exit("%s: %s" % (opc, "; ".join(failures.items)))
    return {key: patch.folder for key, patch in walked.items() if patch.folder not in children}


def box_mean(a, k):
    """The k x k box mean of `a` (edges: the mean of what the box holds)."""
    pad = k // 2
    padded = np.pad(a, pad, mode="edge")
    c = np.cumsum(np.cumsum(padded, axis=0), axis=1)
    c = np.pad(c, ((1, 0), (1, 0)))
    s = c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]
    return s / (k * k)


def luminance(rgb):
    return 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]


def measure(opc, dem_path, image_path, n):
    leaves = leaves_by_key(opc)
    depth = max(k[0] for k in leaves)
    deepest = {k: f for k, f in leaves.items() if k[0] == depth}
    first = gdal.Open(os.path.join(opc, "Images", "Diffuse", next(iter(deepest.values())) + ".tif"))
    tile = first.RasterXSize
    per_quad = tile / (n - 1)  # texels per DEM quad, a side
    side = 1 << depth
    mosaic = np.zeros((4, side * tile, side * tile))
    for (_, x, y), folder in deepest.items():
        t = gdal.Open(os.path.join(opc, "Images", "Diffuse", folder + ".tif")).ReadAsArray()
        t = t.astype(float)
        if t.shape[0] == 3:
            t = np.concatenate([t, np.full((1,) + t.shape[1:], 255.0)])
        mosaic[:, y * tile:(y + 1) * tile, x * tile:(x + 1) * tile] = t
    dem = gdal.Open(dem_path)
    dgt = dem.GetGeoTransform()
    img = gdal.Open(image_path)
    igt = img.GetGeoTransform()
    image = img.ReadAsArray().astype(float)
    # Image pixel centres -> DEM sample coordinates (sample centres at lon = w + (s + 0.5) * dx)
    # -> the mosaic's pixel-edge coordinates (harness.bilinear's): a DEM quad is per_quad texels.
    cols = np.arange(img.RasterXSize)
    rows = np.arange(img.RasterYSize)
    lon = igt[0] + (cols + 0.5) * igt[1]
    lat = igt[3] + (rows + 0.5) * igt[5]
    sx = (lon - dgt[0]) / dgt[1] - 0.5
    sy = (lat - dgt[3]) / dgt[5] - 0.5
    inside_x = (sx >= 0) & (sx <= dem.RasterXSize - 1)
    inside_y = (sy >= 0) & (sy <= dem.RasterYSize - 1)
    gx, gy = np.meshgrid(sx * per_quad, sy * per_quad)
    sampled = bilinear(mosaic, gx, gy)
    covered = (sampled[3] > 254) & inside_y[:, None] & inside_x[None, :]
    # Density: opaque texels over the DEM's area per image pixel over it.
    quads_x, quads_y = dem.RasterXSize - 1, dem.RasterYSize - 1
    area = mosaic[3, :int(quads_y * per_quad), :int(quads_x * per_quad)]
    texels = int(np.count_nonzero(area > 0))
    pixels = quads_x * abs(dgt[1] / igt[1]) * quads_y * abs(dgt[5] / igt[5])
    hp_image = luminance(image) - box_mean(luminance(image), 5)
    hp_tiles = luminance(sampled) - box_mean(luminance(sampled), 5)
    # Away from the edges of what is covered, where the box mean mixes in what is not.
    core = box_mean(covered.astype(float), 5) > 0.999
    r = float(np.corrcoef(hp_image[core], hp_tiles[core])[0, 1])
    return tile, per_quad, texels / pixels, r, int(np.count_nonzero(core))


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--factors", default="1,2,4")
    parser.add_argument("--patch-size", type=int, default=65)
    args = parser.parse_args()
    shutil.rmtree(args.work, ignore_errors=True)
    os.makedirs(args.work)
    for factor in [int(f) for f in args.factors.split(",")]:
        dem, image = make_pair(args.data, args.work, factor)
        opc = os.path.join(args.work, "model-%d" % factor)
        subprocess.run([args.vsm, "import", dem, opc, "--patch-size", str(args.patch_size),
                        "--texture", image], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, timeout=600)
        tile, per_quad, density, r, pixels = measure(opc, dem, image, args.patch_size)
        print("image %dx finer than the DEM: tiles of %d texels (%.2f a grid quad), density "
              "%.3f texel per image pixel, high-pass r %.3f over %d pixels"
              % (factor, tile, per_quad, density, r, pixels), flush=True)


if __name__ == "__main__":
    main()
