#!/usr/bin/python3
"""Independent check of an OPC that `vsm import` made from a raster.

    /usr/bin/python3 check_import.py <raster.tif> <opc-dir>

Uses none of vsm's code: GDAL's Python bindings read the raster, and this file reads the OPC from
its specification (docs/OPC.md): xml.etree for the XML, its own .aara decoder, its own ECEF ->
geodetic conversion (Bowring's formula plus a Newton step).

Checks
- the hierarchy is a tree reached from RootPatch; keys follow from quadrant positions (and match
  vsm's <Vsm><Key> extension when present); every leaf is at the deepest level (a plain import is
  full resolution everywhere);
- every leaf vertex: bottom patch (x, y) at depth D, vertex (i, j) is raster sample
  (x * (N - 1) + i, y * (N - 1) + j). Inside the raster it is defined exactly where the sample is
  (no-data and NaN are undefined) and, converted back to lon/lat/height, sits at the pixel centre
  with the sample's height; beyond the raster it is undefined (padding). Tolerance: max(1 cm,
  float32 rounding of the patch's stored coordinates = 2^-23 x its largest absolute local
  coordinate), turned into degrees with the local radii of curvature for lon/lat;
- every defined raster sample is present in some leaf (exactly once, or on a shared border line in
  each patch holding that line, all equal to the sample);
- every parent vertex (i, j) equals vertex (2i, 2j) of its children's union, and is undefined
  exactly where no present child defines that vertex; tolerance: the float32 rounding of both
  patches (2^-23 x largest absolute local coordinate of each);
- PRo3D opens it (check_pro3d, OPC.md): Images/ beside Patches/, and every patch names a
  Coordinates file of its positions' size and a first texture whose tile exists under Images/.

A unittest case: it prints one summary line and fails listing the failures (at most 50,
then a count).
"""

import argparse
import os
import re
import sys
import unittest
import xml.etree.ElementTree as ET

import numpy as np
from osgeo import gdal, osr

import harness  # the .aara reader (beside this file)

gdal.UseExceptions()

# WGS 84
A = 6378137.0
F = 1.0 / 298.257223563
E2 = F * (2.0 - F)
B = A * (1.0 - F)
EP2 = (A * A - B * B) / (B * B)

QUADRANTS = {"nw": (0, 0), "ne": (1, 0), "sw": (0, 1), "se": (1, 1)}
QUADRANT_ORDER = ["nw", "ne", "sw", "se"]
MAX_LISTED = 50


class Failures:
    """The findings of a checker that walks a whole model (thousands of patches, each checked
    alone): collected rather than raised at the first, so one run lists them all; the test then
    asserts there are none (assert_none)."""

    def __init__(self):
        self.items = []
        self.count = 0

    def add(self, message):
        self.count += 1
        if len(self.items) < MAX_LISTED:
            self.items.append(message)

    def assert_none(self, test, summary=""):
        """The verdict of a unittest case: the summary printed, then none failed (the first
        MAX_LISTED listed in the assertion's message)."""
        if summary:
            print(summary)
        more = self.count - len(self.items)
        test.assertEqual(self.count, 0, "%d failures:\n%s" % (
            self.count, "\n".join(self.items + (["... and %d more" % more] if more else []))))


# ------------------------------------------------------------------------------------------------
# Reading the OPC


def find_ci(directory, name):
    """The entry of `directory` named `name` in any letter case."""
    for entry in os.listdir(directory):
        if entry.lower() == name.lower():
            return os.path.join(directory, entry)
    raise FileNotFoundError(os.path.join(directory, name))


def child_ci(element, name):
    for child in element:
        if child.tag.lower() == name.lower():
            return child
    return None


def numbers(text):
    """All numbers of an OPC list such as "[[1, 0, 0, 5], ...]" in reading order."""
    return [float(t) for t in re.findall(r"[-+]?(?:nan|inf|(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)",
                                         text, flags=re.IGNORECASE)]


def read_tile(path):
    """A texture tile as (4, rows, cols) floats, RGBA: vsm writes RGB where every texel is opaque
    and RGBA elsewhere; a file without alpha reads as alpha 255, a grey one as R = G = B."""
    t = gdal.Open(path).ReadAsArray().astype(float)
    if t.ndim == 2:
        t = t[None]
    if t.shape[0] < 3:
        t = np.concatenate([t[:1], t[:1], t[:1], t[1:]])
    if t.shape[0] == 3:
        t = np.concatenate([t, np.full((1,) + t.shape[1:], 255.0)])
    return t


def read_aara(path):
    """(type name, sizes, elements as float64 array of shape (rows, cols, 3))."""
    type_name, sizes, values = harness.read_aara(path)
    if type_name not in ("V3f", "V3d"):
        raise ValueError("%s: unexpected array %s" % (path, type_name))
    return type_name, tuple(sizes), values.astype(np.float64)


def read_items(sub_patch_map, children):
    """The <item> elements of a SubPatchMap into {folder: {quadrant: child folder}}."""
    for item in sub_patch_map:
        key = child_ci(item, "key").text.strip()
        if key in children:
            raise ValueError("patch %s has two <item> elements" % key)
        children[key] = {c.tag.lower(): c.text.strip() for c in child_ci(item, "val")}


def hidden_file(opc, name="patchhierarchy.xml"):
    """The second hierarchy file a hierarchy names (<Vsm><HiddenLevels>: vsm's hidden levels,
    thesis 5.2), or None."""
    patches = find_ci(opc, "Patches")
    ph = child_ci(ET.parse(find_ci(patches, name)).getroot(), "PatchHierarchy")
    vsm = child_ci(ph, "Vsm")
    hidden = child_ci(vsm, "HiddenLevels") if vsm is not None else None
    return None if hidden is None else os.path.join(patches, hidden.text.strip())


def read_hierarchy(opc, name="patchhierarchy.xml", hidden=False):
    """(Patches dir, root folder, {folder: {quadrant: child folder}}) of the hierarchy file
    `name` (the current one, or a kept revision's "vsm-revision-N.xml"): what other OPC readers
    see, or with `hidden` the items of the second file it names too (every level)."""
    patches = find_ci(opc, "Patches")
    root = ET.parse(find_ci(patches, name)).getroot()
    ph = child_ci(root, "PatchHierarchy")
    children = {}
    read_items(child_ci(ph, "SubPatchMap"), children)
    second = hidden_file(opc, name) if hidden else None
    if second is not None:
        levels = child_ci(ET.parse(second).getroot(), "VsmHiddenLevels")
        read_items(child_ci(levels, "SubPatchMap"), children)
    return patches, child_ci(ph, "RootPatch").text.strip(), children


class Patch:
    """One patch: its key (depth, x, y) from its position in the tree and its vertex data."""

    def __init__(self, patches_dir, folder, key):
        self.folder = folder
        self.key = key
        directory = find_ci(patches_dir, folder)
        xml_root = ET.parse(find_ci(directory, "Patch.xml")).getroot()
        patch = child_ci(xml_root, "Patch")
        m = numbers(child_ci(patch, "Local2Global").text)
        if len(m) != 16:
            raise ValueError("%s: Local2Global has %d numbers" % (folder, len(m)))
        self.l2g = np.array(m).reshape(4, 4)  # row by row, translation in the last column
        _, sizes, local = read_aara(find_ci(directory, child_ci(patch, "Positions").text.strip()))
        self.stored_cols, self.stored_rows = sizes
        self.local = local
        self.offset = (0, 0)
        self.vsm_key = None
        self.vsm_size = None
        vsm = child_ci(patch, "Vsm")
        if vsm is not None:
            offset = child_ci(vsm, "Offset")
            if offset is not None:
                values = numbers(offset.text)
                self.offset = (int(values[0]), int(values[1]))
            key_element = child_ci(vsm, "Key")
            if key_element is not None:
                self.vsm_key = key_element.text.strip()
            for name in ("GridSize", "Size"):
                element = child_ci(vsm, name)
                if element is not None:
                    self.vsm_size = int(numbers(element.text)[0])
                    break
        defined = ~np.isnan(local).any(axis=2)
        # float32 rounding of the stored coordinates: half an ulp per component, so the 3D error
        # is below 2^-23 x the largest absolute local coordinate.
        self.rounding = 2.0 ** -23 * (float(np.abs(local[defined]).max()) if defined.any() else 0.0)
        self.grid = None  # full N x N global positions, once the patch size is known

    def expand(self, n):
        """Global positions on the full n x n grid (cropped borders undefined)."""
        ox, oy = self.offset
        if ox + self.stored_cols > n or oy + self.stored_rows > n or ox < 0 or oy < 0:
            raise ValueError("%s: stored %dx%d at offset %s exceeds the %dx%d grid" %
                             (self.folder, self.stored_cols, self.stored_rows, self.offset, n, n))
        local = self.local
        ones = np.ones(local.shape[:2] + (1,))
        glob = np.concatenate([local, ones], axis=2) @ self.l2g.T
        grid = np.full((n, n, 3), np.nan)
        grid[oy:oy + self.stored_rows, ox:ox + self.stored_cols] = glob[:, :, :3]
        undefined = np.isnan(grid).any(axis=2)
        grid[undefined] = np.nan
        self.grid = grid


# ------------------------------------------------------------------------------------------------
# What PRo3D needs to open a model (OPC.md)

TEXTURE_EXTENSIONS = (".dds", ".tif", ".tiff")  # readers swap the extension trying these
TIFF_MAGIC = (b"II*\x00", b"MM\x00*")


def aara_header(path):
    """(type name, sizes) of an .aara file, checking that its length fits them."""
    type_name, sizes, _ = harness.read_aara(path)
    return type_name, sizes


def check_pro3d(opc, failures, only=None):
    """OPC.md's "What PRo3D needs": `Images/` beside `Patches/`, and for every patch reached from
    the root (or only the folders in `only`) a first <Coordinates> entry naming a V2f/V2d file of
    the positions' size in its folder and a first <Textures> entry whose tile exists under
    Images/ (backslash paths, the extension swapped as readers do) and is a TIFF or DDS file.
    Returns the patches checked."""
    for name in ("Images", "Patches"):
        if not os.path.isdir(os.path.join(opc, name)):
            failures.add("%s: no %s/ folder: PRo3D does not open the model" % (opc, name))
            return 0
    patches_dir, root, children = read_hierarchy(opc)
    folders = [root] + [f for kids in children.values() for f in kids.values()]
    if only is not None:
        folders = [f for f in folders if f in only]
    for folder in folders:
        directory = find_ci(patches_dir, folder)
        patch = child_ci(ET.parse(find_ci(directory, "Patch.xml")).getroot(), "Patch")
        coordinates = child_ci(patch, "Coordinates")
        textures = child_ci(patch, "Textures")
        if coordinates is None or len(coordinates) == 0 or textures is None or len(textures) == 0:
            failures.add("%s: Patch.xml names no texture coordinates or no texture" % folder)
            continue
        coords_file = os.path.join(directory, coordinates[0].text.strip())
        positions_file = os.path.join(directory, child_ci(patch, "Positions").text.strip())
        if not os.path.isfile(coords_file):
            failures.add("%s: coordinates %s missing" % (folder, coords_file))
        else:
            ctype, csizes = aara_header(coords_file)
            _, psizes = aara_header(positions_file)
            if ctype not in ("V2f", "V2d") or csizes != psizes:
                failures.add("%s: coordinates are %s %s, positions %s" %
                             (folder, ctype, csizes, psizes))
        entry = textures[0].text.strip().replace("\\", "/")
        stem = os.path.splitext(os.path.join(opc, "Images", entry))[0]
        tiles = [stem + ext for ext in TEXTURE_EXTENSIONS if os.path.isfile(stem + ext)]
        if not tiles:
            failures.add("%s: texture %s is not under Images/" % (folder, textures[0].text))
            continue
        with open(tiles[0], "rb") as f:
            magic = f.read(4)
        if magic not in TIFF_MAGIC and magic != b"DDS ":
            failures.add("%s: texture %s is neither TIFF nor DDS" % (folder, tiles[0]))
    return len(folders)


# ------------------------------------------------------------------------------------------------
# Geodesy


def ecef_to_geodetic(x, y, z):
    """WGS 84 ECEF (m) -> lon, lat (degrees), ellipsoidal height (m). Bowring's formula, then one
    Newton step on the latitude; sub-millimetre for terrestrial heights."""
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    theta = np.arctan2(z * A, p * B)
    lat = np.arctan2(z + EP2 * B * np.sin(theta) ** 3, p - E2 * A * np.cos(theta) ** 3)
    for _ in range(2):
        s = np.sin(lat)
        n = A / np.sqrt(1.0 - E2 * s * s)
        h = p * np.cos(lat) + z * s - A * np.sqrt(1.0 - E2 * s * s)
        lat = np.arctan2(z, p * (1.0 - E2 * n / (n + h)))
    s = np.sin(lat)
    h = p * np.cos(lat) + z * s - A * np.sqrt(1.0 - E2 * s * s)
    return np.degrees(lon), np.degrees(lat), h


def radii(lat_deg):
    """Meridian and prime-vertical radii of curvature (m) at a latitude."""
    s = np.sin(np.radians(lat_deg))
    w = np.sqrt(1.0 - E2 * s * s)
    return A * (1.0 - E2) / w ** 3, A / w


# ------------------------------------------------------------------------------------------------
# The raster


class Raster:
    def __init__(self, path):
        ds = gdal.Open(path)
        band = ds.GetRasterBand(1)
        self.width, self.height = ds.RasterXSize, ds.RasterYSize
        gt = ds.GetGeoTransform()
        if gt[2] != 0 or gt[4] != 0:
            raise ValueError("rotated geotransform")
        self.heights = harness.band_heights(band)
        # Pixel centres in lon/lat (WGS 84), per sample.
        cols = gt[0] + (np.arange(self.width) + 0.5) * gt[1]
        rows = gt[3] + (np.arange(self.height) + 0.5) * gt[5]
        srs = ds.GetSpatialRef()
        wgs84 = osr.SpatialReference()
        wgs84.ImportFromEPSG(4326)
        wgs84.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
        srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
        if srs.IsGeographic() and srs.IsSameGeogCS(wgs84):
            self.lon = np.broadcast_to(cols[None, :], (self.height, self.width))
            self.lat = np.broadcast_to(rows[:, None], (self.height, self.width))
        else:
            ct = osr.CoordinateTransformation(srs, wgs84)
            xs, ys = np.meshgrid(cols, rows)
            points = np.array(ct.TransformPoints(np.stack([xs.ravel(), ys.ravel()], axis=1)))
            self.lon = points[:, 0].reshape(self.height, self.width)
            self.lat = points[:, 1].reshape(self.height, self.width)


# ------------------------------------------------------------------------------------------------
# Checks


def walk(patches_dir, root_folder, children, failures):
    """All patches by key, from the hierarchy alone."""
    patches = {}
    stack = [(root_folder, (0, 0, 0))]
    seen = set()
    while stack:
        folder, key = stack.pop()
        if folder in seen:
            failures.add("%s: reached twice in the hierarchy" % folder)
            continue
        seen.add(folder)
        patch = Patch(patches_dir, folder, key)
        expected = "%d_%d_%d" % key
        if patch.vsm_key is not None and patch.vsm_key != expected:
            failures.add("%s: <Vsm><Key> %s, but its place in the tree is %s" %
                         (folder, patch.vsm_key, expected))
        patches[key] = patch
        for quadrant, child in children.get(folder, {}).items():
            if quadrant not in QUADRANTS:
                failures.add("%s: unknown quadrant %s" % (folder, quadrant))
                continue
            qx, qy = QUADRANTS[quadrant]
            stack.append((child, (key[0] + 1, 2 * key[1] + qx, 2 * key[2] + qy)))
    return patches


def patch_size(patches, raster, depth):
    """N from the data: the Vsm size when written, else the one 2^n + 1 for which depth D is the
    smallest with (N - 1) * 2^D >= max(width, height) - 1."""
    sizes = {p.vsm_size for p in patches.values() if p.vsm_size is not None}
    if len(sizes) == 1:
        return sizes.pop()
    largest = max(max(p.stored_cols, p.stored_rows) for p in patches.values())
    extent = max(raster.width, raster.height) - 1
    if depth == 0:
        return largest  # one patch: its vertex positions do not depend on N
    intervals = 2
    while intervals * 2 ** depth < extent:
        intervals *= 2
    return intervals + 1


def check_leaf(patch, key, raster, n, failures, stats, coverage):
    """One leaf at the raster's resolution: every vertex the sample (c, r) of its place, defined
    exactly where the sample is, within the float32 rounding or 1 cm; the samples it holds
    counted in `coverage`."""
    c0, r0 = key[1] * (n - 1), key[2] * (n - 1)
    w = max(0, min(n, raster.width - c0))
    h = max(0, min(n, raster.height - r0))
    grid = patch.grid
    defined = ~np.isnan(grid[:, :, 0])
    inside = np.zeros((n, n), dtype=bool)
    inside[:h, :w] = True
    padding = defined & ~inside
    if padding.any():
        j, i = np.argwhere(padding)[0]
        failures.add("%s: vertex %d,%d beyond the raster is defined (%d such)" %
                     (patch.folder, i, j, int(padding.sum())))
    if w == 0 or h == 0:
        return
    heights = raster.heights[r0:r0 + h, c0:c0 + w]
    sample_defined = ~np.isnan(heights)
    here = defined[:h, :w]
    mismatch = here != sample_defined
    if mismatch.any():
        j, i = np.argwhere(mismatch)[0]
        failures.add("%s: vertex %d,%d (sample %d,%d) is %s but the sample is %s (%d such)" %
                     (patch.folder, i, j, c0 + i, r0 + j,
                      "defined" if here[j, i] else "undefined",
                      "defined" if sample_defined[j, i] else "no-data", int(mismatch.sum())))
    both = here & sample_defined
    coverage[r0:r0 + h, c0:c0 + w] += both
    stats["samples"] += int(both.sum())
    if not both.any():
        return
    g = grid[:h, :w][both]
    lon, lat, hgt = ecef_to_geodetic(g[:, 0], g[:, 1], g[:, 2])
    lon_c = raster.lon[r0:r0 + h, c0:c0 + w][both]
    lat_c = raster.lat[r0:r0 + h, c0:c0 + w][both]
    tolerance = max(0.01, patch.rounding)
    m, nu = radii(lat_c)
    north = np.radians(lat - lat_c) * m
    east = np.radians((lon - lon_c + 180.0) % 360.0 - 180.0) * nu * np.cos(np.radians(lat_c))
    up = hgt - heights[both]
    # The tolerance in degrees, per axis: the same metres over the local radii of curvature.
    lat_tol = np.degrees(tolerance / m)
    lon_tol = np.degrees(tolerance / (nu * np.maximum(np.cos(np.radians(lat_c)), 1e-12)))
    bad = (np.abs(lat - lat_c) > lat_tol) | \
          (np.abs((lon - lon_c + 180.0) % 360.0 - 180.0) > lon_tol) | (np.abs(up) > tolerance)
    stats["horizontal"] = max(stats["horizontal"], float(np.hypot(north, east).max()))
    stats["vertical"] = max(stats["vertical"], float(np.abs(up).max()))
    if bad.any():
        k = int(np.argmax(bad))
        j, i = np.argwhere(both)[k]
        failures.add("%s: vertex %d,%d (sample %d,%d) is %.4f m east, %.4f m north, %.4f m up "
                     "of its pixel centre and height (tolerance %.4f m; %d such)" %
                     (patch.folder, i, j, c0 + i, r0 + j, east[k], north[k], up[k], tolerance,
                      int(bad.sum())))


def check_leaves(patches, children_of, raster, n, depth, failures, stats):
    coverage = np.zeros((raster.height, raster.width), dtype=np.int32)
    for key, patch in sorted(patches.items()):
        if children_of[key]:
            continue
        if key[0] != depth:
            failures.add("%s: leaf at depth %d, but the pyramid is %d deep" %
                         (patch.folder, key[0], depth))
            continue
        check_leaf(patch, key, raster, n, failures, stats, coverage)
    missing = ~np.isnan(raster.heights) & (coverage == 0)
    if missing.any():
        r, c = np.argwhere(missing)[0]
        failures.add("raster sample %d,%d (and %d more) is in no leaf" % (c, r, int(missing.sum()) - 1))
    # A sample inside a patch (not on a border line) is in exactly one leaf.
    cols = np.arange(raster.width)
    rows = np.arange(raster.height)
    border = (cols[None, :] % (n - 1) == 0) | (rows[:, None] % (n - 1) == 0)
    repeated = (coverage > 1) & ~border
    if repeated.any():
        r, c = np.argwhere(repeated)[0]
        failures.add("raster sample %d,%d is in %d leaves" % (c, r, coverage[r, c]))
    stats["overlap"] = int((coverage > 1).sum())
    stats["undefined"] = int(np.isnan(raster.heights).sum())


def check_parents(patches, children_of, n, failures, stats):
    half = n - 1
    for key, parent in sorted(patches.items()):
        kids = children_of[key]
        if not kids:
            continue
        union = np.full((2 * n - 1, 2 * n - 1, 3), np.nan)
        rounding = np.zeros((2 * n - 1, 2 * n - 1))
        for quadrant in QUADRANT_ORDER:
            if quadrant not in kids:
                continue
            qx, qy = QUADRANTS[quadrant]
            child = patches[kids[quadrant]]
            block = union[qy * half:qy * half + n, qx * half:qx * half + n]
            tol = rounding[qy * half:qy * half + n, qx * half:qx * half + n]
            child_defined = ~np.isnan(child.grid[:, :, 0])
            already = ~np.isnan(block[:, :, 0])
            # Children sharing a border line agree on it.
            shared = already & child_defined
            if shared.any():
                d = np.linalg.norm(block[shared] - child.grid[shared], axis=1)
                limit = tol[shared] + child.rounding + 1e-6
                if (d > limit).any():
                    k = int(np.argmax(d - limit))
                    failures.add("%s: children disagree on their shared border by %.6f m" %
                                 (parent.folder, d[k]))
            take = ~already & child_defined
            block[take] = child.grid[take]
            tol[take] = child.rounding
        expected = union[::2, ::2]
        expected_tol = rounding[::2, ::2] + parent.rounding + 1e-6
        parent_defined = ~np.isnan(parent.grid[:, :, 0])
        expected_defined = ~np.isnan(expected[:, :, 0])
        mismatch = parent_defined != expected_defined
        if mismatch.any():
            j, i = np.argwhere(mismatch)[0]
            failures.add("%s: vertex %d,%d is %s but its child vertex is %s (%d such)" %
                         (parent.folder, i, j, "defined" if parent_defined[j, i] else "undefined",
                          "defined" if expected_defined[j, i] else "undefined or missing",
                          int(mismatch.sum())))
        both = parent_defined & expected_defined
        if both.any():
            d = np.linalg.norm(parent.grid[both] - expected[both], axis=1)
            limit = expected_tol[both]
            stats["parent"] = max(stats["parent"], float(d.max()))
            stats["parent_vertices"] += int(both.sum())
            if (d > limit).any():
                k = int(np.argmax(d - limit))
                j, i = np.argwhere(both)[k]
                failures.add("%s: vertex %d,%d is %.6f m from its child vertex (tolerance %.6f m)"
                             % (parent.folder, i, j, d[k], limit[k]))


ARGS = None


class CheckImport(unittest.TestCase):
    def test_the_model_is_the_raster(self):
        """Geometry, hierarchy, parents and PRo3D completeness of the OPC against the raster."""
        try:
            failures, summary = check(ARGS.raster, ARGS.opc)
        except (OSError, ValueError, KeyError, AttributeError, IndexError, ET.ParseError,
                RuntimeError) as e:
            # A file that cannot be read as the specification says is a failure, not a crash.
            self.fail("%s: %s: %s" % (ARGS.opc, type(e).__name__, e))
        failures.assert_none(self, summary)


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("raster")
    parser.add_argument("opc")
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


def check(raster_path, opc):
    failures = Failures()
    raster = Raster(raster_path)
    patches_dir, root_folder, children = read_hierarchy(opc, hidden=True)
    patches = walk(patches_dir, root_folder, children, failures)
    children_of = {}
    for key, patch in patches.items():
        children_of[key] = {q: (key[0] + 1, 2 * key[1] + QUADRANTS[q][0], 2 * key[2] + QUADRANTS[q][1])
                            for q in children.get(patch.folder, {}) if q in QUADRANTS}
    depth = max(key[0] for key in patches)
    n = patch_size(patches, raster, depth)
    for patch in patches.values():
        patch.expand(n)
        if np.isnan(patch.grid[:, :, 0]).all():
            failures.add("%s: no defined vertex (empty patches are omitted)" % patch.folder)
    stats = {"samples": 0, "undefined": 0, "overlap": 0, "horizontal": 0.0, "vertical": 0.0,
             "parent": 0.0, "parent_vertices": 0}
    check_leaves(patches, children_of, raster, n, depth, failures, stats)
    check_parents(patches, children_of, n, failures, stats)
    check_pro3d(opc, failures)
    leaves = sum(1 for k in patches if not children_of[k])
    summary = ("%s: %d patches (%d leaves), depth %d, patch size %d; %d samples checked "
               "(%d on shared borders), %d no-data; %d parent vertices; max error horizontal "
               "%.2e m, height %.2e m, parent-child %.2e m" %
               (opc, len(patches), leaves, depth, n, stats["samples"], stats["overlap"],
                stats["undefined"], stats["parent_vertices"], stats["horizontal"],
                stats["vertical"], stats["parent"]))
    return failures, summary


if __name__ == "__main__":
    main()
