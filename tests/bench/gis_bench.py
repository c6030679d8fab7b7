#!/usr/bin/python3
"""Benchmark (not a test): heights for GIS clients (issue 29), on ONE core.

The model is REAL: ../shared/data/jacksboro_fault_dem.tif imported by `vsm import` (--patch-size,
default 257).

1. export: `vsm export` of a 4096 x 4096 area over Jacksboro (its bounds at 1/4096 of their
   width: finer than the raster, so every pixel is sampled) against `gdalwarp` of the source
   raster to the same grid (-te, -ts, bilinear, float32, DEFLATE tiled: the nearest equivalent
   product), both under `taskset -c <cpu>`, median of --repeat wall times each. The ratio is
   vsm / gdalwarp (target <= 2).
2. points: vsmd pinned to one CPU (one I/O and one CPU-pool thread), POSTs of 1000 random
   points over Jacksboro (a GeoJSON MultiPoint) for --seconds on one keep-alive connection:
   points per second, and the latency per request.

    /usr/bin/python3 tests/bench/gis_bench.py [--vsm build/server/cli/vsm]
        [--vsmd build/server/vsmd] [--data ../shared/data] [--patch-size 257] [--repeat 3]
"""

import argparse
import http.client
import json
import os
import random
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

from osgeo import gdal

gdal.UseExceptions()


def timed(cmd, cpu):
    start = time.monotonic()
    subprocess.run(["taskset", "-c", str(cpu)] + cmd, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return time.monotonic() - start


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", default="build/server/cli/vsm")
    parser.add_argument("--vsmd", default="build/server/vsmd")
    parser.add_argument("--data", default="../shared/data")
    parser.add_argument("--patch-size", type=int, default=257)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=5)
    parser.add_argument("--cpu", type=int, default=0)
    args = parser.parse_args()
    work = tempfile.mkdtemp(prefix="gis-bench-")
    try:
        source = os.path.join(args.data, "jacksboro_fault_dem.tif")
        model = os.path.join(work, "root", "jack")
        os.makedirs(os.path.dirname(model))
        subprocess.run([args.vsm, "import", source, model, "--patch-size", str(args.patch_size),
                        "--texture", "none"], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        ds = gdal.Open(source)
        t = ds.GetGeoTransform()
        w, n = t[0], t[3]
        e, s = w + ds.RasterXSize * t[1], n + ds.RasterYSize * t[5]
        size = 4096
        res = (e - w) / size
        s = n - size * res
        print("load average %s; %d x %d pixels over Jacksboro (%.3g deg pixels), cpu %d"
              % (" ".join("%.2f" % x for x in os.getloadavg()), size, size, res, args.cpu))
        vsm_times, warp_times = [], []
        for _ in range(args.repeat):
            out = os.path.join(work, "vsm.tif")
            vsm_times.append(timed([args.vsm, "export", model, out, "--bounds",
                                    "%r,%r,%r,%r" % (w, s, e, n), "--resolution", repr(res)],
                                   args.cpu))
            warped = os.path.join(work, "warp.tif")
            if os.path.exists(warped):
                os.remove(warped)
            warp_times.append(timed(["gdalwarp", "-q", "-te", repr(w), repr(s), repr(e), repr(n),
                                     "-ts", str(size), str(size), "-r", "bilinear", "-ot",
                                     "Float32", "-co", "TILED=YES", "-co", "COMPRESS=DEFLATE",
                                     "-co", "PREDICTOR=3", source, warped], args.cpu))
        vm, gm = statistics.median(vsm_times), statistics.median(warp_times)
        print("export: vsm %.3f s, gdalwarp %.3f s (medians of %d), ratio %.2fx (target <= 2x)"
              % (vm, gm, args.repeat, vm / gm))

        # Points.
        root = os.path.dirname(model)
        port_file = os.path.join(root, "port")
        daemon = subprocess.Popen(["taskset", "-c", str(args.cpu), args.vsmd, "--listen",
                                   "127.0.0.1:0", "--data-root", root, "--port-file", port_file,
                                   "--set", "threads.cpu=1", "--set", "threads.io=1"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            while not os.path.exists(port_file):
                if daemon.poll() is not None:
                    raise SystemExit("vsmd exited with %d" % daemon.returncode)
                time.sleep(0.02)
            time.sleep(0.1)
            port = int(open(port_file).read())
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
            rng = random.Random(29)

            def body():
                return json.dumps({"type": "MultiPoint", "coordinates": [
                    [rng.uniform(w, e), rng.uniform(s, n)] for _ in range(1000)]})

            conn.request("POST", "/v1/models/jack/elevation", body=body())  # builds the layer
            first = conn.getresponse()
            first.read()
            assert first.status == 200, first.status
            latencies = []
            start = time.monotonic()
            while time.monotonic() - start < args.seconds:
                b = body()
                t0 = time.monotonic()
                conn.request("POST", "/v1/models/jack/elevation", body=b)
                r = conn.getresponse()
                r.read()
                latencies.append(time.monotonic() - t0)
                assert r.status == 200, r.status
            total = sum(latencies)
            print("points: %d requests of 1000 points, %.0f points/s, latency median %.1f ms, "
                  "max %.1f ms" % (len(latencies), 1000 * len(latencies) / total,
                                   1000 * statistics.median(latencies), 1000 * max(latencies)))
        finally:
            daemon.terminate()
            daemon.wait()
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
