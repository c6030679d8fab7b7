"""How much of a draped image's detail a textured model keeps, judged from the stored tiles alone,
without vsm's code (issue 28): the measure of tests/bench/texture_density.py and of
texture_density_test.py.

An image pair: a DEM (a crop of a real one) and an image of the same place `factor` times finer,
the bundled NASA image warped by GDAL (cubic) with a fixed-seed texture of +-40 per channel added
per pixel, so that it has detail at its own scale (the NASA image alone is 19 km a pixel, smooth at
these scales). The image covers the DEM's grid quads, from its first sample centre to its last, so
that at factor 1 a pixel is a quad.

measure() lays the tiles of the leaves at one depth out as one mosaic (a leaf's key from its place
in the hierarchy, by the import checker's walk; texel (i, j) of leaf (x, y) at `levels` below the
DEM's own leaves, tiles of T texels, covers DEM sample coordinates
(x (N - 1) + (i + 0.5) (N - 1) / T) / 2^levels), then reports
- density: opaque texels per image pixel over the same area;
- high-pass correlation: the mosaic sampled bilinearly at every image pixel's centre, both reduced
  to luminance minus its 5 x 5 box mean, Pearson's r over the pixels the tiles cover.
Issue 28 asks for density >= 0.8 and r >= 0.75; one texel per grid quad gives 1/factor^2 and less.
"""

import os
import sys

import numpy as np
from osgeo import gdal

from check_import import Failures, read_hierarchy, read_tile, walk
from harness import bilinear

gdal.UseExceptions()


def make_pair(dem_source, image_source, work, name, factor, window=None):
    """(dem, image) GeoTIFFs of the same area under `work`: `dem_source` cropped to `window`
    (west, north, east, south; None: whole), the image warped from `image_source` `factor` times
    finer, plus the texture."""
    dem = os.path.join(work, name + "-dem.tif")
    if not os.path.exists(dem):
        if window is None:
            gdal.Translate(dem, dem_source)
        else:
            gdal.Translate(dem, dem_source, projWin=list(window))
    ds = gdal.Open(dem)
    gt = ds.GetGeoTransform()
    smooth = os.path.join(work, "%s-image-%g-smooth.tif" % (name, factor))
    # The quads' area: the first sample's centre to the last's (west, south, east, north).
    gdal.Warp(smooth, image_source,
              outputBounds=(gt[0] + 0.5 * gt[1], gt[3] + (ds.RasterYSize - 0.5) * gt[5],
                            gt[0] + (ds.RasterXSize - 0.5) * gt[1], gt[3] + 0.5 * gt[5]),
              xRes=gt[1] / factor, yRes=-gt[5] / factor, resampleAlg="cubic")
    src = gdal.Open(smooth)
    rgb = src.ReadAsArray().astype(np.int16)[:3]
    rng = np.random.default_rng(28)
    detail = rng.integers(-40, 41, size=rgb.shape[1:], dtype=np.int16)
    rgb = np.clip(rgb + detail[None, :, :], 0, 255).astype(np.uint8)
    image = os.path.join(work, "%s-image-%g.tif" % (name, factor))
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


class Measure:
    def __init__(self, tile, per_quad, density, r, pixels):
        self.tile, self.per_quad, self.density, self.r, self.pixels = (
            tile, per_quad, density, r, pixels)

    def __str__(self):
        return ("tiles of %d texels (%.2f a grid quad), density %.3f texel per image pixel, "
                "high-pass r %.3f over %d pixels"
                % (self.tile, self.per_quad, self.density, self.r, self.pixels))


def measure(opc, dem_path, image_path, n, depth=None, levels=0, exclude=None):
    """The Measure of `image_path` in the tiles of the leaves at `depth` (None: the deepest) of
    `opc`, imported from `dem_path` with patch size `n` and then, where `levels` > 0, merged with
    detail that put those leaves `levels` below the DEM's own. Pixels whose centres fall in
    `exclude` (west, north, east, south) count for neither side."""
    leaves = leaves_by_key(opc)
    depth = max(k[0] for k in leaves) if depth is None else depth
    chosen = {k: f for k, f in leaves.items() if k[0] == depth}
    tile = gdal.Open(os.path.join(opc, "Images", "Diffuse",
                                  next(iter(chosen.values())) + ".tif")).RasterXSize
    scale = 1 << levels
    per_quad = tile / (n - 1)  # texels per quad of the leaves, a side
    # The mosaic spans the chosen leaves' keys only.
    x0 = min(k[1] for k in chosen)
    y0 = min(k[2] for k in chosen)
    cols = max(k[1] for k in chosen) - x0 + 1
    rows = max(k[2] for k in chosen) - y0 + 1
    mosaic = np.zeros((4, rows * tile, cols * tile))
    for (_, x, y), folder in chosen.items():
        t = read_tile(os.path.join(opc, "Images", "Diffuse", folder + ".tif"))
        if t.shape[1] != tile:
            sys.exit("%s: leaves at depth %d with tiles of %d and %d texels" %
                     (opc, depth, tile, t.shape[1]))
        mosaic[:, (y - y0) * tile:(y - y0 + 1) * tile, (x - x0) * tile:(x - x0 + 1) * tile] = t
    dem = gdal.Open(dem_path)
    dgt = dem.GetGeoTransform()
    img = gdal.Open(image_path)
    igt = img.GetGeoTransform()
    image = img.ReadAsArray().astype(float)[:3]
    # DEM sample coordinate s (centres at lon = w + (s + 0.5) dx) <-> the mosaic's pixel-edge
    # coordinate m = (s scale - origin (N - 1)) per_quad.
    to_mosaic_x = lambda s: (s * scale - x0 * (n - 1)) * per_quad  # noqa: E731
    to_mosaic_y = lambda s: (s * scale - y0 * (n - 1)) * per_quad  # noqa: E731
    lon = igt[0] + (np.arange(img.RasterXSize) + 0.5) * igt[1]
    lat = igt[3] + (np.arange(img.RasterYSize) + 0.5) * igt[5]
    sx = (lon - dgt[0]) / dgt[1] - 0.5
    sy = (lat - dgt[3]) / dgt[5] - 0.5
    gx, gy = np.meshgrid(to_mosaic_x(sx), to_mosaic_y(sy))
    sampled = bilinear(mosaic, gx, gy)
    inside_x = (sx >= 0) & (sx <= dem.RasterXSize - 1)
    inside_y = (sy >= 0) & (sy <= dem.RasterYSize - 1)
    covered = (sampled[3] > 254) & inside_y[:, None] & inside_x[None, :]
    # Texel centres in lon/lat, for the density's texels: opaque, inside the image, not excluded.
    ts_x = ((np.arange(cols * tile) + 0.5) / per_quad + x0 * (n - 1)) / scale
    ts_y = ((np.arange(rows * tile) + 0.5) / per_quad + y0 * (n - 1)) / scale
    t_lon = dgt[0] + (ts_x + 0.5) * dgt[1]
    t_lat = dgt[3] + (ts_y + 0.5) * dgt[5]
    west, east = igt[0], igt[0] + img.RasterXSize * igt[1]
    north, south = igt[3], igt[3] + img.RasterYSize * igt[5]
    texel_in = ((t_lat < north) & (t_lat > south))[:, None] & \
        ((t_lon > west) & (t_lon < east))[None, :] & (mosaic[3] > 0)
    if exclude is not None:
        ew, en, ee, es = exclude
        covered &= ~(((lat < en) & (lat > es))[:, None] & ((lon > ew) & (lon < ee))[None, :])
        texel_in &= ~(((t_lat < en) & (t_lat > es))[:, None] & ((t_lon > ew) & (t_lon < ee))[None, :])
    texels = int(np.count_nonzero(texel_in))
    pixels = int(np.count_nonzero(covered))
    hp_image = luminance(image) - box_mean(luminance(image), 5)
    hp_tiles = luminance(sampled) - box_mean(luminance(sampled), 5)
    # Away from the edges of what is covered, where the box mean mixes in what is not.
    core = box_mean(covered.astype(float), 5) > 0.999
    r = float(np.corrcoef(hp_image[core], hp_tiles[core])[0, 1])
    return Measure(tile, per_quad, texels / max(pixels, 1), r, int(np.count_nonzero(core)))
