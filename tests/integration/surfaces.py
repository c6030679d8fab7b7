#!/usr/bin/python3
"""Synthetic rock surfaces for issue 33: organized point clouds (PCD) with their true surface known
in closed form, written without any of vsm's code.

    /usr/bin/python3 surfaces.py <surface> <out-dir>     writes <out-dir>/A.pcd and B.pcd
    /usr/bin/python3 surfaces.py --list

Surfaces (local frame in metres, z up): `ground` (flat ground, the height field today's merge
handles: the checks' control on a real merge), `face` (a vertical rock face), `overhang` (a face
leaning 20 degrees past vertical), `tunnel` (a horseshoe: 240 degrees of a 3 m circle about a
horizontal axis; the detail sits on the wall where it is vertical, so the ceiling above it folds
over it seen along z) and `boulder` (a zone of a 4 m sphere about a horizontal axis, from 120
degrees on one side over the top to 120 degrees on the other: the top is terrain-like, the flanks
vertical, their lower parts overhang; the detail sits where the flank turns past vertical).

Every surface is a base surface (plane, cylinder or sphere) with parameters (u, v) in metres of
arc length along it and a unit normal N(u, v), displaced along N by a height f(u, v):

    S(u, v) = base(u, v) + f(u, v) N(u, v)

`coords(p)` inverts the base in closed form: the (u, v) of the base point below p and p's height
h along N (for a plane the exact offset; for the cylinder and the sphere the radial distance to
the base). So `h - f(u, v)` is p's signed distance to S along the true normal of the base: p and
S(u, v) lie on the same normal line, so |h - f| bounds p's distance to S from above, and a check
of |h - f| <= tol needs no sampling of S at all. `foot(p)` is that point S(u, v).

A, the coarse scan, samples S with f = fA (a gentle undulation, the same in both scans). B, the
detail, samples 4x finer over part of A (its lattice not aligned with A's) with f = fB = fA plus
two features A does not have:
- a bump: a Gaussian of 0.3 m height (sigma 0.4 m) along N;
- a groove: a V 4 cm deep along v whose kinks lie on three neighbouring columns of B's lattice
  (half its depth is one B sample wide). B's bilinear interpolation reproduces it exactly, so a
  vertex placed anywhere on B's surface is on S, and the groove is the finest thing B resolves.
B's bilinear surface errs by at most 2 mm (the bump's curvature, M h^2 / 8 along a cell's
diagonal), A's by up to 6 mm on the boulder (the sphere's chord); `interpolation_error` measures
both, and the check "on A" allows A's own error.
"""

import argparse
import math
import os
import sys

import numpy as np

BUMP_HEIGHT = 0.3    # m
BUMP_SIGMA = 0.4     # m
GROOVE_DEPTH = 0.04  # m
FINER = 4            # B's spacing is A's / 4


class Grid:
    """A lattice in parameter space: u0 + i du for i < nu, v0 + j dv for j < nv."""

    def __init__(self, u0, du, nu, v0, dv, nv):
        self.u0, self.du, self.nu, self.v0, self.dv, self.nv = u0, du, nu, v0, dv, nv

    @property
    def u1(self):
        return self.u0 + (self.nu - 1) * self.du

    @property
    def v1(self):
        return self.v0 + (self.nv - 1) * self.dv

    def mesh(self):
        """(u, v), each of shape (nv, nu): row j, column i."""
        u = self.u0 + np.arange(self.nu) * self.du
        v = self.v0 + np.arange(self.nv) * self.dv
        return np.meshgrid(u, v)

    def inside(self, u, v, margin=0.0):
        return ((u >= self.u0 + margin) & (u <= self.u1 - margin) &
                (v >= self.v0 + margin) & (v <= self.v1 - margin))


class Surface:
    """A base with normal coordinates, a coarse grid A and a detail grid B (see the module doc)."""

    name = ""
    description = ""

    def __init__(self, a, b_start, b_size, bump_at, groove_at):
        """a: A's Grid; b_start (u, v) and b_size (metres along u, v): B's extent; bump_at and
        groove_at: the bump's centre and the groove's u, as fractions of B's extent."""
        self.a = a
        du, dv = a.du / FINER, a.dv / FINER
        self.b = Grid(b_start[0], du, int(round(b_size[0] / du)) + 1,
                      b_start[1], dv, int(round(b_size[1] / dv)) + 1)
        self.bump_u = self.b.u0 + bump_at[0] * (self.b.u1 - self.b.u0)
        self.bump_v = self.b.v0 + bump_at[1] * (self.b.v1 - self.b.v0)
        # The groove's bottom on a column of B's lattice.
        self.groove_column = int(round(groove_at * (self.b.nu - 1)))
        self.groove_u = self.b.u0 + self.groove_column * self.b.du

    # -- the base: overridden --

    def base(self, u, v):
        """(points, unit normals), shape (..., 3)."""
        raise NotImplementedError

    def coords(self, p):
        """(u, v, h) of points p (..., 3): the base point below p and the height along N."""
        raise NotImplementedError

    def area_element(self, u, v):
        """dA / (du dv) of the base at (u, v)."""
        return np.ones_like(u)

    def radius(self):
        """The base's smallest radius of curvature (inf for a plane)."""
        return math.inf

    # -- heights --

    def undulation(self, u, v):
        return 0.15 * np.sin(2 * math.pi * u / 11.0) * np.cos(2 * math.pi * v / 13.0)

    def bump(self, u, v):
        r2 = (u - self.bump_u) ** 2 + (v - self.bump_v) ** 2
        return BUMP_HEIGHT * np.exp(-r2 / (2 * BUMP_SIGMA ** 2))

    def groove(self, u, v):
        t = np.abs(u - self.groove_u) / self.b.du
        return -GROOVE_DEPTH * np.maximum(0.0, 1.0 - t) + 0.0 * v

    def f_a(self, u, v):
        return self.undulation(u, v)

    def f_b(self, u, v):
        return self.undulation(u, v) + self.bump(u, v) + self.groove(u, v)

    def point(self, u, v, f):
        p, n = self.base(u, v)
        return p + f[..., None] * n

    def distance_a(self, p):
        """Signed distance along the true normal to A's true surface, and (u, v)."""
        u, v, h = self.coords(p)
        return h - self.f_a(u, v), u, v

    def distance_b(self, p):
        u, v, h = self.coords(p)
        return h - self.f_b(u, v), u, v

    # -- the scans --

    def grid_points(self, which):
        grid = self.a if which == "A" else self.b
        u, v = grid.mesh()
        f = self.f_a(u, v) if which == "A" else self.f_b(u, v)
        return self.point(u, v, f)

    def interpolation_error(self, which):
        """Largest distance along N between the grid's bilinear surface and the true one, at the
        cell centres and edge midpoints (where bilinear interpolation errs most)."""
        pts = self.grid_points(which)
        worst = 0.0
        mids = [0.5 * (pts[:, :-1] + pts[:, 1:]), 0.5 * (pts[:-1, :] + pts[1:, :]),
                0.25 * (pts[:-1, :-1] + pts[1:, :-1] + pts[:-1, 1:] + pts[1:, 1:])]
        f = self.f_a if which == "A" else self.f_b
        for m in mids:
            u, v, h = self.coords(m)
            worst = max(worst, float(np.abs(h - f(u, v)).max()))
        return worst

    def foot(self, p):
        """The point of B's true surface along the base's normal through p."""
        u, v, _ = self.coords(p)
        return self.point(u, v, self.f_b(u, v))

    def ideal_points(self, with_b=True):
        """What a merge along the surface should give, as one grid: A's lattice refined 4x over
        A's whole extent, on B's true surface over B's extent and on A's elsewhere (the checks'
        positive control: imported as it is, it must pass them). Without B: A refined alone (a
        negative control: on-B and bump must fail)."""
        a = self.a
        fine = Grid(a.u0, a.du / FINER, FINER * (a.nu - 1) + 1, a.v0, a.dv / FINER,
                    FINER * (a.nv - 1) + 1)
        u, v = fine.mesh()
        f = np.where(self.b.inside(u, v) & with_b, self.f_b(u, v), self.f_a(u, v))
        return self.point(u, v, f)

    def write(self, directory):
        os.makedirs(directory, exist_ok=True)
        for which in ("A", "B"):
            write_pcd(os.path.join(directory, which + ".pcd"), self.grid_points(which))


class Plane(Surface):
    """A plane through `origin` spanned by unit eu (along u) and ev (along v); N = eu x ev."""

    def __init__(self, origin, eu, ev, **kw):
        self.origin = np.asarray(origin, float)
        self.eu = np.asarray(eu, float)
        self.ev = np.asarray(ev, float)
        self.n = np.cross(self.eu, self.ev)
        super().__init__(**kw)

    def base(self, u, v):
        p = self.origin + u[..., None] * self.eu + v[..., None] * self.ev
        return p, np.broadcast_to(self.n, p.shape)

    def coords(self, p):
        d = p - self.origin
        return d @ self.eu, d @ self.ev, d @ self.n


class Ground(Plane):
    name = "ground"
    description = "flat ground (plane z = 0, facing up), 16 x 16 m: the height field of today"

    def __init__(self):
        a = Grid(0.0, 0.25, 65, 0.0, 0.25, 65)
        super().__init__(origin=(0, 0, 0), eu=(1, 0, 0), ev=(0, 1, 0), a=a,
                         b_start=(5.31, 5.17), b_size=(4.5, 4.5), bump_at=(0.33, 0.5),
                         groove_at=0.75)


class Face(Plane):
    name = "face"
    description = "vertical rock face (plane y = 0, facing -y), 16 x 16 m"

    def __init__(self):
        a = Grid(0.0, 0.25, 65, 0.0, 0.25, 65)
        super().__init__(origin=(0, 0, 0), eu=(1, 0, 0), ev=(0, 0, 1), a=a,
                         b_start=(5.31, 5.17), b_size=(4.5, 4.5), bump_at=(0.33, 0.5),
                         groove_at=0.75)


class RockFace(Face):
    """The vertical face with a rock's relief at B's scale (0.4 m, wavelengths of 3.1 and 3.7 m),
    which both scans see: enough shape for ICP to find a misplaced detail scan back along the
    face, where a flat face (a plane slides on itself) gives it nothing to hold."""

    name = "rockface"
    description = "vertical rock face with 0.4 m relief at a 3 m scale, 16 x 16 m"

    def undulation(self, u, v):
        return (0.4 * np.sin(2 * math.pi * u / 3.1) * np.cos(2 * math.pi * v / 3.7) +
                super().undulation(u, v))


class Overhang(Plane):
    name = "overhang"
    description = "face leaning 20 degrees past vertical (its top over -y), 16 x 16 m"

    def __init__(self):
        lean = math.radians(20.0)
        a = Grid(0.0, 0.25, 65, 0.0, 0.25, 65)
        super().__init__(origin=(0, 0, 0), eu=(1, 0, 0),
                         ev=(0, -math.sin(lean), math.cos(lean)), a=a,
                         b_start=(5.31, 5.17), b_size=(4.5, 4.5), bump_at=(0.33, 0.5),
                         groove_at=0.75)


class Tunnel(Surface):
    """Cylinder about the x axis at height ZC, radius R; v = R phi, phi the angle from the top
    towards +y; N points inwards (towards the axis), so a bump juts into the tunnel."""

    name = "tunnel"
    R = 3.0
    ZC = 4.0
    description = "horseshoe tunnel: 240 degrees of a 3 m circle about the x axis, 16 m long"

    def __init__(self):
        arc = self.R * math.radians(240.0)
        nv = 49
        a = Grid(0.0, 0.25, 65, -arc / 2, arc / (nv - 1), nv)
        wall = self.R * math.pi / 2  # phi = 90 degrees: the wall is vertical
        # B from phi = 33 to 117 degrees, inside A's 120 (it once reached 132: vsm now refuses a
        # detail that leaves the target's surface, and says where).
        super().__init__(a=a, b_start=(5.31, wall - 3.0), b_size=(4.5, 4.4),
                         bump_at=(0.33, 0.5), groove_at=0.75)

    def base(self, u, v):
        phi = v / self.R
        s, c = np.sin(phi), np.cos(phi)
        p = np.stack([u, self.R * s, self.ZC + self.R * c], axis=-1)
        n = np.stack([np.zeros_like(u), -s, -c], axis=-1)
        return p, n

    def coords(self, p):
        y, z = p[..., 1], p[..., 2] - self.ZC
        return p[..., 0], self.R * np.arctan2(y, z), self.R - np.hypot(y, z)

    def radius(self):
        return self.R


class Boulder(Surface):
    """Sphere of radius R about (0, 0, ZC); u = R lam (lam the angle from the top about the x
    axis, towards +y), v = R beta (beta the latitude towards +x); N outwards."""

    name = "boulder"
    R = 4.0
    ZC = 0.0
    description = ("boulder: a zone of a 4 m sphere, +-45 degrees about the x axis, 120 degrees "
                   "each side of the top")

    def __init__(self):
        ulen = self.R * math.radians(240.0)
        vlen = self.R * math.radians(90.0)
        nu, nv = 67, 25
        a = Grid(-ulen / 2, ulen / (nu - 1), nu, -vlen / 2, vlen / (nv - 1), nv)
        flank = self.R * math.radians(95.0)  # just past vertical
        super().__init__(a=a, b_start=(flank - 1.6, -1.5), b_size=(3.2, 3.0),
                         bump_at=(0.35, 0.5), groove_at=0.8)

    def base(self, u, v):
        lam, beta = u / self.R, v / self.R
        d = np.stack([np.sin(beta), np.cos(beta) * np.sin(lam), np.cos(beta) * np.cos(lam)],
                     axis=-1)
        return np.array([0.0, 0.0, self.ZC]) + self.R * d, d

    def coords(self, p):
        x, y, z = p[..., 0], p[..., 1], p[..., 2] - self.ZC
        r = np.sqrt(x * x + y * y + z * z)
        return (self.R * np.arctan2(y, z), self.R * np.arcsin(np.clip(x / r, -1, 1)),
                r - self.R)

    def area_element(self, u, v):
        return np.cos(v / self.R)

    def radius(self):
        return self.R

    def undulation(self, u, v):
        return 0.08 * np.sin(2 * math.pi * u / 7.0) * np.cos(2 * math.pi * v / 5.0)


SURFACES = {cls.name: cls for cls in (Ground, Face, Overhang, Tunnel, Boulder)}
# Surfaces made for one check only (not in the default list).
EXTRA = {cls.name: cls for cls in (RockFace,)}


def make(name):
    return {**SURFACES, **EXTRA}[name]()


def write_pcd(path, points):
    """An organized binary PCD (x y z float32; NaN rows allowed): points of shape (rows, cols, 3),
    the rows being PCD's HEIGHT."""
    rows, cols = points.shape[:2]
    header = ("# .PCD v0.7 - issue 33 test surface\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
              "TYPE F F F\nCOUNT 1 1 1\nWIDTH %d\nHEIGHT %d\nVIEWPOINT 0 0 0 1 0 0 0\n"
              "POINTS %d\nDATA binary\n" % (cols, rows, rows * cols))
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(points, dtype="<f4").tobytes())


def read_pcd(path):
    """(rows, cols, 3) float64 from a PCD written by write_pcd."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"DATA binary\n") + len(b"DATA binary\n")
    header = data[:end].decode("ascii").split("\n")
    fields = dict(line.split(" ", 1) for line in header if line and not line.startswith("#"))
    cols, rows = int(fields["WIDTH"]), int(fields["HEIGHT"])
    values = np.frombuffer(data, dtype="<f4", offset=end, count=rows * cols * 3)
    return values.reshape(rows, cols, 3).astype(np.float64)


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("surface", nargs="?", choices=sorted(SURFACES))
    parser.add_argument("out", nargs="?")
    parser.add_argument("--list", action="store_true")
    args = parser.parse_args()
    if args.list or not args.surface:
        for name, cls in SURFACES.items():
            s = cls()
            print("%-8s %s; A %dx%d, B %dx%d; interpolation error A %.2f mm, B %.2f mm" %
                  (name, cls.description, s.a.nu, s.a.nv, s.b.nu, s.b.nv,
                   1e3 * s.interpolation_error("A"), 1e3 * s.interpolation_error("B")))
        return 0
    make(args.surface).write(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
