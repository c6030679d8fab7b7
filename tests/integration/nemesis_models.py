"""The nemesis's synthetic models (nemesis_test.py): three flat targets t0, t1, t2 and twelve
details d0..d11, each flat at its own height in its own place inside the targets, so that a merge
of di is seen in any revision by the height at di's centre."""

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402

TARGETS = ["t0", "t1", "t2"]
DETAILS = 12
PIXEL = 2.0 ** -12  # degrees, the targets' spacing (about 27 m)
WEST, NORTH = 10.0, 0.05
BASE_HEIGHT = 100.0


def detail_height(i):
    return 1000.0 + 100.0 * i


def detail_place(i):
    """(column, row) of the target pixel under detail i's first pixel."""
    return 20 + 56 * (i % 4), 20 + 70 * (i // 4)


def detail_centre(i):
    """(lon, lat) of detail i's centre: 33 samples of a quarter pixel, 8.25 target pixels."""
    c, r = detail_place(i)
    return WEST + (c + 4.125) * PIXEL, NORTH - (r + 4.125) * PIXEL


def make_models(data, work):
    """The targets and details imported into `data` (their rasters written in `work`); the vsm
    binary is harness's (harness.configure)."""
    base = os.path.join(work, "base.tif")
    harness.write_raster(base, np.full((257, 257), BASE_HEIGHT), WEST, NORTH, PIXEL)
    for target in TARGETS:
        harness.import_dem(base, os.path.join(data, target), 65)
    for i in range(DETAILS):
        c, r = detail_place(i)
        raster = os.path.join(work, "d%d.tif" % i)
        harness.write_raster(raster, np.full((33, 33), detail_height(i)), WEST + c * PIXEL,
                             NORTH - r * PIXEL, PIXEL / 4)
        harness.import_dem(raster, os.path.join(data, "d%d" % i), 33)
