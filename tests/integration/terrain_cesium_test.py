#!/usr/bin/python3
"""vsmd's quantized-mesh terrain read by CesiumJS itself: CesiumTerrainProvider and
sampleTerrainMostDetailed from the npm package (the version client-examples/web/build.sh pins,
installed by the web.tools fixture) run in Node against the real vsmd on 127.0.0.1:0 serving PRISM
with Jacksboro merged into it (imported at --patch-size 65 and merged by the real `vsm`).

Checks: the provider loads (vertex normals and metadata offered), no tile error, the root tiles
decode with a normal per vertex, and at 100 DEM pixel centres (50 of PRISM away from Jacksboro, 50
inside Jacksboro; seeded random) CesiumJS's heights equal GDAL's value of the source raster within
the relief of the 4 x 4 DEM samples around the point (the tiles interpolate the model's surface
linearly between their own vertices) plus 1 m, and it refined to the levels layer.json offers there
(PRISM's finest, Jacksboro's deeper ones).

    /usr/bin/python3 terrain_cesium_test.py --vsm <vsm> --vsmd <vsmd> --data <shared/data>
        --work <dir> --cesium <web-tools/node_modules/cesium>
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import unittest

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import server_test as base  # noqa: E402  (the Daemon harness)
from terrain_test import Dem, tile_of  # noqa: E402  (GDAL reader, tiling maths: not vsm's)

ARGS = None
PRISM = "PRISMelevation"
JACK = "jacksboro_fault_dem"


def pixel_centres(dem, count, rng, avoid=None):
    """`count` random pixel centres of `dem` with data around them, as (lon, lat)."""
    out = []
    while len(out) < count:
        c, r = int(rng.integers(2, dem.w - 3)), int(rng.integers(2, dem.h - 3))
        lon = dem.gt[0] + (c + 0.5) * dem.gt[1]
        lat = dem.gt[3] + (r + 0.5) * dem.gt[5]
        if avoid is not None and avoid[0] - 0.5 <= lon <= avoid[2] + 0.5 \
                and avoid[1] - 0.5 <= lat <= avoid[3] + 0.5:
            continue
        if dem.bilinear(lon, lat) is not None:
            out.append((lon, lat))
    return out


class TerrainInCesium(unittest.TestCase):
    def test_cesium_reads_the_terrain(self):
        shutil.rmtree(ARGS.work, ignore_errors=True)
        models, root = os.path.join(ARGS.work, "models"), os.path.join(ARGS.work, "root")
        os.makedirs(models)
        os.makedirs(root)
        for name in (PRISM, JACK):
            subprocess.run([ARGS.vsm, "import", os.path.join(ARGS.data, name + ".tif"),
                            os.path.join(models, name), "--patch-size", "65", "--texture", "none"],
                           check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        subprocess.run([ARGS.vsm, "merge", os.path.join(models, PRISM), os.path.join(models, JACK),
                        "--out", os.path.join(root, "merged")], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        prism = Dem(os.path.join(ARGS.data, PRISM + ".tif"))
        jack = Dem(os.path.join(ARGS.data, JACK + ".tif"))
        rng = np.random.default_rng(14)
        points = pixel_centres(prism, 50, rng, avoid=jack.bounds()) + pixel_centres(jack, 50, rng)
        points_file = os.path.join(ARGS.work, "points.json")
        with open(points_file, "w") as f:
            json.dump(points, f)

        daemon = base.Daemon("--set", "threads.cpu=2", root=root)
        try:
            _, _, layer = daemon.get_json("/v1/models/merged/terrain/layer.json")
            url = "http://127.0.0.1:%d/v1/models/merged/terrain/" % daemon.port
            run = subprocess.run(["node", os.path.join(os.path.dirname(__file__),
                                                       "terrain_cesium_check.mjs"),
                                  ARGS.cesium, url, points_file], capture_output=True, text=True,
                                 timeout=600)
            self.assertEqual(run.returncode, 0, run.stderr[-3000:])
            result = json.loads(run.stdout.strip().splitlines()[-1])
        finally:
            code = daemon.stop()
            daemon.cleanup(keep=code != 0)

        self.assertTrue(result["hasVertexNormals"])
        self.assertTrue(result["hasMetadata"])
        self.assertEqual(result["errors"], [])
        for tile in result["roots"]:
            self.assertEqual(tile["vertices"], 65 * 65)
            self.assertEqual(tile["normals"], 65 * 65)
        self.assertGreater(result["roots"][0]["maximumHeight"], 1000)  # the US is in tile 0/0/0

        worst, errors = -1e9, []
        for k, ((lon, lat), height, level) in enumerate(zip(points, result["heights"],
                                                            result["levels"])):
            dem = prism if k < 50 else jack
            value, relief = dem.bilinear(lon, lat)
            self.assertIsNotNone(height, (lon, lat))
            worst = max(worst, abs(height - value) - relief)
            errors.append(abs(height - value))
            self.assertLessEqual(abs(height - value), relief + 1.0,
                                 "CesiumJS's height at %.5f %.5f" % (lon, lat))
            # Refined as deep as layer.json offers at the point.
            deepest = max(z for z in range(len(layer["available"]))
                          if any(r["startX"] <= tile_of(z, lon, lat)[1] <= r["endX"]
                                 and r["startY"] <= tile_of(z, lon, lat)[2] <= r["endY"]
                                 for r in layer["available"][z]))
            self.assertEqual(level, deepest, (lon, lat))
        print("\nterrain in CesiumJS: 100 heights, |CesiumJS - GDAL| median %.2f m, max %.2f m; "
              "largest (error - relief) %.2f m" % (float(np.median(errors)), max(errors), worst),
              file=sys.stderr)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    for name in ("--vsm", "--vsmd", "--data", "--work", "--cesium"):
        parser.add_argument(name, required=True)
    ARGS, rest = parser.parse_known_args()
    base.ARGS = ARGS
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
