#!/usr/bin/python3
"""Checks of a merged model along the true normal of a synthetic surface (surfaces.py), with
none of vsm's code: the OPC is read as merge_check.py reads it (check_import.py's reader, from
docs/OPC.md), the truth is the surface's closed form.

    /usr/bin/python3 surface_check.py --vsm <vsm> --surface <name> --merged <opc>

Checks (issue 33, "what must be true when it is done"); "over B" is B's extent in the surface's
(u, v) shrunk by one A sample, "away from B" is outside it grown by one A sample:
- on-B: every leaf vertex over B is within 1 cm of B's true surface (|h - fB(u, v)|, the
  distance along the base's normal);
- density: the distinct leaf vertices over B per m^2 (area on the base) are within 2x of B's
  samples per m^2 over the same region;
- bump: the highest leaf vertex within one sigma of the bump's centre reads at least 90 % of its
  0.3 m height above A's surface (the groove's depth read is reported beside it);
- on-A: every leaf vertex away from B is on A's true surface within A's own interpolation error
  (surfaces.Surface.interpolation_error, times 1.25) + 1 mm, and within A's (u, v) extent;
- seam: leaves that meet share their border vertices: on the lattice of the deepest level, every
  border vertex held by two leaves is the same point in both (within both patches' float32
  rounding), defined in both or in neither, and a finer leaf's border vertex between two
  vertices of a coarser neighbour lies on the straight edge between them (no crack at a
  T-junction);
- validate: `vsm validate` exits 0.

As a module: check(vsm, surface, merged_dir) -> list of Result.
"""

import argparse
import os
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import surfaces  # noqa: E402
from check_import import Failures  # noqa: E402
from merge_check import load  # noqa: E402

ON_B_TOLERANCE = 0.01   # m
DENSITY_FACTOR = 2.0
BUMP_FRACTION = 0.9


class Result:
    def __init__(self, name, ok, detail):
        self.name, self.ok, self.detail = name, ok, detail

    def __str__(self):
        return "%s %-8s %s" % ("ok  " if self.ok else "FAIL", self.name, self.detail)


def leaves(opc):
    """(leaf patches {key: Patch with .grid}, patch size n, reader failures)."""
    failures = Failures()
    _, patches, children_of, n = load(opc, 17, failures)
    return {k: p for k, p in patches.items() if not children_of[k]}, n, failures


def leaf_vertices(leaf):
    g = leaf.grid.reshape(-1, 3)
    return g[~np.isnan(g[:, 0])]


def distinct(points):
    """Points that differ by more than 0.1 mm (shared border vertices counted once)."""
    if len(points) == 0:
        return points
    keys = np.round(points / 1e-4).astype(np.int64)
    _, index = np.unique(keys, axis=0, return_index=True)
    return points[index]


def region_area(surface, grid_box, steps=400):
    """Area on the base of the (u, v) box (u0, u1, v0, v1), by the midpoint rule."""
    u0, u1, v0, v1 = grid_box
    u = u0 + (np.arange(steps) + 0.5) * (u1 - u0) / steps
    v = v0 + (np.arange(steps) + 0.5) * (v1 - v0) / steps
    uu, vv = np.meshgrid(u, v)
    return float(surface.area_element(uu, vv).mean() * (u1 - u0) * (v1 - v0))


def check_seam(leaf_patches, n):
    """The seam check (see the module doc): (failure messages, stats)."""
    problems = []
    depth = max(k[0] for k in leaf_patches)
    points = {}  # lattice (X, Y) -> [(position, rounding, key)]
    edges = []   # (lattice a, lattice b, step, pos a, pos b, rounding, key)
    for key, leaf in leaf_patches.items():
        d, x, y = key
        s = 1 << (depth - d)
        g = leaf.grid
        border = [(i, j) for j in (0, n - 1) for i in range(n)] + \
                 [(i, j) for i in (0, n - 1) for j in range(1, n - 1)]
        for i, j in border:
            lattice = ((x * (n - 1) + i) * s, (y * (n - 1) + j) * s)
            points.setdefault(lattice, []).append((g[j, i], leaf.rounding, key))
        if s > 1:
            for (j0, i0, dj, di) in ((0, 0, 0, 1), (n - 1, 0, 0, 1), (0, 0, 1, 0),
                                     (0, n - 1, 1, 0)):
                for t in range(n - 1):
                    ja, ia = j0 + dj * t, i0 + di * t
                    jb, ib = ja + dj, ia + di
                    la = ((x * (n - 1) + ia) * s, (y * (n - 1) + ja) * s)
                    lb = ((x * (n - 1) + ib) * s, (y * (n - 1) + jb) * s)
                    edges.append((la, lb, s, g[ja, ia], g[jb, ib], leaf.rounding, key))
    shared = mismatched = holes = 0
    worst = 0.0
    for lattice, entries in points.items():
        if len(entries) < 2:
            continue
        shared += 1
        defined = [e for e in entries if not np.isnan(e[0][0])]
        if defined and len(defined) != len(entries):
            holes += 1
            if holes <= 5:
                problems.append("lattice vertex %s defined in %s, undefined in %s" %
                                (lattice, [e[2] for e in defined],
                                 [e[2] for e in entries if np.isnan(e[0][0])]))
            continue
        for a in defined[1:]:
            dist = float(np.linalg.norm(a[0] - defined[0][0]))
            worst = max(worst, dist)
            if dist > a[1] + defined[0][1] + 1e-6:
                mismatched += 1
                if mismatched <= 5:
                    problems.append("border vertex at lattice %s differs by %.4f m between "
                                    "leaves %s and %s" % (lattice, dist, defined[0][2], a[2]))
    tjunctions = cracks = 0
    worst_t = 0.0
    for la, lb, s, pa, pb, rounding, key in edges:
        if np.isnan(pa[0]) or np.isnan(pb[0]):
            continue
        dx, dy = (lb[0] - la[0]) // s, (lb[1] - la[1]) // s
        for t in range(1, s):
            lattice = (la[0] + dx * t, la[1] + dy * t)
            for p, r, other in points.get(lattice, []):
                if np.isnan(p[0]):
                    continue
                tjunctions += 1
                expected = pa + (pb - pa) * (t / s)
                dist = float(np.linalg.norm(p - expected))
                worst_t = max(worst_t, dist)
                if dist > rounding + r + 1e-5:
                    cracks += 1
                    if cracks <= 5:
                        problems.append("T-junction crack of %.4f m at lattice %s: leaf %s's "
                                        "vertex is off leaf %s's edge" %
                                        (dist, lattice, other, key))
    if mismatched > 5 or holes > 5 or cracks > 5:
        problems.append("in all: %d differing shared vertices, %d defined on one side only, %d "
                        "T-junction cracks" % (mismatched, holes, cracks))
    return problems, {"shared": shared, "worst": worst, "tjunctions": tjunctions,
                      "worst_t": worst_t}


def check(vsm, surface, merged_dir):
    results = []
    validate = subprocess.run([vsm, "validate", merged_dir], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    results.append(Result("validate", validate.returncode == 0,
                          "vsm validate exit %d%s" % (validate.returncode,
                                                      (": " + validate.stdout.strip()[-300:])
                                                      if validate.returncode else "")))
    leaf_patches, n, failures = leaves(merged_dir)
    if failures.count:
        results.append(Result("read", False, "; ".join(failures.items[:5])))
    pts = np.concatenate([leaf_vertices(p) for p in leaf_patches.values()])
    a, b = surface.a, surface.b
    margin = max(a.du, a.dv)
    d_b, u, v = surface.distance_b(pts)
    d_a, _, _ = surface.distance_a(pts)
    over_b = b.inside(u, v, margin)
    away = ~b.inside(u, v, -margin)

    # on-B
    if over_b.any():
        err = np.abs(d_b[over_b])
        bad = err > ON_B_TOLERANCE
        results.append(Result(
            "on-B", not bad.any(),
            "%d of %d leaf vertices over B off B's surface by more than %.0f cm (max %.3f m, "
            "p99 %.4f m, mean %.4f m)" % (int(bad.sum()), int(over_b.sum()), ON_B_TOLERANCE * 100,
                                         err.max(), np.percentile(err, 99), err.mean())))
    else:
        results.append(Result("on-B", False, "no leaf vertex over B"))

    # density
    box = (b.u0 + margin, b.u1 - margin, b.v0 + margin, b.v1 - margin)
    area = region_area(surface, box)
    merged_count = len(distinct(pts[over_b]))
    bu, bv = b.mesh()
    b_count = int(b.inside(bu, bv, margin).sum())
    ratio = merged_count / b_count if b_count else 0.0
    leaf_depths = sorted({k[0] for k, p in leaf_patches.items()
                          if b.inside(*surface.coords(leaf_vertices(p))[:2], margin).any()})
    results.append(Result(
        "density", 1 / DENSITY_FACTOR <= ratio <= DENSITY_FACTOR,
        "%.0f vertices/m^2 over B, B has %.0f (ratio %.2f, allowed %.1f..%.1f); leaf depths over "
        "B %s" % (merged_count / area, b_count / area, ratio, 1 / DENSITY_FACTOR, DENSITY_FACTOR,
                  leaf_depths)))

    # bump (and the groove, reported)
    near = (u - surface.bump_u) ** 2 + (v - surface.bump_v) ** 2 <= surfaces.BUMP_SIGMA ** 2
    read = float((d_a[near]).max()) if near.any() else 0.0
    groove = over_b & (np.abs(u - surface.groove_u) <= b.du)
    groove_read = float(-d_a[groove].min()) if groove.any() else 0.0
    results.append(Result(
        "bump", read >= BUMP_FRACTION * surfaces.BUMP_HEIGHT,
        "reads %.3f m of %.2f m (%.0f %%, at least %.0f %% needed; %d vertices near its top); "
        "groove reads %.3f m of %.3f m" %
        (read, surfaces.BUMP_HEIGHT, 100 * read / surfaces.BUMP_HEIGHT, 100 * BUMP_FRACTION,
         int(near.sum()), groove_read, surfaces.GROOVE_DEPTH)))

    # on-A
    tol_a = 1.25 * surface.interpolation_error("A") + 0.001
    # A's chords at its border map a little outside its (u, v) extent where (u, v) are angles
    # (the boulder's latitude of a chord point is higher than its ends'), by about their distance
    # from the true surface: allowed as far as tol_a.
    outside_a = away & ~a.inside(u, v, -tol_a)
    err = np.abs(d_a[away])
    bad = (np.abs(d_a) > tol_a) & away
    results.append(Result(
        "on-A", not bad.any() and not outside_a.any(),
        "%d of %d leaf vertices away from B off A's surface by more than %.1f mm (max %.4f m); "
        "%d outside A's extent" % (int(bad.sum()), int(away.sum()), tol_a * 1e3,
                                   err.max() if len(err) else 0.0, int(outside_a.sum()))))

    # seam
    problems, stats = check_seam(leaf_patches, n)
    results.append(Result(
        "seam", not problems,
        "%d shared border vertices (max difference %.2e m), %d T-junction vertices (max off "
        "the edge %.2e m)%s" % (stats["shared"], stats["worst"], stats["tjunctions"],
                                stats["worst_t"], ("; " + "; ".join(problems)) if problems
                                else "")))
    return results


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--surface", required=True, choices=sorted(surfaces.SURFACES))
    parser.add_argument("--merged", required=True)
    args = parser.parse_args()
    results = check(args.vsm, surfaces.make(args.surface), args.merged)
    for r in results:
        print(r)
    return 0 if all(r.ok for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
