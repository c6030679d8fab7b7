#!/usr/bin/python3
"""For tests/bench/merge_bench.sh: the displacement that the rigid transform printed by
`vsm merge --register` (its stdout, in <file>) gives a point at lon/lat (degrees, 1500 m above the
WGS 84 ellipsoid), in local east/north/up metres.

    merge_transform.py <vsm-merge-stdout> <lon> <lat>
"""

import re
import sys

import numpy as np


def main():
    rows = [[float(v) for v in re.findall(r"[-+]?[0-9.]+(?:e[-+]?[0-9]+)?", line)]
            for line in open(sys.argv[1]) if line.strip().startswith("[")]
    m = np.array(rows[:3])
    lon, lat, h = np.radians(float(sys.argv[2])), np.radians(float(sys.argv[3])), 1500.0
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    p = np.array([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                  (n * (1 - e2) + h) * np.sin(lat)])
    d = m[:, :3] @ p + m[:, 3] - p
    east = np.array([-np.sin(lon), np.cos(lon), 0.0])
    north = np.array([-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)])
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    print("%.2f m east, %.2f m north, %.2f m up" % (d @ east, d @ north, d @ up))


if __name__ == "__main__":
    main()
