#!/usr/bin/python3
"""Issue 28's measure (not a test): how much of a draped image's detail a textured model keeps,
judged from the stored tiles alone, without vsm's code.

    /usr/bin/python3 tests/bench/texture_density.py --vsm build/server/cli/vsm \\
        --data ../shared/data --work /tmp/texture-density [--factors 1,2,4] [--patch-size 65] \\
        [--import-options '--texels-per-quad 1']

For each factor F: the DEM is a crop of PRISM (2.5', -90..-82 E, 33..39 N), the image the NASA
image F times finer with a per-pixel texture (tests/integration/texel_density.py says how it is
made and measured). `vsm import dem model --texture image --patch-size N [--import-options]`
makes the model. Issue 28 asks for density >= 0.8 and r >= 0.75.

Prints one line per factor."""

import argparse
import os
import shutil
import subprocess
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "integration"))
from texel_density import make_pair, measure  # noqa: E402

WINDOW = (-90.0, 39.0, -82.0, 33.0)  # west, north, east, south: a crop of PRISM


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--factors", default="1,2,4")
    parser.add_argument("--patch-size", type=int, default=65)
    parser.add_argument("--import-options", default="",
                        help="more options of vsm import, e.g. '--texels-per-quad 1'")
    args = parser.parse_args()
    shutil.rmtree(args.work, ignore_errors=True)
    os.makedirs(args.work)
    for factor in [float(f) for f in args.factors.split(",")]:
        dem, image = make_pair(os.path.join(args.data, "PRISMelevation.tif"),
                               os.path.join(args.data, "conus_visible_earth.tif"), args.work,
                               "prism", factor, WINDOW)
        opc = os.path.join(args.work, "model-%g" % factor)
        subprocess.run([args.vsm, "import", dem, opc, "--patch-size", str(args.patch_size),
                        "--texture", image, *args.import_options.split()], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
        print("image %gx finer than the DEM: %s" % (factor, measure(opc, dem, image,
                                                                    args.patch_size)), flush=True)

if __name__ == "__main__":
    main()
