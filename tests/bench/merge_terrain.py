#!/usr/bin/python3
"""Synthetic terrain GeoTIFFs for tests/bench/merge_bench.sh (not a test).

    merge_terrain.py <out.tif> <west> <north> <spacing-arcsec> <size> [--shift-east M] [--up M]

Writes a size x size float32 GeoTIFF (EPSG:4326, north-up, pixel-is-area) sampling ONE analytic
terrain function at the pixel centres: sum of 14 sinusoids with wavelengths from 60 km down to
120 m in fixed pseudo-random directions (amplitude proportional to wavelength^0.9), plus 1500 m.
The function is defined in metres on a local tangent plane at 36 N, 100 W, so rasters of any
extent and spacing sample the same surface: a coarse target and a fine detail model inside it
agree wherever both exist. --shift-east/--up sample the surface moved by that many metres (east,
up): a detail model that needs registration.
"""

import argparse

import numpy as np
from osgeo import gdal, osr

gdal.UseExceptions()

LON0, LAT0 = -100.0, 36.0
M_PER_DEG_LAT = 110_950.0
M_PER_DEG_LON = 111_320.0 * np.cos(np.radians(LAT0))


def terrain(x, y):
    rng = np.random.default_rng(7)
    z = np.full(np.broadcast_shapes(x.shape, y.shape), 1500.0, dtype=np.float64)
    for wavelength in np.geomspace(60_000.0, 120.0, 14):
        angle = rng.uniform(0.0, np.pi)
        phase = rng.uniform(0.0, 2.0 * np.pi)
        amplitude = 0.05 * wavelength ** 0.9
        k = 2.0 * np.pi / wavelength
        z += amplitude * np.sin(k * (np.cos(angle) * x + np.sin(angle) * y) + phase)
    return z


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("out")
    parser.add_argument("west", type=float)
    parser.add_argument("north", type=float)
    parser.add_argument("spacing", type=float, help="arc-seconds")
    parser.add_argument("size", type=int)
    parser.add_argument("--shift-east", type=float, default=0.0)
    parser.add_argument("--up", type=float, default=0.0)
    args = parser.parse_args()

    step = args.spacing / 3600.0
    ds = gdal.GetDriverByName("GTiff").Create(args.out, args.size, args.size, 1, gdal.GDT_Float32)
    ds.SetGeoTransform((args.west, step, 0.0, args.north, 0.0, -step))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ds.SetProjection(srs.ExportToWkt())
    band = ds.GetRasterBand(1)
    lon = args.west + (np.arange(args.size) + 0.5) * step
    x = (lon - LON0) * M_PER_DEG_LON - args.shift_east
    rows = 512
    for r0 in range(0, args.size, rows):
        r1 = min(args.size, r0 + rows)
        lat = args.north - (np.arange(r0, r1) + 0.5) * step
        y = (lat - LAT0) * M_PER_DEG_LAT
        z = terrain(x[None, :], y[:, None]) + args.up
        band.WriteArray(z.astype(np.float32), 0, r0)
    band = None
    ds = None


if __name__ == "__main__":
    main()
