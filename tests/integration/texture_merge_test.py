#!/usr/bin/python3
"""A merge carries textures (issue 6), checked with none of vsm's code:

A = PRISMelevation.tif imported with the real NASA image (conus_visible_earth.tif, georeferenced)
draped over it; B = jacksboro_fault_dem.tif imported with a synthetic gradient image stretched
over its extent (red = column, green = row, blue = 200: the colour says where a texel came from);
both with 65 x 65 patches. `vsm merge A B --out M`, `vsm validate M`, then with our own OPC and
.aara readers (check_import.py, written from OPC.md), our own ECEF -> geodetic conversion and GDAL:

(a) files: every patch of M names Coordinates.aara and Diffuse\\<folder>.tif, the tiles in
    Images/Diffuse are exactly the ones named (the replaced patches' old tiles are gone);
(b) every patch M shares with A (same folder) has the same tile bytes as in A;
(c) in M's deepest patches, every sampled texel whose centre (the bilinear mean of its quad's
    four corner vertices, converted to lon/lat) lies inside B's raster is the gradient image at that lon/lat
    (bilinear between pixel centres) within GRADIENT_TOLERANCE, and far from A's image there for
    many of them (so (c) fails if the merge kept A's texture);
(d) texels of the new patches outside B match the NASA image at their lon/lat within
    IMAGE_TOLERANCE (A's texture upsampled);
(e) every parent has as many texels per grid quad as its finest child, and each of its texels
    is the mean of the 2 x 2 texels it covers of a child with as many (within rounding);
(g) B's image is finer than B's grid (1.27 pixels per sample), so B's tiles have 2 texels per
    quad, and every new leaf that takes texels from B has at least as many (issue 28: each
    model's imagery keeps its own resolution; A's are 1 per quad);
(f) merges mixing textured and untextured models still give every patch they write a tile and
    coordinates (check_import.check_pro3d): A untextured (`--texture none`, as a foreign OPC
    without Images/) with B textured: every patch the merge wrote, B's image inside B and grey
    shaded relief outside it in the new leaves; A textured with B untextured: the whole result.

Run by ctest:  texture_merge_test.py --vsm build/server/cli/vsm --data ../shared/data --work <dir>
"""

import argparse
import hashlib
import os
import shutil
import sys
import unittest

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
import check_import  # noqa: E402
from check_import import QUADRANTS, Failures, check_pro3d, ecef_to_geodetic  # noqa: E402
from harness import bilinear  # noqa: E402
from merge_check import load  # noqa: E402
from model_states import REVISION_FILE, reachable_folders  # noqa: E402

gdal.UseExceptions()

N = 65                     # vertices per patch side
QUADS = N - 1              # grid quads per patch side; a tile has QUADS * f texels a side
GRADIENT_SIZE = (512, 384)  # columns, rows of B's image
GRADIENT_TOLERANCE = 2.0   # 8-bit units: three roundings of a linear ramp (image, B's tile, merge)
IMAGE_TOLERANCE = 3.0      # A's tile (the image at A's quad centres) upsampled vs. the image
MARGIN = 2                 # B raster pixels kept clear of B's border in (c), A's pixels in (d)


def gradient_image(path):
    cols, rows = GRADIENT_SIZE
    x = np.arange(cols)[None, :].repeat(rows, 0)
    y = np.arange(rows)[:, None].repeat(cols, 1)
    bands = [np.round(255 * x / (cols - 1)), np.round(255 * y / (rows - 1)),
             np.full((rows, cols), 200.0)]
    mem = gdal.GetDriverByName("MEM").Create("", cols, rows, 3, gdal.GDT_Byte)
    for b, band in enumerate(bands):
        mem.GetRasterBand(b + 1).WriteArray(band.astype(np.uint8))
    gdal.GetDriverByName("PNG").CreateCopy(path, mem)
    return np.stack(bands)


def read_tile(opc, folder):
    """The tile's texels (band, row, column) and f, its texels per grid quad side: a power of two
    (the tile QUADS * f texels a side)."""
    ds = gdal.Open(os.path.join(opc, "Images", "Diffuse", folder + ".tif"))
    size = ds.RasterXSize
    f = size // QUADS
    assert ds.RasterYSize == size and size == QUADS * f and f & (f - 1) == 0, (folder, size)
    return check_import.read_tile(os.path.join(opc, "Images", "Diffuse", folder + ".tif")), f


def digest(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def texel_lonlat(patch, i, j, f):
    """lon, lat of the centre of texel (i, j) of a tile of f texels per quad side: the bilinear
    mean of its quad's four corners at the texel's centre."""
    qx, qy = i // f, j // f
    corners = patch.grid[qy:qy + 2, qx:qx + 2].reshape(4, 3)
    if np.isnan(corners).any():
        return None
    sx, sy = (i % f + 0.5) / f, (j % f + 0.5) / f
    w = np.array([(1 - sx) * (1 - sy), sx * (1 - sy), (1 - sx) * sy, sx * sy])
    c = w @ corners
    lon, lat, _ = ecef_to_geodetic(c[0], c[1], c[2])
    return float(lon), float(lat)


def check_mixed(args, textured_a, textured_b, failures):
    """(f): the merges of a textured model with an untextured one, both ways."""
    bare_a, bare_b = (os.path.join(args.work, name) for name in ("bare-a", "bare-b"))
    for dem, out in (("PRISMelevation.tif", bare_a), ("jacksboro_fault_dem.tif", bare_b)):
        harness.import_dem(os.path.join(args.data, dem), out, N, "--texture", "none")
        if os.path.exists(os.path.join(out, "Images")):
            failures.add("%s: --texture none wrote Images/" % out)

    # A untextured, B textured: every patch the merge wrote (the folders A did not have).
    merged = os.path.join(args.work, "merged-bare-a")
    harness.vsm("merge", bare_a, textured_b, "--out", merged, check=True)
    harness.vsm("validate", merged, check=True)
    _, a_patches, _, _ = load(bare_a, N, failures)
    _, m_patches, m_children, _ = load(merged, N, failures)
    a_folders = {p.folder for p in a_patches.values()}
    written = {p.folder for p in m_patches.values() if p.folder not in a_folders}
    checked = check_pro3d(merged, failures, only=written)
    if checked != len(written) or checked < 10:
        failures.add("merge into an untextured target: %d of %d written patches checked" %
                     (checked, len(written)))
    # In the new leaves: B's gradient (blue 200) or grey relief (r = g = b), nothing transparent
    # where the quad has a surface.
    coloured = grey = 0
    for key, patch in m_patches.items():
        if patch.folder not in written or m_children[key]:
            continue
        tile, f = read_tile(merged, patch.folder)
        for j in range(0, QUADS * f, 5):
            for i in range(0, QUADS * f, 5):
                if texel_lonlat(patch, i, j, f) is None:
                    continue
                r, g, b, a = tile[:, j, i]
                if a != 255:
                    failures.add("%s texel (%d, %d) transparent over the surface" %
                                 (patch.folder, i, j))
                elif r == g == b:
                    grey += 1
                elif b == 200:
                    coloured += 1
                else:
                    failures.add("%s texel (%d, %d) %s: neither B's image nor relief" %
                                 (patch.folder, i, j, (r, g, b)))
    if coloured < 100 or grey < 100:
        failures.add("merge into an untextured target: %d texels of B's image, %d of relief" %
                     (coloured, grey))

    # A textured, B untextured: the result is complete for PRo3D.
    merged = os.path.join(args.work, "merged-bare-b")
    harness.vsm("merge", textured_a, bare_b, "--out", merged, check=True)
    complete = check_pro3d(merged, failures)
    return ("untextured target: %d written patches with tiles (%d texels of B's image, %d of "
            "relief); untextured detail: %d patches complete" %
            (len(written), coloured, grey, complete))


ARGS = None


class TextureMerge(unittest.TestCase):
    def test_a_merge_carries_textures(self):
        """Every texel of the new deepest patches from the image it must come from; parents,
        untouched tiles, mixed merges."""
        shutil.rmtree(ARGS.work, ignore_errors=True)
        os.makedirs(ARGS.work)
        target, detail, merged = (os.path.join(ARGS.work, name) for name in ("a", "b", "merged"))
        gradient_path = os.path.join(ARGS.work, "gradient.png")
        gradient = gradient_image(gradient_path)
        nasa_path = os.path.join(ARGS.data, "conus_visible_earth.tif")
        dem_b_path = os.path.join(ARGS.data, "jacksboro_fault_dem.tif")
        harness.import_dem(os.path.join(ARGS.data, "PRISMelevation.tif"), target, N,
                           "--texture", nasa_path)
        harness.import_dem(dem_b_path, detail, N, "--texture", gradient_path)
        harness.vsm("merge", target, detail, "--out", merged, check=True)
        harness.vsm("validate", merged, check=True)

        failures = Failures()
        _, a_patches, _, _ = load(target, N, failures)
        _, m_patches, m_children, _ = load(merged, N, failures)

        # (a) every patch textured; the tiles on disk exactly the named ones and those of the target's
        # revision before the merge, which the merged model keeps (core/store/README.md).
        kept = set()
        for name in os.listdir(os.path.join(merged, "Patches")):
            if REVISION_FILE.fullmatch(name):
                kept |= {folder + ".tif" for folder in reachable_folders(merged, name)}
        if not kept:
            failures.add("the merged model keeps no revision before the merge")
        named = set()
        for key, patch in m_patches.items():
            xml = open(os.path.join(merged, "Patches", patch.folder, "Patch.xml")).read()
            entry = "Diffuse\\%s.tif" % patch.folder
            if entry not in xml or "Coordinates.aara" not in xml:
                failures.add("%s: Patch.xml does not name %s and Coordinates.aara" % (patch.folder, entry))
            named.add(patch.folder + ".tif")
        on_disk = set(os.listdir(os.path.join(merged, "Images", "Diffuse")))
        if on_disk != named | kept:
            failures.add("Images/Diffuse holds %d tiles no patch names (%s) and misses %d named ones" %
                         (len(on_disk - named - kept), sorted(on_disk - named - kept)[:5],
                          len((named | kept) - on_disk)))

        # (b) shared patches keep their tiles byte for byte.
        a_folders = {p.folder for p in a_patches.values()}
        shared = [p.folder for p in m_patches.values() if p.folder in a_folders]
        for folder in shared:
            before = digest(os.path.join(target, "Images", "Diffuse", folder + ".tif"))
            after = digest(os.path.join(merged, "Images", "Diffuse", folder + ".tif"))
            if before != after:
                failures.add("%s: tile changed although the patch was not rewritten" % folder)
        new_keys = [k for k, p in m_patches.items() if p.folder not in a_folders]

        # (c) and (d): texels of the new leaves against the two images at their own lon/lat.
        dem_b = gdal.Open(dem_b_path)
        b_gt = dem_b.GetGeoTransform()
        b_west, b_north = b_gt[0], b_gt[3]
        b_east = b_west + dem_b.RasterXSize * b_gt[1]
        b_south = b_north + dem_b.RasterYSize * b_gt[5]
        nasa = gdal.Open(nasa_path)
        nasa_inv = gdal.InvGeoTransform(nasa.GetGeoTransform())
        nasa_image = nasa.ReadAsArray().astype(float)

        def nasa_at(lon, lat):
            ix = nasa_inv[0] + lon * nasa_inv[1] + lat * nasa_inv[2]
            iy = nasa_inv[3] + lon * nasa_inv[4] + lat * nasa_inv[5]
            return bilinear(nasa_image, ix, iy)[:3]

        max_depth = max(k[0] for k in m_patches)
        inside = outside = differs = 0
        coarse_inside = []  # new leaves with texels from B at fewer texels per quad than B's
        b_texels = read_tile(detail, "0_0_0")[1]
        if b_texels < 2:
            failures.add("B's %dx%d image over its 403x344 samples got %d texel per quad, not 2" %
                         (GRADIENT_SIZE[0], GRADIENT_SIZE[1], b_texels))
        worst_inside = worst_outside = 0.0
        for key in new_keys:
            if m_children[key]:
                continue
            patch = m_patches[key]
            tile, f = read_tile(merged, patch.folder)
            inside_before = inside
            for j in range(0, QUADS * f, 7):
                for i in range(0, QUADS * f, 7):
                    at = texel_lonlat(patch, i, j, f)
                    if at is None:
                        continue
                    lon, lat = at
                    got = tile[:3, j, i]
                    margin_lon, margin_lat = MARGIN * b_gt[1], -MARGIN * b_gt[5]
                    if (key[0] == max_depth and b_west + margin_lon < lon < b_east - margin_lon and
                            b_south + margin_lat < lat < b_north - margin_lat):
                        # The gradient is stretched over B's raster, pixel edge to pixel edge.
                        gx = (lon - b_west) / (b_east - b_west) * GRADIENT_SIZE[0]
                        gy = (b_north - lat) / (b_north - b_south) * GRADIENT_SIZE[1]
                        expected = bilinear(gradient, gx, gy)
                        error = float(np.max(np.abs(got - expected)))
                        worst_inside = max(worst_inside, error)
                        if error > GRADIENT_TOLERANCE:
                            failures.add("%s texel (%d, %d) at %.5f, %.5f: %s, B's image %s" %
                                         (patch.folder, i, j, lon, lat, got, expected))
                        if float(np.max(np.abs(got - nasa_at(lon, lat)))) > 30:
                            differs += 1
                        inside += 1
                    elif not (b_west - 4 * margin_lon < lon < b_east + 4 * margin_lon and
                              b_south - 4 * margin_lat < lat < b_north + 4 * margin_lat):
                        expected = nasa_at(lon, lat)
                        error = float(np.max(np.abs(got - expected)))
                        worst_outside = max(worst_outside, error)
                        if error > IMAGE_TOLERANCE:
                            failures.add("%s texel (%d, %d) at %.5f, %.5f: %s, A's image %s" %
                                         (patch.folder, i, j, lon, lat, got, expected))
                        outside += 1
            if inside > inside_before and f < b_texels:
                coarse_inside.append((patch.folder, f))
        if coarse_inside:
            failures.add("%d new leaves take B's image at fewer texels per quad than B's %d: %s" %
                         (len(coarse_inside), b_texels, coarse_inside[:5]))
        if inside < 500 or differs < inside // 2:
            failures.add("only %d texels checked inside B (%d of them unlike A's image)" %
                         (inside, differs))
        if outside < 100:
            failures.add("only %d texels checked outside B" % outside)

        # (e) parents: as many texels per quad as their finest child; each texel the mean of the
        # 2 x 2 texels it covers of a child of that many (a coarser child is upsampled first: the
        # unit tests check that).
        parents = upsampled = 0
        tiles = {}

        def tile_of(key):
            if key not in tiles:
                tiles[key] = read_tile(merged, m_patches[key].folder)
            return tiles[key]

        for key, children in m_children.items():
            if not children or m_patches[key].folder in a_folders:
                continue
            parent, f = tile_of(key)
            finest = max(tile_of(child_key)[1] for child_key in children.values())
            if f != finest:
                failures.add("%s: %d texels per quad, its finest child %d" %
                             (m_patches[key].folder, f, finest))
            half = QUADS * f // 2
            for q, child_key in children.items():
                qx, qy = QUADRANTS[q]
                c, child_f = tile_of(child_key)
                if child_f != f:
                    upsampled += 1
                    continue
                mean = (c[:, 0::2, 0::2] + c[:, 0::2, 1::2] + c[:, 1::2, 0::2] + c[:, 1::2, 1::2]) / 4
                got = parent[:, qy * half:(qy + 1) * half, qx * half:(qx + 1) * half]
                if not np.all(np.abs(got - mean) <= 0.5 + 1e-9):
                    failures.add("%s: quadrant %s is not the mean of %s" %
                                 (m_patches[key].folder, q, m_patches[child_key].folder))
                parents += 1

        mixed = check_mixed(ARGS, target, detail, failures)

        summary = (
            "texture merge: %d patches (%d new, %d shared byte-identical), %d texels inside B within "
            "%.2f of B's image (%d unlike A's, B at %d texels per quad), %d outside within %.2f of "
            "A's image, %d parent quadrants exact (%d from coarser children)" %
            (len(m_patches), len(new_keys), len(shared), inside, worst_inside, differs, b_texels,
             outside, worst_outside, parents, upsampled) + "; " + mixed)
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
