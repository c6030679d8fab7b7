#!/usr/bin/python3
"""Benchmark (not a test): quantized-mesh and terrain-RGB tiles from vsmd on ONE core.

The model is REAL: ../shared/data/PRISMelevation.tif and jacksboro_fault_dem.tif imported by
`vsm import` (default 257 x 257 patches, or --patch-size) and merged with `vsm merge --out`. vsmd
runs pinned to one CPU (taskset -c <cpu>) with one network and one CPU-pool thread; the client (this
script, http.client, one keep-alive connection) runs pinned to another CPU when there is one.

1. layer.json is fetched once first (it builds the layer: every patch read once) and timed apart.
2. cold: every tile of `available` at the levels asked for (default: all levels from 5 on, at most
   --max-tiles, spread evenly) is fetched once, as CesiumJS asks for it (the Accept header with
   octvertexnormals-metadata, gzip accepted): each is sampled from the patches (read from disk
   through the patch cache when not resident yet), encoded, gzipped and cached. tiles/s and the
   per-tile latency (median, p90, max) seen by the client over the local connection.
3. warm: the same tiles again, answered from the encoded-tile cache on the network thread.
4. The same for the terrain-RGB tiles (MapLibre's raster-dem, Terrarium PNGs): every Web Mercator
   tile over the model's bounds from --min-level to the TileJSON's maxzoom (at most --max-tiles,
   spread evenly), cold then warm.

    /usr/bin/python3 tests/bench/terrain_bench.py [--vsm build/server/cli/vsm]
        [--vsmd build/server/vsmd] [--data ../shared/data] [--patch-size 257] [--max-tiles 400]
"""

import argparse
import http.client
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ACCEPT = ("application/vnd.quantized-mesh;extensions=octvertexnormals-metadata,"
          "application/octet-stream;q=0.9,*/*;q=0.01")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--vsm", default=os.path.join(ROOT, "build/server/cli/vsm"))
    p.add_argument("--vsmd", default=os.path.join(ROOT, "build/server/vsmd"))
    p.add_argument("--data", default=os.path.join(ROOT, "../shared/data"))
    p.add_argument("--patch-size", default="257")
    p.add_argument("--max-tiles", type=int, default=400)
    p.add_argument("--min-level", type=int, default=5)
    p.add_argument("--cpu", type=int, default=0)
    p.add_argument("--keep", help="keep vsmd's log (access lines with latencies) here")
    args = p.parse_args()

    work = tempfile.mkdtemp(prefix="vsm-terrain-bench-")
    daemon = None
    try:
        for name in ("PRISMelevation", "jacksboro_fault_dem"):
            subprocess.run([args.vsm, "import", os.path.join(args.data, name + ".tif"),
                            os.path.join(work, name), "--patch-size", args.patch_size,
                            "--texture", "none"], check=True, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
        root = os.path.join(work, "root")
        os.makedirs(root)
        subprocess.run([args.vsm, "merge", os.path.join(work, "PRISMelevation"),
                        os.path.join(work, "jacksboro_fault_dem"), "--out",
                        os.path.join(root, "merged")], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        port_file = os.path.join(work, "port")
        log = open(os.path.join(work, "vsmd.log"), "wb")
        daemon = subprocess.Popen(["taskset", "-c", str(args.cpu), args.vsmd, "--listen",
                                   "127.0.0.1:0", "--data-root", root, "--port-file", port_file,
                                   "--set", "threads.cpu=1", "--set", "threads.io=1",
                                   "--log-level", "info" if args.keep else "warn"], stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 30
        while not os.path.exists(port_file):
            assert daemon.poll() is None and time.monotonic() < deadline, "vsmd did not start"
            time.sleep(0.02)
        time.sleep(0.05)
        port = int(open(port_file).read())
        ncpu = os.cpu_count() or 1
        if ncpu > 1:
            os.sched_setaffinity(0, {(args.cpu + 1) % ncpu})
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)

        def get(path, headers=None):
            conn.request("GET", path, headers=headers or {})
            r = conn.getresponse()
            body = r.read()
            assert r.status == 200, (path, r.status, body[:200])
            return body

        start = time.perf_counter()
        layer = json.loads(get("/v1/models/merged/terrain/layer.json"))
        layer_s = time.perf_counter() - start

        tiles = []
        for z, ranges in enumerate(layer["available"]):
            if z < args.min_level:
                continue
            for r in ranges:
                for y in range(r["startY"], r["endY"] + 1):
                    for x in range(r["startX"], r["endX"] + 1):
                        tiles.append((z, x, y))
        available = len(tiles)
        if len(tiles) > args.max_tiles:
            step = len(tiles) / args.max_tiles
            tiles = [tiles[int(i * step)] for i in range(args.max_tiles)]
        headers = {"Accept": ACCEPT, "Accept-Encoding": "gzip"}

        def run(paths, headers=None):
            """Each path fetched once: (seconds, per-path seconds, bytes)."""
            times, size = [], 0
            t0 = time.perf_counter()
            for path in paths:
                s = time.perf_counter()
                size += len(get(path, headers))
                times.append(time.perf_counter() - s)
            return time.perf_counter() - t0, times, size

        paths = ["/v1/models/merged/terrain/%d/%d/%d.terrain" % t for t in tiles]
        cold_s, cold, cold_bytes = run(paths, headers)
        warm_s, warm, _ = run(paths, headers)
        levels = sorted({t[0] for t in tiles})

        def ms(values, q):
            values = sorted(values)
            return 1000 * values[min(len(values) - 1, int(q * len(values)))]

        load = os.getloadavg()
        print("terrain_bench: PRISM (%s x %s patches) merged with Jacksboro; vsmd on CPU %d "
              "(threads.cpu=1, threads.io=1); load average %.2f %.2f %.2f on %d CPUs"
              % (args.patch_size, args.patch_size, args.cpu, load[0], load[1], load[2], ncpu))
        print("layer.json (first, builds the layer): %.1f ms" % (1000 * layer_s))
        print("tiles: %d of levels %s (of %d available from level %d); Accept with "
              "octvertexnormals-metadata, gzip; mean %.1f KiB gzipped"
              % (len(tiles), levels, available, args.min_level,
                 cold_bytes / len(tiles) / 1024))
        print("cold (sample + encode + gzip + cache): %7.1f tiles/s   per tile median %.2f ms, "
              "p90 %.2f ms, max %.2f ms"
              % (len(tiles) / cold_s, ms(cold, 0.5), ms(cold, 0.9), max(cold) * 1000))
        print("warm (from the cache, network thread): %7.1f tiles/s   per tile median %.3f ms, "
              "p90 %.3f ms" % (len(tiles) / warm_s, ms(warm, 0.5), ms(warm, 0.9)))
        print("(latencies as the client sees them over one local keep-alive connection, HTTP "
              "included; target: a cold tile <= 5 ms)")

        tilejson = json.loads(get("/v1/models/merged/terrain-rgb/tiles.json"))
        w, s, e, n = tilejson["bounds"]
        rgb_tiles = []
        for z in range(args.min_level, tilejson["maxzoom"] + 1):
            count = 2 ** z

            def row(lat):
                return int((1 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2 * count)

            for y in range(row(n), min(row(s), count - 1) + 1):
                for x in range(int((w + 180) / 360 * count),
                               min(int((e + 180) / 360 * count), count - 1) + 1):
                    rgb_tiles.append((z, x, y))
        rgb_available = len(rgb_tiles)
        if len(rgb_tiles) > args.max_tiles:
            step = len(rgb_tiles) / args.max_tiles
            rgb_tiles = [rgb_tiles[int(i * step)] for i in range(args.max_tiles)]

        paths = ["/v1/models/merged/terrain-rgb/%d/%d/%d.png" % t for t in rgb_tiles]
        cold_s, cold, cold_bytes = run(paths)
        warm_s, warm, _ = run(paths)
        print("terrain-RGB: %d tiles of levels %d..%d (of %d over the bounds), 256 x 256 "
              "Terrarium PNG, mean %.1f KiB"
              % (len(rgb_tiles), args.min_level, tilejson["maxzoom"], rgb_available,
                 cold_bytes / len(rgb_tiles) / 1024))
        print("cold (sample + encode + cache):        %7.1f tiles/s   per tile median %.2f ms, "
              "p90 %.2f ms, max %.2f ms"
              % (len(rgb_tiles) / cold_s, ms(cold, 0.5), ms(cold, 0.9), max(cold) * 1000))
        print("warm (from the cache, network thread): %7.1f tiles/s   per tile median %.3f ms, "
              "p90 %.3f ms" % (len(rgb_tiles) / warm_s, ms(warm, 0.5), ms(warm, 0.9)))
        load = os.getloadavg()
        print("load average after: %.2f %.2f %.2f" % load)
    finally:
        if daemon is not None:
            daemon.terminate()
            daemon.wait(timeout=30)
            if args.keep:
                shutil.copy(os.path.join(work, "vsmd.log"), args.keep)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
