#!/usr/bin/python3
"""Real-data merge check: `vsm merge` of a detail model into a target, checked independently.

    /usr/bin/python3 merge_check.py --vsm <vsm> --target <A-opc> --target-raster <A.tif>
                                    --detail <B-opc> --detail-raster <B.tif> --work <dir>

A and B are OPCs that `vsm import` made from the two rasters (in CI: PRISMelevation.tif and
jacksboro_fault_dem.tif with 65 x 65 patches). Runs `vsm merge A B --out <work>/merged` and
`vsm validate` on the result, then checks the result with none of vsm's code: the OPC reader and
the geodesy are check_import.py's (written from docs/OPC.md), the rasters are read with GDAL.

Checks
(a) every defined vertex of every leaf that lies inside B's raster (its lon/lat within the hull
    of B's pixel centres) is within 0.5 m, in height, of B's bilinear surface: the raster's
    heights interpolated bilinearly between pixel centres at the vertex's own lon/lat. Those
    leaves are the deepest patches of the merged model. (For diagnosis the distance to the
    nearer of the cell's two triangulations is reported too: a placement on triangles instead of
    the bilinear patch shows up as an (a) failure with a small triangle distance.);
(b) the same vertices are far from A's surface somewhere (more than 20 m from A's raster,
    bilinear at the same lon/lat), so (a) could fail if the merge kept A's surface;
(c) every parent vertex equals vertex (2i, 2j) of the union of its children (shared borders
    agree), undefined exactly where no child defines it (check_import.check_parents);
(d) the matched leaves are A's leaves that have children in the merged model; they cover B's
    raster; every patch that is neither a matched leaf, below one, nor an ancestor of one keeps its
    folder name, and that folder holds the same files with the same bytes as in A; every patch in
    the affected subtree got a new folder; A itself is not modified.

A unittest case: it prints a summary and fails listing the failures.
"""

import argparse
import hashlib
import os
import re
import subprocess
import sys
import time
import unittest

import numpy as np
from osgeo import gdal, osr

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from check_import import (QUADRANTS, Failures, check_parents, check_pro3d,  # noqa: E402
                          ecef_to_geodetic,
                          read_hierarchy, walk)

gdal.UseExceptions()

PLACEMENT_TOLERANCE = 0.5  # metres, the bound for a merged vertex vs. B's bilinear surface
FAR_FROM_TARGET = 20.0     # metres: A differs from B by tens of metres in B's area


class GeoRaster:
    """Heights of a north-up WGS 84 geographic raster, interpolated between pixel centres."""

    def __init__(self, path):
        ds = gdal.Open(path)
        band = ds.GetRasterBand(1)
        gt = ds.GetGeoTransform()
        if gt[2] != 0 or gt[4] != 0:
            raise ValueError("%s: rotated geotransform" % path)
        srs = ds.GetSpatialRef()
        wgs84 = osr.SpatialReference()
        wgs84.ImportFromEPSG(4326)
        if not (srs.IsGeographic() and srs.IsSameGeogCS(wgs84)):
            raise ValueError("%s: not WGS 84 geographic" % path)
        self.heights = harness.band_heights(band)
        self.gt = gt
        self.height, self.width = self.heights.shape
        # The hull of the pixel centres, lon/lat.
        lons = gt[0] + np.array([0.5, self.width - 0.5]) * gt[1]
        lats = gt[3] + np.array([0.5, self.height - 0.5]) * gt[5]
        self.lon_range = (lons.min(), lons.max())
        self.lat_range = (lats.min(), lats.max())
        band = None
        ds = None

    def pixel(self, lon, lat):
        """Fractional (column, row) of lon/lat in pixel-centre coordinates."""
        return (lon - self.gt[0]) / self.gt[1] - 0.5, (lat - self.gt[3]) / self.gt[5] - 0.5

    def inside(self, lon, lat):
        col, row = self.pixel(lon, lat)
        return (col >= 0) & (col <= self.width - 1) & (row >= 0) & (row <= self.height - 1)

    def corners(self, lon, lat):
        """The four pixel-centre heights around each point and the fractions within the cell.
        Precondition: inside()."""
        col, row = self.pixel(lon, lat)
        c0 = np.clip(np.floor(col).astype(np.int64), 0, self.width - 2)
        r0 = np.clip(np.floor(row).astype(np.int64), 0, self.height - 2)
        u, v = col - c0, row - r0
        h = self.heights
        return h[r0, c0], h[r0, c0 + 1], h[r0 + 1, c0], h[r0 + 1, c0 + 1], u, v

    def bilinear(self, lon, lat):
        z00, z10, z01, z11, u, v = self.corners(lon, lat)
        return (z00 * (1 - u) * (1 - v) + z10 * u * (1 - v) + z01 * (1 - u) * v + z11 * u * v)

    def triangles(self, lon, lat):
        """Heights of the cell's two triangulations (diagonal 00-11, diagonal 10-01)."""
        z00, z10, z01, z11, u, v = self.corners(lon, lat)
        main = np.where(u >= v, z00 + u * (z10 - z00) + v * (z11 - z10),
                        z00 + v * (z01 - z00) + u * (z11 - z01))
        anti = np.where(u + v <= 1, z00 + u * (z10 - z00) + v * (z01 - z00),
                        z11 + (1 - u) * (z01 - z11) + (1 - v) * (z10 - z11))
        return main, anti


def load(opc, n, failures):
    patches_dir, root_folder, children = read_hierarchy(opc)
    patches = walk(patches_dir, root_folder, children, failures)
    children_of = {}
    for key, patch in patches.items():
        children_of[key] = {q: (key[0] + 1, 2 * key[1] + QUADRANTS[q][0],
                                2 * key[2] + QUADRANTS[q][1])
                            for q in children.get(patch.folder, {}) if q in QUADRANTS}
    sizes = {p.vsm_size for p in patches.values() if p.vsm_size is not None}
    if len(sizes) == 1:
        n = sizes.pop()
    for patch in patches.values():
        patch.expand(n)
    return patches_dir, patches, children_of, n


# An edit's folders carry its random nonce ("2_1_0-v3-1a2b3c4d"): two runs of the same write name
# them differently, so versions are compared with the nonces left out.
NONCE = re.compile(rb"(-v[0-9]+)-[0-9a-f]{8}")


def folder_digest(directory, without_nonces=False):
    """{file name: sha256} of every file in a patch folder (recursively, relative names); with
    `without_nonces`, the nonces an edit writes into XML files (the tile a Patch.xml names) left
    out."""
    digest = {}
    for base, _, files in os.walk(directory):
        for name in files:
            path = os.path.join(base, name)
            with open(path, "rb") as f:
                data = f.read()
            if without_nonces and name.lower().endswith(".xml"):
                data = NONCE.sub(rb"\1", data)
            digest[os.path.relpath(path, directory)] = hashlib.sha256(data).hexdigest()
    return digest


def tree_digest(opc):
    """{relative path: sha256} of every file under an OPC directory."""
    return folder_digest(opc)


def leaf_points(patches, children_of):
    """(key, patch, lon, lat, height) of each leaf with defined vertices: those vertices in
    geodetic coordinates (WGS 84)."""
    for key, patch in patches.items():
        if children_of[key]:
            continue
        g = patch.grid.reshape(-1, 3)
        g = g[~np.isnan(g[:, 0])]
        if len(g) == 0:
            continue
        lon, lat, h = ecef_to_geodetic(g[:, 0], g[:, 1], g[:, 2])
        yield key, patch, lon, lat, h


def check_placement(merged, children_of, detail, target, failures, stats):
    """(a) and (b) over every defined leaf vertex inside the detail raster."""
    max_depth = max(k[0] for k in merged)
    heights, lons, lats, depths = [], [], [], []
    for key, patch, lon, lat, h in leaf_points(merged, children_of):
        inside = detail.inside(lon, lat)
        if not inside.any():
            continue
        heights.append(h[inside])
        lons.append(lon[inside])
        lats.append(lat[inside])
        depths.append(np.full(int(inside.sum()), key[0]))
        shallow = key[0] != max_depth
        if shallow:
            failures.add("%s: leaf at depth %d (the deepest level is %d) has %d vertices inside "
                         "the detail raster" % (patch.folder, key[0], max_depth,
                                                int(inside.sum())))
    if not heights:
        failures.add("no leaf vertex lies inside the detail raster")
        return
    h = np.concatenate(heights)
    lon = np.concatenate(lons)
    lat = np.concatenate(lats)
    bil = detail.bilinear(lon, lat)
    tri_main, tri_anti = detail.triangles(lon, lat)
    d_bil = np.abs(h - bil)
    d_tri = np.minimum(np.abs(h - tri_main), np.abs(h - tri_anti))
    # Between the two triangulations (the bilinear value always is): the envelope of every
    # piecewise-linear interpolation of the cell.
    lo, hi = np.minimum(tri_main, tri_anti), np.maximum(tri_main, tri_anti)
    d_env = np.maximum(0.0, np.maximum(lo - h, h - hi))
    stats["vertices"] = len(h)
    stats["bilinear_max"] = float(d_bil.max())
    stats["bilinear_mean"] = float(d_bil.mean())
    stats["bilinear_p99"] = float(np.percentile(d_bil, 99))
    stats["triangle_max"] = float(d_tri.max())
    stats["envelope_max"] = float(d_env.max())
    bad = d_bil > PLACEMENT_TOLERANCE
    if bad.any():
        k = int(np.argmax(d_bil))
        failures.add("%d of %d merged vertices inside the detail raster are more than %.2f m from "
                     "its bilinear surface (max %.3f m at lon %.6f lat %.6f: height %.3f, "
                     "bilinear %.3f, triangulations %.3f / %.3f; max distance to the nearer "
                     "triangulation %.3f m, outside both %.3f m)" %
                     (int(bad.sum()), len(h), PLACEMENT_TOLERANCE, d_bil[k], lon[k], lat[k], h[k],
                      bil[k], tri_main[k], tri_anti[k], stats["triangle_max"],
                      stats["envelope_max"]))
    # (b) the target's surface at the same places.
    in_target = target.inside(lon, lat)
    coarse = target.bilinear(lon[in_target], lat[in_target])
    d_target = np.abs(h[in_target] - coarse)
    d_target = d_target[np.isfinite(d_target)]
    stats["target_max"] = float(d_target.max()) if len(d_target) else 0.0
    stats["target_mean"] = float(d_target.mean()) if len(d_target) else 0.0
    if stats["target_max"] <= FAR_FROM_TARGET:
        failures.add("the merged vertices are never more than %.1f m from the target's surface "
                     "(max %.3f m): the check cannot tell B's surface from A's" %
                     (FAR_FROM_TARGET, stats["target_max"]))
    # The detail raster's samples are all represented: at least one merged vertex per B cell.
    col, row = detail.pixel(lon, lat)
    cells = set(zip(np.minimum(np.floor(col), detail.width - 2).astype(int),
                    np.minimum(np.floor(row), detail.height - 2).astype(int)))
    stats["cells"] = len(cells)
    stats["cells_total"] = (detail.width - 1) * (detail.height - 1)


def lonlat_range(patch):
    g = patch.grid.reshape(-1, 3)
    g = g[~np.isnan(g[:, 0])]
    lon, lat, _ = ecef_to_geodetic(g[:, 0], g[:, 1], g[:, 2])
    return lon.min(), lon.max(), lat.min(), lat.max()


def check_untouched(target_dir, target, target_children, merged_dir, merged, merged_children,
                    detail, failures, stats):
    """(d)."""
    matched = {k for k, p in target.items()
               if not target_children[k] and merged_children.get(k)}
    stats["matched"] = len(matched)
    if not matched:
        failures.add("no leaf of the target received new levels")
        return
    affected = set()
    for key in matched:
        d, x, y = key
        while d >= 0:
            affected.add((d, x, y))
            d, x, y = d - 1, x // 2, y // 2
    # B lies inside the matched leaves: every target leaf whose footprint meets B's raster is one.
    for key, patch in target.items():
        if target_children[key] or key in matched:
            continue
        lon0, lon1, lat0, lat1 = lonlat_range(patch)
        if (lon0 < detail.lon_range[1] and lon1 > detail.lon_range[0] and
                lat0 < detail.lat_range[1] and lat1 > detail.lat_range[0]):
            failures.add("%s: target leaf overlaps the detail raster but received no new levels" %
                         patch.folder)
    for key in merged:
        if key in target:
            continue
        d, x, y = key
        ancestor = None
        while d > 0:
            d, x, y = d - 1, x // 2, y // 2
            if (d, x, y) in matched:
                ancestor = (d, x, y)
                break
        if ancestor is None:
            failures.add("%s: new patch %d_%d_%d is not below a matched leaf" %
                         ((merged[key].folder,) + key))
    unchanged = 0
    for key, patch in target.items():
        if key not in merged:
            failures.add("%s: patch %d_%d_%d of the target is missing from the merged model" %
                         ((patch.folder,) + key))
            continue
        new_folder = merged[key].folder
        if key in affected:
            if new_folder == patch.folder:
                failures.add("%s: patch %d_%d_%d is in the affected subtree but kept its folder" %
                             ((patch.folder,) + key))
            continue
        if new_folder != patch.folder:
            failures.add("%s: patch %d_%d_%d outside the affected subtree moved to folder %s" %
                         ((patch.folder,) + key + (new_folder,)))
            continue
        before = folder_digest(os.path.join(target_dir, patch.folder))
        after = folder_digest(os.path.join(merged_dir, new_folder))
        if before != after:
            changed = sorted(set(before) ^ set(after) |
                             {f for f in set(before) & set(after) if before[f] != after[f]})
            failures.add("%s: files differ from the target's: %s" % (patch.folder,
                                                                      ", ".join(changed)))
            continue
        unchanged += 1
    stats["unchanged"] = unchanged
    stats["affected"] = len(affected)
    if unchanged == 0:
        failures.add("no patch outside the affected subtree: (d) checked nothing")


ARGS = None


class MergeCheck(unittest.TestCase):
    def test_the_merge_keeps_b_in_b_and_a_elsewhere(self):
        """(a) to (d) of the module's doc on `vsm merge A B --out`, validated."""
        failures = Failures()
        os.makedirs(ARGS.work, exist_ok=True)
        merged_dir = os.path.join(ARGS.work, "merged")
        subprocess.run(["rm", "-rf", merged_dir], check=True)
        target_before = tree_digest(ARGS.target)

        start = time.monotonic()
        merge = harness.vsm("merge", ARGS.target, ARGS.detail, "--out", merged_dir)
        merge_seconds = time.monotonic() - start
        if merge.returncode != 0:
            self.fail("vsm merge exited %d:\n%s%s" % (merge.returncode, merge.stdout, merge.stderr))
        print(merge.stdout.strip())
        validate = harness.vsm("validate", merged_dir)
        if validate.returncode != 0:
            failures.add("vsm validate %s exited %d: %s" % (merged_dir, validate.returncode,
                                                           validate.stdout.strip()[-2000:]))
        if tree_digest(ARGS.target) != target_before:
            failures.add("vsm merge --out modified the target %s" % ARGS.target)

        target_raster = GeoRaster(ARGS.target_raster)
        detail_raster = GeoRaster(ARGS.detail_raster)
        target_patches, target, target_children, n = load(ARGS.target, ARGS.patch_size, failures)
        merged_patches, merged, merged_children, n_merged = load(merged_dir, n, failures)
        if n_merged != n:
            failures.add("patch size %d after the merge, %d before" % (n_merged, n))
        stats = {"parent": 0.0, "parent_vertices": 0}
        check_placement(merged, merged_children, detail_raster, target_raster, failures, stats)
        check_parents(merged, merged_children, n, failures, stats)
        check_untouched(target_patches, target, target_children, merged_patches, merged,
                        merged_children, detail_raster, failures, stats)
        check_pro3d(merged_dir, failures)

        summary = (
            "%s: %d patches (target %d), depth %d (target %d), merge %.2f s; "
            "(a) %d vertices inside the detail raster in %d of its %d cells: bilinear distance max "
            "%.3f m, p99 %.3f m, mean %.3f m (tolerance %.2f m); nearer triangulation max %.3f m; "
            "(b) distance to the target's surface max %.1f m, mean %.1f m; (c) %d parent vertices, "
            "max parent-child %.2e m; (d) %d matched leaves, %d affected patches, %d patches "
            "byte-identical" %
            (merged_dir, len(merged), len(target), max(k[0] for k in merged),
             max(k[0] for k in target), merge_seconds, stats.get("vertices", 0),
             stats.get("cells", 0), stats.get("cells_total", 0), stats.get("bilinear_max", 0),
             stats.get("bilinear_p99", 0), stats.get("bilinear_mean", 0), PLACEMENT_TOLERANCE,
             stats.get("triangle_max", 0), stats.get("target_max", 0), stats.get("target_mean", 0),
             stats["parent_vertices"], stats["parent"], stats.get("matched", 0),
             stats.get("affected", 0), stats.get("unchanged", 0)))
        failures.assert_none(self, summary)


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--target", required=True)
    parser.add_argument("--target-raster", required=True)
    parser.add_argument("--detail", required=True)
    parser.add_argument("--detail-raster", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--patch-size", type=int, default=65,
                        help="used when the OPC does not state it")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
