#!/usr/bin/python3
"""A merge keeps every detail sample, its border included (issue 18), checked independently.

    /usr/bin/python3 merge_border_test.py --vsm <vsm> --work <dir> [--case NAME ...]

Makes synthetic WGS 84 rasters with GDAL: a target A (65 x 65 samples, pixel 2^-15 degrees near
the equator, 17 x 17 patches) and detail rasters B of half A's pixel size lying inside A, so that
the merge's new leaves have a vertex on B's pixel centres (B's grid lines up with the new leaves):
- aligned: B's pixel centres on the new vertices, all four borders included;
- +1e-9, -1e-9: B shifted by that many of its pixels (both axes): on the vertices up to noise;
- +0.5, -0.5: B's pixel centres midway between new vertices (both axes);
- lon+0.5: shifted in longitude only, so B's north and south borders run along vertex rows
  between B's samples;
- holes: aligned, with no-data samples inside B (a single one, one on a seam between B's patches,
  a 2 x 2 block);
every B is 37 x 41 samples imported with 17 x 17 patches, i.e. a detail model of several patches
(3 x 3 leaves), so B's seams are checked too. B's heights are 5 to 9 m above or below A's, so a
vertex that lost B's surface is metres away from it.

Each case: `vsm import` both, `vsm merge A B --out`, then the merged OPC is read with
check_import.py's reader (none of vsm's code) and compared with the rasters read by GDAL:
(1) samples: every defined sample of B that a merged leaf vertex lies on (within 1e-3 of B's
    pixels, after converting the vertex to lon/lat) is there at B's height, unless it lies in
    the seam band (below) on A's surface; a sample is lost when some leaf vertex on it is not.
    The merge places each new vertex along the normal of A's subdivided surface (issue 33), not
    along the vertical: over this tilted A, B's samples 5 to 9 m off it are met beside the
    vertical through A's vertex, so they are no longer all vertices (the counts are printed);
(2) surface: every leaf vertex on B's surface, or outside it by at most 1e-3 of B's pixels, is at
    B's height at its own lon/lat: B's surface as core/merge/README.md defines it, computed here
    from the raster (bilinear in cells with four defined samples, the triangle of the other three
    where one is undefined, a point just outside clamped onto the nearest cell). In the seam
    band, within SEAM_BAND of B's pixels of its border or a hole, a vertex may instead keep A's
    surface: its ray along A's normal, tilted by A's slope, passes B's border there (the band's
    width is the largest gap between A and B times the tangent of A's steepest slope);
(3) outside: every leaf vertex farther than 0.25 of B's pixels from any cell of B with surface
    (beyond B's hull or in a hole) keeps A's surface (A's bilinear height at its lon/lat): a ray
    from there along A's normal meets no part of B.
Height tolerance: float32 rounding of the vertex's patch (16 x 2^-23 x its largest absolute
local coordinate, a few micrometres here) plus 1e-6 m; in (3) 1e-4 m more (A's new vertices
interpolate its ECEF vertices along chords, not its geodetic bilinear surface).

Prints one line per case with its counts (samples on vertices, lost samples, border samples);
exit 1 when any case has a failure.
"""

import argparse
import os
import subprocess
import sys
import unittest

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from check_import import Failures  # noqa: E402
import harness  # noqa: E402
from harness import write_raster  # noqa: E402
from merge_check import GeoRaster, leaf_points, load  # noqa: E402

gdal.UseExceptions()

PATCH = 17
A_SIZE = 65
A_PIXEL = 2.0 ** -15          # degrees (about 3.4 m)
B_PIXEL = A_PIXEL / 2
A_WEST, A_NORTH = 10.0, 0.001
B_WIDTH, B_HEIGHT = 37, 41    # 3 x 3 patches of 17 x 17
B_FIRST = (12, 10)            # A's pixel (column, row) under B's first pixel centre, unshifted
NODATA = -9999.0
ON_VERTEX = 1e-3              # B pixels: a vertex this close to a sample lies on it
NEAR_HULL = 1e-3              # B pixels: within this outside the hull counts as on the border
OUTSIDE = 0.25                # B pixels: beyond this outside the hull it is the target's
METRES_PER_DEGREE = 6378137.0 * np.pi / 180  # at the equator, in longitude and latitude

CASES = {
    "aligned": (0.0, 0.0, []),
    "+1e-9": (1e-9, 1e-9, []),
    "-1e-9": (-1e-9, -1e-9, []),
    "+0.5": (0.5, 0.5, []),
    "-0.5": (-0.5, -0.5, []),
    "lon+0.5": (0.5, 0.0, []),
    # (column, row) of B's no-data samples: one inside, one on the seam column 16 between B's
    # patches, a 2 x 2 block.
    "holes": (0.0, 0.0, [(7, 9), (16, 27), (25, 14), (26, 14), (25, 15), (26, 15)]),
}


def a_height(col, row):
    """A's heights at fractional A pixel (column, row): a gentle tilted, curved surface."""
    return 200.0 + 0.3 * col - 0.2 * row + 0.004 * (col - 30.0) ** 2


def seam_band():
    """B's pixels from its border or a hole within which a vertex may keep A's surface: the
    largest gap between B and A (9 m) times the tangent of A's steepest slope, plus a tenth."""
    rows, cols = np.mgrid[0:A_SIZE, 0:A_SIZE].astype(np.float64)
    heights = a_height(cols, rows)
    pixel = A_PIXEL * METRES_PER_DEGREE
    slope = np.hypot(*np.gradient(heights, pixel)).max()
    return 9.0 * slope / (B_PIXEL * METRES_PER_DEGREE) + 0.1


SEAM_BAND = seam_band()


def make_target(path):
    rows, cols = np.mgrid[0:A_SIZE, 0:A_SIZE].astype(np.float64)
    write_raster(path, a_height(cols, rows), A_WEST, A_NORTH, A_PIXEL)


def make_detail(path, shift_lon, shift_lat, holes):
    """B: its first pixel centre on A's pixel centre B_FIRST plus the shift (in B pixels)."""
    rows, cols = np.mgrid[0:B_HEIGHT, 0:B_WIDTH].astype(np.float64)
    # Where B's samples lie in A's pixels, for heights that differ from A's everywhere.
    a_cols = B_FIRST[0] + (cols + shift_lon) / 2
    a_rows = B_FIRST[1] + (rows + shift_lat) / 2
    # 5 to 9 m above or below A, the side changing irregularly: a border vertex at A's height
    # lies below or above B's sample, so projected along one up direction it falls on either
    # side of B's border (as in the real merge).
    side = np.where(np.sin(0.9 * cols + 1.3 * rows + 0.4) > 0, 1.0, -1.0)
    heights = a_height(a_cols, a_rows) + side * (7.0 + 2.0 * np.sin(0.7 * cols) *
                                                 np.cos(0.5 * rows))
    for c, r in holes:
        heights[r, c] = NODATA
    west = A_WEST + (B_FIRST[0] + 0.5) * A_PIXEL + (shift_lon - 0.5) * B_PIXEL
    north = A_NORTH - (B_FIRST[1] + 0.5) * A_PIXEL - (shift_lat - 0.5) * B_PIXEL
    write_raster(path, heights, west, north, B_PIXEL, NODATA if holes else None)


def leaf_vertices(patches, children_of):
    """(lon, lat, height, tolerance, depth) of every defined vertex of every leaf."""
    out = [[], [], [], [], []]
    for key, patch, lon, lat, h in leaf_points(patches, children_of):
        for target, values in zip(out, (lon, lat, h)):
            target.append(values)
        out[3].append(np.full(len(h), 16 * patch.rounding + 1e-6))
        out[4].append(np.full(len(h), key[0]))
    return [np.concatenate(values) for values in out]


def bilinear(heights, col, row):
    """Bilinear heights between pixel centres at fractional (col, row), clamped onto the grid."""
    rows, cols = heights.shape
    col = np.clip(col, 0, cols - 1)
    row = np.clip(row, 0, rows - 1)
    c0 = np.clip(np.floor(col).astype(np.int64), 0, cols - 2)
    r0 = np.clip(np.floor(row).astype(np.int64), 0, rows - 2)
    u, v = col - c0, row - r0
    return (heights[r0, c0] * (1 - u) * (1 - v) + heights[r0, c0 + 1] * u * (1 - v) +
            heights[r0 + 1, c0] * (1 - u) * v + heights[r0 + 1, c0 + 1] * u * v)


CORNERS = ((0, 0), (1, 0), (0, 1), (1, 1))


def on_cell(heights, c0, r0, col, row):
    """(distance outside the cell in B's pixels, height) of B's surface in cell (c0, r0) at its
    point nearest to (col, row), as core/merge/README.md defines the surface: bilinear in a cell
    with four defined corners (the parameter clamped onto [0, 1]^2), the triangle of the other
    three where one corner is undefined (barycentric coordinates clamped at 0 and re-normalised);
    None where the cell has no surface."""
    z = [heights[r0 + dr, c0 + dc] for dc, dr in CORNERS]
    defined = [np.isfinite(value) for value in z]
    u, v = col - c0, row - r0
    if all(defined):
        cu, cv = min(max(u, 0.0), 1.0), min(max(v, 0.0), 1.0)
        return (np.hypot(u - cu, v - cv), z[0] * (1 - cu) * (1 - cv) + z[1] * cu * (1 - cv) +
                z[2] * (1 - cu) * cv + z[3] * cu * cv)
    if sum(defined) != 3:
        return None
    (ax, ay), (bx, by), (cx, cy) = [CORNERS[i] for i in range(4) if defined[i]]
    za, zb, zc = [z[i] for i in range(4) if defined[i]]
    d = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    l1 = ((u - ax) * (cy - ay) - (v - ay) * (cx - ax)) / d
    l2 = ((bx - ax) * (v - ay) - (by - ay) * (u - ax)) / d
    lam = np.array([1 - l1 - l2, l1, l2])
    clamped = np.maximum(lam, 0.0)
    clamped /= clamped.sum()
    moved = lam - clamped
    distance = np.hypot(moved @ [ax, bx, cx], moved @ [ay, by, cy])
    return distance, clamped @ [za, zb, zc]


def detail_surface(heights, col, row, reach):
    """Heights of B's surface at the cells within `reach` pixels of each point (col, row): a list
    per point, empty where B has no surface that near."""
    rows, cols = heights.shape
    out = []
    for c, r in zip(col, row):
        found = []
        for c0 in range(max(int(np.floor(c - reach)), 0),
                        min(int(np.floor(c + reach)), cols - 2) + 1):
            for r0 in range(max(int(np.floor(r - reach)), 0),
                            min(int(np.floor(r + reach)), rows - 2) + 1):
                hit = on_cell(heights, c0, r0, c, r)
                if hit is not None and hit[0] <= reach:
                    found.append(hit[1])
        out.append(found)
    return out


def check_case(merged, target_raster, detail_raster):
    """Counts and failure messages of one merged model."""
    patches, children_of = merged
    lon, lat, h, tol, depth = leaf_vertices(patches, children_of)
    col, row = detail_raster.pixel(lon, lat)
    heights = detail_raster.heights
    rows, cols = heights.shape
    failures = []
    counts = {}

    # Every leaf vertex near B: B's surface heights within NEAR_HULL (it must take one of them),
    # and whether B has surface within OUTSIDE (else it must keep A's).
    near = ((col > -1) & (col < cols) & (row > -1) & (row < rows))
    index = np.nonzero(near)[0]
    on_surface = np.zeros(len(col), dtype=bool)
    matches = np.zeros(len(col), dtype=bool)
    error = np.full(len(col), np.inf)
    candidates = detail_surface(heights, col[index], row[index], NEAR_HULL)
    for i, found in zip(index, candidates):
        if found:
            on_surface[i] = True
            error[i] = min(abs(h[i] - value) for value in found)
            matches[i] = error[i] <= tol[i]
    reached = np.zeros(len(col), dtype=bool)
    for i, found in zip(index, detail_surface(heights, col[index], row[index], OUTSIDE)):
        reached[i] = bool(found)
    # The seam band, where a vertex may keep A's surface instead (it must then be on A's).
    edge = np.minimum.reduce([col, cols - 1 - col, row, rows - 1 - row])
    for r, c in zip(*np.nonzero(~np.isfinite(heights))):
        edge = np.minimum(edge, np.maximum(np.abs(col - c), np.abs(row - r)) - 1)
    a_col, a_row = target_raster.pixel(lon, lat)
    on_target = np.abs(h - bilinear(target_raster.heights, a_col, a_row)) <= tol + 1e-4
    seam = (edge <= SEAM_BAND) & on_target

    # (1) samples.
    near_c, near_r = np.rint(col), np.rint(row)
    on = ((np.abs(col - near_c) <= ON_VERTEX) & (np.abs(row - near_r) <= ON_VERTEX) &
          (near_c >= 0) & (near_c <= cols - 1) & (near_r >= 0) & (near_r <= rows - 1))
    ci, ri = near_c[on].astype(np.int64), near_r[on].astype(np.int64)
    defined_on = np.isfinite(heights[ri, ci])
    wrong = ~matches[on] & ~seam[on]
    found = np.zeros(heights.shape, dtype=bool)
    lost = np.zeros(heights.shape, dtype=bool)
    found[ri[defined_on], ci[defined_on]] = True
    lost[ri[defined_on & wrong], ci[defined_on & wrong]] = True
    defined = np.isfinite(heights)
    border = np.zeros(heights.shape, dtype=bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    for r, c in zip(*np.nonzero(~defined)):
        border[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2] = True
    border &= defined
    counts["samples"] = int(defined.sum())
    counts["on_vertices"] = int(found.sum())
    counts["border_on_vertices"] = int((found & border).sum())
    counts["lost"] = int(lost.sum())
    counts["lost_border"] = int((lost & border).sum())
    if lost.any():
        r, c = np.argwhere(lost)[0]
        failures.append("%d samples of B lost (%d on its borders), e.g. (col %d, row %d) = %.3f m" %
                        (counts["lost"], counts["lost_border"], c, r, heights[r, c]))

    # (2) every leaf vertex on B's surface (within NEAR_HULL of a cell that has surface), or in
    # the seam band on A's.
    bad = on_surface & ~matches & ~seam
    counts["inside"] = int(on_surface.sum())
    counts["inside_wrong"] = int(bad.sum())
    counts["seam"] = int((on_surface & ~matches & seam).sum())
    kept = on_surface & matches
    counts["inside_max_error"] = float(error[kept].max()) if kept.any() else 0.0
    if bad.any():
        failures.append("%d of %d leaf vertices on B's surface (or within %g of its pixels "
                        "outside it) are off it (max %.6f m)" %
                        (int(bad.sum()), counts["inside"], NEAR_HULL, counts["inside_max_error"]))

    # (3) outside: farther than OUTSIDE from any cell of B with surface, the target's surface.
    away = ~reached
    a_col, a_row = target_raster.pixel(lon[away], lat[away])
    coarse = bilinear(target_raster.heights, a_col, a_row)
    a_error = np.abs(h[away] - coarse)
    # A's new vertices interpolate A's ECEF vertices: a chord, within micrometres of the
    # geodetic bilinear surface over cells of a few metres.
    bad = ~(a_error <= tol[away] + 1e-4)
    counts["outside"] = int(away.sum())
    counts["outside_wrong"] = int(bad.sum())
    if bad.any():
        failures.append("%d of %d leaf vertices more than %g of B's pixels away from B's surface "
                        "are off A's surface (max %.6f m)" %
                        (int(bad.sum()), counts["outside"], OUTSIDE, float(a_error.max())))
    counts["depth"] = int(depth.max())
    return counts, failures


ARGS = None


class MergeBorder(unittest.TestCase):
    def test_detail_samples_on_vertices_are_kept(self):
        """Each case (shifts, holes) merged into A: every detail sample on a leaf vertex keeps
        its height."""
        os.makedirs(ARGS.work, exist_ok=True)

        target_tif = os.path.join(ARGS.work, "target.tif")
        target_opc = os.path.join(ARGS.work, "target")
        make_target(target_tif)
        subprocess.run(["rm", "-rf", target_opc], check=True)
        harness.import_dem(target_tif, target_opc, PATCH)
        target_raster = GeoRaster(target_tif)

        total_failures = 0
        case_verdicts = []
        totals = {"lost": 0, "lost_border": 0, "border_on_vertices": 0}
        for name in ARGS.case or list(CASES):
            shift_lon, shift_lat, holes = CASES[name]
            directory = os.path.join(ARGS.work, name)
            subprocess.run(["rm", "-rf", directory], check=True)
            os.makedirs(directory)
            detail_tif = os.path.join(directory, "detail.tif")
            detail_opc = os.path.join(directory, "detail")
            merged_opc = os.path.join(directory, "merged")
            make_detail(detail_tif, shift_lon, shift_lat, holes)
            harness.import_dem(detail_tif, detail_opc, PATCH)
            harness.vsm("merge", target_opc, detail_opc, "--out", merged_opc, check=True)
            validate = harness.vsm("validate", merged_opc)
            failures = []
            if validate.returncode != 0:
                failures.append("vsm validate exited %d: %s" % (
                    validate.returncode, (validate.stdout + validate.stderr).strip()[-1000:]))
            load_failures = Failures()
            _, patches, children_of, _ = load(merged_opc, PATCH, load_failures)
            failures += load_failures.items
            counts, case_failures = check_case((patches, children_of), target_raster,
                                               GeoRaster(detail_tif))
            failures += case_failures
            for key in totals:
                totals[key] += counts[key]
            print("%s %s: %d samples, %d on leaf vertices (%d on B's borders), lost %d (%d on "
                  "borders); %d vertices inside (max error %.2e m, %d wrong, %d on A in the seam "
                  "band of %.2f pixels), %d outside (%d wrong); depth %d" %
                  ("FAIL" if failures else "OK", name, counts["samples"], counts["on_vertices"],
                   counts["border_on_vertices"], counts["lost"], counts["lost_border"],
                   counts["inside"], counts["inside_max_error"], counts["inside_wrong"],
                   counts["seam"], SEAM_BAND, counts["outside"], counts["outside_wrong"], counts["depth"]))
            for message in failures:
                print("  FAIL " + message)
            total_failures += len(failures)
            case_verdicts.append((name, failures))
        print("total: %d samples lost (%d on borders) of %d border samples on vertices; %d failures" %
              (totals["lost"], totals["lost_border"], totals["border_on_vertices"], total_failures))
        for name, failures in case_verdicts:
            with self.subTest(name):
                self.assertEqual(failures, [], name)


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--case", action="append", choices=sorted(CASES),
                        help="run only these cases (default: all)")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
