#!/usr/bin/python3
"""Turning changes nothing (issue 33): the real merge of PRISM and Jacksboro as organized point
clouds in a local east-north-up frame, turned as a whole about the east axis, merged by the real
`vsm`, turned back and compared with the unturned merge.

    /usr/bin/python3 turned_merge.py --vsm <vsm> --data <shared/data> --work <dir>
                                     [--angles 0,45,75,90,95,135,180]

The clouds (with none of vsm's code): A is a 33 x 33 crop of PRISMelevation.tif centred on
Jacksboro (about 120 x 150 km, 4 km samples), B the whole jacksboro_fault_dem.tif (403 x 344,
90 m); every pixel centre's lon/lat/height goes to WGS 84 ECEF and then to east-north-up metres
about Jacksboro's centre at 500 m (rows of the cloud are the raster's rows). Each angle turns
both clouds by the same rotation about the east (x) axis through that origin and writes them as
binary PCD (float32, as PCL reads them); `vsm import` (A with 17 x 17 patches, B with 65 x 65,
no texture) and `vsm merge --out` follow.

Checks
- angle 0, the terrain merge of today (the reference): every leaf vertex inside B's raster hull,
  turned to lon/lat/height, is within 0.5 m in height of B's bilinear surface at its lon/lat
  (merge.check's tolerance), and every leaf there is at the deepest level;
- every other angle, turned back by the inverse rotation: the same leaves (keys) as the
  reference (the same density), each vertex defined where the reference's is and within float32
  rounding of it: 2 sqrt(3) 2^-24 x the clouds' largest coordinate (the two clouds' own rounding,
  which placement by interpolation does not enlarge) + both patches' storage rounding (2^-23 x
  the largest local coordinate) + 1 um. For the vertices off by more that lie over Jacksboro,
  their height off Jacksboro's bilinear surface is reported too (the reference's surface there,
  as its own check shows), and how many of those off it lie within 5 of Jacksboro's pixels from
  its border (the seam): a vertex shifted along the surface is still on it, though not where the
  unturned merge put it.

Exit 0 when every requested angle passes; prints one line per angle and check.
"""

import argparse
import math
import os
import shutil
import subprocess
import sys
import time

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from check_import import A as WGS_A, E2, Failures, ecef_to_geodetic  # noqa: E402
from merge_check import GeoRaster, load  # noqa: E402
from surfaces import write_pcd  # noqa: E402

gdal.UseExceptions()

PRISM = "PRISMelevation"
JACK = "jacksboro_fault_dem"
CROP = 33
ORIGIN = (-84.2458, 36.3029, 500.0)  # Jacksboro's centre, lon/lat/height
PLACEMENT_TOLERANCE = 0.5
BORDER_PIXELS = 5  # the diagnosis tells vertices near B's border (the seam) from the others


def geodetic_to_ecef(lon, lat, h):
    lon, lat = np.radians(lon), np.radians(lat)
    n = WGS_A / np.sqrt(1 - E2 * np.sin(lat) ** 2)
    return np.stack([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1 - E2) + h) * np.sin(lat)], axis=-1)


def enu_axes():
    lon, lat = np.radians(ORIGIN[0]), np.radians(ORIGIN[1])
    east = np.array([-np.sin(lon), np.cos(lon), 0.0])
    north = np.array([-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)])
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    return np.stack([east, north, up]), geodetic_to_ecef(*ORIGIN)


def to_enu(ecef):
    axes, origin = enu_axes()
    return (ecef - origin) @ axes.T


def from_enu(enu):
    axes, origin = enu_axes()
    return enu @ axes + origin


def rotation(deg):
    """About the east (x) axis: y towards z."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def raster_cloud(path, window=None):
    """ENU points (rows, cols, 3) of a geographic raster's pixel centres (NaN where no data)."""
    ds = gdal.Open(path)
    band = ds.GetRasterBand(1)
    gt = ds.GetGeoTransform()
    x0, y0, w, h = window or (0, 0, ds.RasterXSize, ds.RasterYSize)
    values = band.ReadAsArray(x0, y0, w, h).astype(np.float64)
    nodata = band.GetNoDataValue()
    if nodata is not None:
        values[values == nodata] = np.nan
    lon = gt[0] + (x0 + np.arange(w) + 0.5) * gt[1]
    lat = gt[3] + (y0 + np.arange(h) + 0.5) * gt[5]
    lon, lat = np.meshgrid(lon, lat)
    return to_enu(geodetic_to_ecef(lon, lat, values))


def prism_window(path):
    ds = gdal.Open(path)
    gt = ds.GetGeoTransform()
    col = int((ORIGIN[0] - gt[0]) / gt[1])
    row = int((ORIGIN[1] - gt[3]) / gt[5])
    return (col - CROP // 2, row - CROP // 2, CROP, CROP)


def run(args):
    return subprocess.run(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def merge_at(vsm, clouds, angle, work):
    """Writes, imports and merges the clouds turned by `angle`: (merged dir or None, message)."""
    d = os.path.join(work, "turn%03d" % angle)
    shutil.rmtree(d, ignore_errors=True)
    os.makedirs(d)
    r = rotation(angle)
    for name, cloud, size in (("A", clouds[0], 17), ("B", clouds[1], 65)):
        path = os.path.join(d, name + ".pcd")
        write_pcd(path, cloud @ r.T)
        res = run([vsm, "import", path, os.path.join(d, name.lower()), "--patch-size", str(size),
                   "--texture", "none"])
        if res.returncode != 0:
            return None, "vsm import %s exited %d: %s" % (name, res.returncode,
                                                          res.stderr.strip()[-300:])
    merged = os.path.join(d, "merged")
    start = time.monotonic()
    res = run([vsm, "merge", os.path.join(d, "a"), os.path.join(d, "b"), "--out", merged])
    if res.returncode != 0:
        error = [line for line in res.stderr.splitlines() if "error" in line]
        return None, "vsm merge exited %d: %s" % (res.returncode,
                                                  (error or [res.stderr.strip()])[-1])
    return merged, "merged in %.1f s" % (time.monotonic() - start)


def leaves(opc):
    failures = Failures()
    _, patches, children_of, n = load(opc, 65, failures)
    if failures.count:
        raise RuntimeError("%s: %s" % (opc, "; ".join(failures.items[:5])))
    return {k: p for k, p in patches.items() if not children_of[k]}


def check_reference(ref, raster):
    """Angle 0 against Jacksboro's raster: (ok, message)."""
    depth = max(k[0] for k in ref)
    worst, count, bad, shallow = 0.0, 0, 0, 0
    for key, leaf in ref.items():
        g = leaf.grid.reshape(-1, 3)
        g = g[~np.isnan(g[:, 0])]
        lon, lat, h = ecef_to_geodetic(*from_enu(g).T)
        inside = raster.inside(lon, lat)
        if not inside.any():
            continue
        shallow += key[0] != depth
        d = np.abs(h[inside] - raster.bilinear(lon[inside], lat[inside]))
        count += len(d)
        bad += int((d > PLACEMENT_TOLERANCE).sum())
        worst = max(worst, float(d.max()))
    ok = count > 0 and bad == 0 and shallow == 0
    return ok, ("%d leaf vertices inside Jacksboro, %d more than %.1f m from its bilinear surface "
                "(max %.3f m); %d leaves there above the deepest level %d" %
                (count, bad, PLACEMENT_TOLERANCE, worst, shallow, depth))


def compare(ref, turned, angle, cloud_max, raster):
    """The turned merge, turned back, against the reference: (ok, message)."""
    back = rotation(angle).T  # the inverse rotation
    missing = sorted(set(ref) - set(turned))
    extra = sorted(set(turned) - set(ref))
    rounding_in = 2 * math.sqrt(3) * 2.0 ** -24 * cloud_max
    count = off = defined_diff = 0
    worst = worst_height = worst_inner = 0.0
    off_surface = off_inside = off_border = 0
    for key in set(ref) & set(turned):
        a, b = ref[key], turned[key]
        pb = b.grid @ back.T
        da, db = ~np.isnan(a.grid[..., 0]), ~np.isnan(pb[..., 0])
        defined_diff += int((da != db).sum())
        both = da & db
        if not both.any():
            continue
        delta = pb[both] - a.grid[both]
        dist = np.linalg.norm(delta, axis=1)
        tol = rounding_in + a.rounding + b.rounding + 1e-6
        count += len(dist)
        worst = max(worst, float(dist.max()))
        bad = dist > tol
        if bad.any():
            off += int(bad.sum())
            # Diagnosis: is a vertex that moved still on the surface? Over Jacksboro the
            # reference is Jacksboro's bilinear surface (check_reference), so its height there.
            lon, lat, h = ecef_to_geodetic(*from_enu(pb[both][bad]).T)
            inside = raster.inside(lon, lat)
            if inside.any():
                dh = np.abs(h[inside] - raster.bilinear(lon[inside], lat[inside]))
                off_inside += int(inside.sum())
                far = dh > PLACEMENT_TOLERANCE
                off_surface += int(far.sum())
                col, row = raster.pixel(lon[inside], lat[inside])
                edge = np.minimum(np.minimum(col, raster.width - 1 - col),
                                  np.minimum(row, raster.height - 1 - row))
                off_border += int((far & (edge <= BORDER_PIXELS)).sum())
                worst_height = max(worst_height, float(dh.max()))
                if (edge > BORDER_PIXELS).any():
                    worst_inner = max(worst_inner, float(dh[edge > BORDER_PIXELS].max()))
    ok = not missing and not extra and not defined_diff and not off and count > 0
    depth_ref = max(k[0] for k in ref)
    depth_turned = max(k[0] for k in turned) if turned else -1
    return ok, ("%d leaves (reference %d, %d missing, %d extra, deepest %d vs %d), %d common "
                "vertices, %d defined on one side only; %d off by more than the rounding "
                "(%.4f m at the clouds' %.0f m), max %.3f m; of these %d lie over Jacksboro, "
                "%d of them more than %.1f m in height off its surface (max %.3f m), %d of "
                "those within %d of its pixels from its border (farther in: max %.3f m)" %
                (len(turned), len(ref), len(missing), len(extra), depth_turned, depth_ref, count,
                 defined_diff, off, rounding_in, cloud_max, worst, off_inside, off_surface,
                 PLACEMENT_TOLERANCE, worst_height, off_border, BORDER_PIXELS, worst_inner))


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--angles", default="0,45,75,90,95,135,180")
    args = parser.parse_args()
    os.makedirs(args.work, exist_ok=True)
    prism = os.path.join(args.data, PRISM + ".tif")
    clouds = (raster_cloud(prism, prism_window(prism)),
              raster_cloud(os.path.join(args.data, JACK + ".tif")))
    cloud_max = max(float(np.nanmax(np.abs(c))) for c in clouds)
    ref_dir, message = merge_at(args.vsm, clouds, 0, args.work)
    print("angle   0: %s" % message)
    if ref_dir is None:
        print("FAIL the unturned merge failed")
        return 1
    ref = leaves(ref_dir)
    results = []
    raster = GeoRaster(os.path.join(args.data, JACK + ".tif"))
    ok, message = check_reference(ref, raster)
    results.append(ok)
    print("%s angle   0 on Jacksboro: %s" % ("ok  " if ok else "FAIL", message))
    for angle in [int(a) for a in args.angles.split(",")]:
        if angle == 0:
            continue
        merged, message = merge_at(args.vsm, clouds, angle, args.work)
        if merged is None:
            results.append(False)
            print("FAIL angle %3d: %s" % (angle, message))
            continue
        validate = run([args.vsm, "validate", merged])
        ok, detail = compare(ref, leaves(merged), angle, cloud_max, raster)
        ok = ok and validate.returncode == 0
        results.append(ok)
        print("%s angle %3d: %s; validate exit %d; %s" % ("ok  " if ok else "FAIL", angle,
                                                          message, validate.returncode, detail))
        sys.stdout.flush()
    print("%d of %d checks failed" % (results.count(False), len(results)))
    return 0 if all(results) else 1


if __name__ == "__main__":
    sys.exit(main())
