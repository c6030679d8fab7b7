#!/usr/bin/env python3
"""The load, the jobs, the sampling and the verdict of tests/bench/soak.sh (read its header).

    soak.py --url URL --token TOKEN --pid VSMD_PID --data-root DIR --out DIR --minutes M

Load: PROCESSES processes, each one asyncio loop over its share of CONNECTIONS keep-alive
connections, each sending the next read as soon as the previous answer is read whole (closed
loop), on raw non-blocking sockets read with recv_into into one buffer a connection (the answer
bytes are counted, not kept). Latency is from the request's write to its last byte. Control
(threads of this process, one short-lived connection per action, so that idle timeouts do not
matter): a merge job every MERGE_EVERY s, an import job every IMPORT_EVERY s (imported, read,
closed, its directory removed), a model opened, read and closed every OPEN_EVERY s, and a sample
every WINDOW s. Writes soak.csv, soak.png, summary.txt into --out; exits 0 when it passed.
Standard library, numpy and matplotlib only.
"""

import argparse
import asyncio
import http.client
import json
import multiprocessing as mp
import os
import queue
import random
import resource
import shutil
import signal
import socket
import sys
import threading
import time
import urllib.parse
from array import array

# Read routes and their weights (a patch's routes on a patch drawn uniformly over the keys of
# the three models, so the big model, 80% of the keys, takes most of the patch reads).
WEIGHTS = {
    "positions": 45,
    "patch": 20,
    "coordinates": 8,  # on textured models; positions elsewhere
    "texture": 4,  # likewise
    "glb": 5,  # prism and detail only (a 257 x 257 mesh encoded per miss is not cheap)
    "hierarchy": 5,
    "lod": 5,
    "tileset": 3,
    "summary": 5,
}


def parse_args():
    p = argparse.ArgumentParser()
    p.add_argument("--url", required=True)
    p.add_argument("--token", required=True)
    p.add_argument("--pid", type=int, required=True)
    p.add_argument("--data-root", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--minutes", type=float, default=30)
    p.add_argument("--connections", type=int, default=64)
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--window", type=float, default=10)
    p.add_argument("--merge-every", type=float, default=60)
    p.add_argument("--import-every", type=float, default=300)
    p.add_argument("--open-every", type=float, default=30)
    p.add_argument("--models", default="prism,big,detail", help="read models (patch routes)")
    p.add_argument("--target", default="target")
    p.add_argument("--detail", default="detail")
    p.add_argument("--import-file", default="rasters/prism.tif")
    p.add_argument("--import-patch-size", type=int, default=257)
    p.add_argument("--open-path", default="occopy")
    p.add_argument("--warmup", type=float, default=0.2, help="fraction of samples left out of the slopes")
    p.add_argument("--rss-slope", type=float, default=1.0, help="MiB/min")
    p.add_argument("--fd-slope", type=float, default=0.5, help="descriptors/min")
    p.add_argument("--p99-ratio", type=float, default=2.0)
    p.add_argument("--timeout", type=float, default=60)
    return p.parse_args()


# ---------------------------------------------------------------- control connections


class Api:
    """One request a connection (control traffic is rare; idle timeouts never bite)."""

    def __init__(self, url, token, timeout=120):
        self.netloc = urllib.parse.urlsplit(url).netloc
        self.token = token
        self.timeout = timeout

    def call(self, method, path, body=None):
        conn = http.client.HTTPConnection(self.netloc, timeout=self.timeout)
        try:
            headers = {"Authorization": "Bearer " + self.token}
            data = None
            if body is not None:
                data = json.dumps(body)
                headers["Content-Type"] = "application/json"
            conn.request(method, path, body=data, headers=headers)
            response = conn.getresponse()
            raw = response.read()
            return response.status, raw
        finally:
            conn.close()

    def json(self, method, path, body=None, ok=(200,)):
        status, raw = self.call(method, path, body)
        if status not in ok:
            raise RuntimeError("%s %s: HTTP %d %s" % (method, path, status, raw[:300]))
        return json.loads(raw) if raw else None

    def wait_job(self, job, poll=0.25):
        while job["state"] in ("queued", "running"):
            time.sleep(poll)
            job = self.json("GET", "/v1/jobs/" + job["id"])
        if job["state"] != "succeeded":
            raise RuntimeError("job %s (%s) %s: %s" % (job["id"], job["type"], job["state"], job.get("error")))
        return job


def walk(node, out):
    out.append(node)
    for child in node.get("children", []):
        walk(child, out)
    return out


def build_targets(api, models, target):
    """The read set: per model its keys, boxes and which patches have a texture."""
    plan = {"patches": [], "glb": [], "textured": [], "lod": [], "model_routes": []}
    for m in models:
        tree = api.json("GET", "/v1/models/%s/hierarchy" % m)
        nodes = walk(tree["root"], [])
        textured = []
        for n in nodes:
            plan["patches"].append((m, n["key"]))
            if m != "big":
                plan["glb"].append((m, n["key"]))
            status, _ = api.call("GET", "/v1/models/%s/patches/%s/coordinates" % (m, n["key"]))
            if status == 200:
                textured.append((m, n["key"]))
            if n.get("resolution"):
                b = n["box"]
                box = ",".join("%.3f" % v for v in b["min"] + b["max"])
                for f in (1.0, 0.5, 0.1):
                    plan["lod"].append("/v1/models/%s/lod?box=%s&resolution=%.3f" % (m, box, n["resolution"] * f))
        plan["textured"] += textured
        print("  %s: %d patches, %d with a texture" % (m, len(nodes), len(textured)), flush=True)
    for m in models + [target]:
        plan["model_routes"].append(m)
    return plan


def pick(rng, plan, routes, cum):
    r = rng.random() * cum[-1]
    route = routes[next(i for i, c in enumerate(cum) if r < c)]
    if route in ("coordinates", "texture"):
        if plan["textured"]:
            m, k = rng.choice(plan["textured"])
            return "/v1/models/%s/patches/%s/%s" % (m, k, route)
        route = "positions"
    if route == "positions":
        m, k = rng.choice(plan["patches"])
        return "/v1/models/%s/patches/%s/positions" % (m, k)
    if route == "patch":
        m, k = rng.choice(plan["patches"])
        return "/v1/models/%s/patches/%s" % (m, k)
    if route == "glb":
        m, k = rng.choice(plan["glb"])
        return "/v1/models/%s/3dtiles/%s.glb" % (m, k)
    if route == "lod":
        return rng.choice(plan["lod"])
    m = rng.choice(plan["model_routes"])
    if route == "hierarchy":
        return "/v1/models/%s/hierarchy" % m
    if route == "tileset":
        return "/v1/models/%s/3dtiles/tileset.json" % m
    return "/v1/models/%s" % m


# ---------------------------------------------------------------- load generator (worker processes)


class Recorder:
    """Per window: latencies (ms, float32), answers, errors, bytes; closed windows go to the queue."""

    def __init__(self, t0, window, out, wid):
        self.t0, self.window, self.out, self.wid = t0, window, out, wid
        self.windows = {}
        self.errors = []

    def slot(self, t):
        w = int((t - self.t0) // self.window)
        s = self.windows.get(w)
        if s is None:
            s = self.windows[w] = {"lat": array("f"), "n": 0, "err": 0, "bytes": 0, "status": {}}
        return s

    def add(self, t, seconds, status, nbytes, path):
        s = self.slot(t)
        s["n"] += 1
        s["status"][status] = s["status"].get(status, 0) + 1
        if 200 <= status < 400:
            s["lat"].append(seconds * 1000.0)
            s["bytes"] += nbytes
        else:
            s["err"] += 1
            if len(self.errors) < 50:
                self.errors.append((round(t - self.t0, 1), path, "HTTP %d" % status))

    def error(self, t, path, what):
        s = self.slot(t)
        s["n"] += 1
        s["err"] += 1
        if len(self.errors) < 50:
            self.errors.append((round(t - self.t0, 1), path, what))

    def flush(self, everything=False):
        now_w = int((time.monotonic() - self.t0) // self.window)
        for w in sorted(self.windows):
            if everything or w < now_w:
                self.out.put(("window", self.wid, w, self.windows.pop(w)))


class Closed(Exception):
    pass


async def one_request(loop, sock, buf, host, path, timeout):
    """Sends GET path, reads the answer whole; returns (status, body bytes, keep-alive)."""
    await loop.sock_sendall(sock, ("GET %s HTTP/1.1\r\nHost: %s\r\n\r\n" % (path, host)).encode())
    view = memoryview(buf)
    have = 0
    while True:
        n = await asyncio.wait_for(loop.sock_recv_into(sock, view[have:]), timeout)
        if n == 0:
            raise Closed("connection closed by the server")
        have += n
        end = buf.find(b"\r\n\r\n", 0, have)
        if end >= 0:
            break
        if have == len(buf):
            raise Closed("header too large")
    head = bytes(view[:end]).decode("latin-1").split("\r\n")
    status = int(head[0].split(" ", 2)[1])
    headers = {}
    for line in head[1:]:
        k, _, v = line.partition(":")
        headers[k.strip().lower()] = v.strip()
    if "content-length" not in headers:
        raise Closed("no Content-Length (HTTP %d, %s)" % (status, headers.get("transfer-encoding", "")))
    length = int(headers["content-length"])
    body_have = have - (end + 4)
    while body_have < length:
        n = await asyncio.wait_for(loop.sock_recv_into(sock, view[: min(len(buf), length - body_have)]), timeout)
        if n == 0:
            raise Closed("connection closed mid-body")
        body_have += n
    return status, length, headers.get("connection", "").lower() != "close"


async def connection(plan, host, port, rec, deadline, seed, timeout):
    loop = asyncio.get_running_loop()
    rng = random.Random(seed)
    routes = list(WEIGHTS)
    cum = []
    total = 0
    for r in routes:
        total += WEIGHTS[r]
        cum.append(total)
    buf = bytearray(1 << 20)
    sock = None
    while time.monotonic() < deadline:
        path = pick(rng, plan, routes, cum)
        t0 = time.monotonic()
        try:
            if sock is None:
                sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                sock.setblocking(False)
                await asyncio.wait_for(loop.sock_connect(sock, (host, port)), timeout)
                t0 = time.monotonic()
            status, nbytes, keep = await one_request(loop, sock, buf, host, path, timeout)
            t1 = time.monotonic()
            rec.add(t1, t1 - t0, status, nbytes, path)
            if not keep:
                sock.close()
                sock = None
        except (OSError, Closed, asyncio.TimeoutError, ValueError, IndexError) as e:
            rec.error(time.monotonic(), path, "%s: %s" % (type(e).__name__, e))
            if sock is not None:
                sock.close()
                sock = None
            await asyncio.sleep(0.1)
    if sock is not None:
        sock.close()


async def worker_main(plan, host, port, t0, window, conns, seeds, deadline, out, wid, timeout):
    rec = Recorder(t0, window, out, wid)
    tasks = [asyncio.create_task(connection(plan, host, port, rec, deadline, s, timeout)) for s in seeds[:conns]]

    async def flusher():
        while time.monotonic() < deadline:
            await asyncio.sleep(1)
            rec.flush()

    f = asyncio.create_task(flusher())
    await asyncio.gather(*tasks)
    f.cancel()
    rec.flush(everything=True)
    return rec.errors


def worker(plan, host, port, t0, window, conns, seeds, deadline, out, wid, timeout):
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))
    errors = asyncio.run(worker_main(plan, host, port, t0, window, conns, seeds, deadline, out, wid, timeout))
    ru = resource.getrusage(resource.RUSAGE_SELF)
    out.put(("done", wid, errors, ru.ru_utime + ru.ru_stime))


# ---------------------------------------------------------------- control threads (main process)


class Control:
    def __init__(self, args, t0, deadline):
        self.args, self.t0, self.deadline = args, t0, deadline
        self.api = Api(args.url, args.token)
        self.lock = threading.Lock()
        self.events = []  # (t, kind, ok, seconds, detail)
        self.stop = threading.Event()

    def event(self, kind, ok, seconds, detail=""):
        with self.lock:
            self.events.append((time.monotonic() - self.t0, kind, ok, seconds, detail))
        if not ok:
            print("  [%6.1f s] %s FAILED: %s" % (time.monotonic() - self.t0, kind, detail), flush=True)

    def every(self, period, first, kind, action):
        next_t = self.t0 + first
        while not self.stop.is_set():
            if self.stop.wait(max(0.0, next_t - time.monotonic())):
                return
            if time.monotonic() > self.deadline - 5:
                return
            start = time.monotonic()
            try:
                detail = action()
                self.event(kind, True, time.monotonic() - start, detail or "")
            except Exception as e:  # noqa: BLE001 - every failure is counted and reported
                self.event(kind, False, time.monotonic() - start, "%s: %s" % (type(e).__name__, e))
            next_t = max(next_t + period, time.monotonic())

    def merge(self):
        a = self.args
        job = self.api.json("POST", "/v1/jobs", {"type": "merge", "target": a.target, "source": a.detail}, ok=(202,))
        job = self.api.wait_job(job)
        r = job.get("result") or {}
        return "version %s, %s new patches" % (r.get("version"), r.get("new_patches"))

    def import_model(self):
        a = self.args
        self.imports = getattr(self, "imports", 0) + 1
        mid = "imported-%d" % self.imports
        body = {"id": mid, "source": {"import": a.import_file, "patch_size": a.import_patch_size}}
        job = self.api.json("POST", "/v1/models", body, ok=(202,))
        self.api.wait_job(job)
        tree = self.api.json("GET", "/v1/models/%s/hierarchy" % mid)
        keys = [n["key"] for n in walk(tree["root"], [])]
        for k in keys[:8]:
            status, _ = self.api.call("GET", "/v1/models/%s/patches/%s/positions" % (mid, k))
            if status != 200:
                raise RuntimeError("positions of %s/%s: HTTP %d" % (mid, k, status))
        self.api.json("DELETE", "/v1/models/" + mid, ok=(204,))
        shutil.rmtree(os.path.join(a.data_root, mid))
        return "%s: %d patches, read, closed, removed" % (mid, len(keys))

    def open_close(self):
        a = self.args
        self.api.json("POST", "/v1/models", {"id": "opened", "source": {"path": a.open_path}}, ok=(201,))
        tree = self.api.json("GET", "/v1/models/opened/hierarchy")
        for n in walk(tree["root"], [])[:8]:
            status, _ = self.api.call("GET", "/v1/models/opened/patches/%s/positions" % n["key"])
            if status != 200:
                raise RuntimeError("positions of opened/%s: HTTP %d" % (n["key"], status))
        self.stop.wait(a.open_every / 2)  # open for half the period, while the load runs
        self.api.json("DELETE", "/v1/models/opened", ok=(204,))
        return ""


def read_proc(pid):
    mem = {}
    with open("/proc/%d/status" % pid) as f:
        for line in f:
            if line.startswith(("VmRSS:", "RssAnon:", "RssFile:")):
                mem[line.split(":")[0]] = int(line.split()[1]) * 1024
    fds = len(os.listdir("/proc/%d/fd" % pid))
    with open("/proc/%d/stat" % pid) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return mem, fds, cpu


# ---------------------------------------------------------------- analysis


def slope_per_min(ts, ys):
    import numpy as np

    if len(ts) < 3:
        return float("nan")
    return float(np.polyfit(np.asarray(ts) / 60.0, np.asarray(ys, dtype=float), 1)[0])


def percentile(values, q):
    import numpy as np

    return float(np.percentile(np.asarray(values), q)) if len(values) else float("nan")


def plot(rows, path, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["t_s"] / 60 for r in rows]
    fig, ax = plt.subplots(4, 1, figsize=(10, 11), sharex=True)
    ax[0].plot(t, [r["rss_bytes"] / 2**20 for r in rows], label="vsmd RSS")
    ax[0].plot(t, [r["rss_anon_bytes"] / 2**20 for r in rows], label="RSS anonymous")
    ax[0].plot(t, [r["rss_file_bytes"] / 2**20 for r in rows], label="RSS file-backed")
    ax[0].plot(t, [r["resident_bytes"] / 2**20 for r in rows], label="budget resident")
    ax[0].plot(t, [r["budget_bytes"] / 2**20 for r in rows], "--", label="budget")
    ax[0].set_ylabel("MiB")
    ax[0].legend(loc="center right")
    ax[1].plot(t, [r["fds"] for r in rows], label="open descriptors")
    ax[1].plot(t, [r["open_files"] for r in rows], label="cache open files")
    ax[1].set_ylabel("count")
    ax[1].legend(loc="center right")
    ax[2].plot(t, [r["p50_ms"] for r in rows], label="p50")
    ax[2].plot(t, [r["p99_ms"] for r in rows], label="p99")
    ax[2].set_ylabel("read latency, ms")
    ax[2].set_yscale("log")
    ax[2].legend(loc="center right")
    ax[3].plot(t, [r["reads_per_s"] for r in rows], label="reads/s")
    ax[3].set_ylabel("reads/s")
    ax3b = ax[3].twinx()
    ax3b.plot(t, [r["errors"] + r["control_errors"] for r in rows], "r.", label="errors")
    ax3b.set_ylabel("errors", color="r")
    ax[3].set_xlabel("minutes")
    for w in (0, 1, 2, 3):
        ax[w].grid(alpha=0.3)
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


# ---------------------------------------------------------------- main


def main():
    a = parse_args()
    os.makedirs(a.out, exist_ok=True)
    split = urllib.parse.urlsplit(a.url)
    host, port = split.hostname, split.port
    assert host == "127.0.0.1", "loopback only"
    api = Api(a.url, a.token)
    models = a.models.split(",")
    print("read set:", flush=True)
    plan = build_targets(api, models, a.target)

    stop_all = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))

    t0 = time.monotonic() + 0.5
    duration = a.minutes * 60
    deadline = t0 + duration
    out = mp.Queue()
    procs = []
    seeds = list(range(1, a.connections + 1))
    per = [a.connections // a.processes + (1 if i < a.connections % a.processes else 0) for i in range(a.processes)]
    start = 0
    for i in range(a.processes):
        p = mp.Process(
            target=worker,
            args=(plan, host, port, t0, a.window, per[i], seeds[start : start + per[i]], deadline, out, i, a.timeout),
            daemon=True,
        )
        start += per[i]
        p.start()
        procs.append(p)

    control = Control(a, t0, deadline)
    threads = [
        threading.Thread(target=control.every, args=(a.merge_every, 5, "merge", control.merge), daemon=True),
        threading.Thread(target=control.every, args=(a.import_every, 30, "import", control.import_model), daemon=True),
        threading.Thread(target=control.every, args=(a.open_every, 10, "open-close", control.open_close), daemon=True),
    ]
    for th in threads:
        th.start()

    windows = {}
    worker_errors = []
    worker_cpu = []
    done = 0

    def collect(block_until):
        nonlocal done
        while True:
            left = block_until - time.monotonic()
            try:
                msg = out.get(timeout=max(0.01, left)) if left > 0 else out.get_nowait()
            except queue.Empty:
                return
            if msg[0] == "window":
                _, _, w, s = msg
                agg = windows.setdefault(w, {"lat": [], "n": 0, "err": 0, "bytes": 0, "status": {}})
                agg["lat"].append(s["lat"])
                agg["n"] += s["n"]
                agg["err"] += s["err"]
                agg["bytes"] += s["bytes"]
                for k, v in s["status"].items():
                    agg["status"][k] = agg["status"].get(k, 0) + v
            else:
                _, _, errs, cpu = msg
                worker_errors.extend(errs)
                worker_cpu.append(cpu)
                done += 1

    samples = []
    stats_failures = 0
    k = 0
    cpu_prev = None
    print("load: %d connections in %d processes, %.1f min; sampling every %.0f s" % (a.connections, a.processes, a.minutes, a.window), flush=True)
    try:
        while True:
            k += 1
            at = t0 + k * a.window
            if at > deadline + 0.01:
                break
            collect(at)
            mem, fds, cpu = read_proc(a.pid)
            rss = mem.get("VmRSS", 0)
            try:
                stats = api.json("GET", "/v1/stats")
            except Exception as e:  # noqa: BLE001
                stats_failures += 1
                control.event("stats", False, 0, str(e))
                stats = {"memory": {}, "cache": {}}
            m, c = stats["memory"], stats["cache"]
            cpu_pct = 100.0 * (cpu - cpu_prev) / a.window if cpu_prev is not None else float("nan")
            cpu_prev = cpu
            samples.append(
                {
                    "t_s": k * a.window,
                    "rss_bytes": rss,
                    "rss_anon_bytes": mem.get("RssAnon", 0),
                    "rss_file_bytes": mem.get("RssFile", 0),
                    "fds": fds,
                    "vsmd_cpu_pct": cpu_pct,
                    "resident_bytes": m.get("resident_bytes", -1),
                    "budget_bytes": m.get("budget_bytes", -1),
                    "pinned_bytes": m.get("pinned_bytes", -1),
                    "open_files": m.get("open_files", -1),
                    "cache_hits": c.get("hits", -1),
                    "cache_misses": c.get("misses", -1),
                    "evictions": c.get("evictions", -1),
                    "exhausted": c.get("exhausted", -1),
                }
            )
            w = windows.get(k - 2, {"n": 0, "err": 0})  # the last window all workers have sent
            print(
                "  %5.0f s  RSS %7.1f MiB (anon %7.1f)  fds %4d  resident %6.1f / %6.1f MiB  reads %6d  errors %d"
                % (k * a.window, rss / 2**20, mem.get("RssAnon", 0) / 2**20, fds, m.get("resident_bytes", 0) / 2**20,
                   m.get("budget_bytes", 0) / 2**20, w["n"], w["err"]),
                flush=True,
            )
    finally:
        control.stop.set()
        stop_all.set()
    for th in threads:
        th.join(timeout=180)
    deadline_join = time.monotonic() + a.timeout + 30
    while done < a.processes and time.monotonic() < deadline_join:
        collect(time.monotonic() + 1)
    for p in procs:
        p.join(timeout=5)

    # ---- rows: sample k (at the end of window k - 1) with that window's reads
    events = control.events
    rows = []
    for s in samples:
        w = int(s["t_s"] // a.window) - 1
        agg = windows.get(w, {"lat": [], "n": 0, "err": 0, "bytes": 0})
        lat = [x for part in agg["lat"] for x in part]
        lo, hi = s["t_s"] - a.window, s["t_s"]
        in_window = [e for e in events if lo <= e[0] < hi]
        row = dict(s)
        row.update(
            {
                "reads": agg["n"],
                "reads_per_s": agg["n"] / a.window,
                "read_mib_per_s": agg["bytes"] / a.window / 2**20,
                "errors": agg["err"],
                "p50_ms": percentile(lat, 50),
                "p99_ms": percentile(lat, 99),
                "jobs_ok": sum(1 for e in in_window if e[2] and e[1] in ("merge", "import")),
                "control_errors": sum(1 for e in in_window if not e[2]),
            }
        )
        rows.append(row)
    cols = list(rows[0].keys()) if rows else []
    with open(os.path.join(a.out, "soak.csv"), "w") as f:
        f.write(",".join(cols) + "\n")
        for r in rows:
            f.write(",".join(("%.3f" % v) if isinstance(v, float) else str(v) for v in (r[c] for c in cols)) + "\n")
    with open(os.path.join(a.out, "events.csv"), "w") as f:
        f.write("t_s,kind,ok,seconds,detail\n")
        for e in events:
            f.write('%.1f,%s,%d,%.2f,"%s"\n' % (e[0], e[1], e[2], e[3], str(e[4]).replace('"', "'")))

    # ---- verdict
    n = len(rows)
    after = rows[int(n * a.warmup) :] if n else []
    rss_slope = slope_per_min([r["t_s"] for r in after], [r["rss_bytes"] / 2**20 for r in after])
    anon_slope = slope_per_min([r["t_s"] for r in after], [r["rss_anon_bytes"] / 2**20 for r in after])
    fd_slope = slope_per_min([r["t_s"] for r in after], [r["fds"] for r in after])
    over = [r for r in rows if r["budget_bytes"] < 0 or r["resident_bytes"] > r["budget_bytes"]]
    read_errors = sum(r["errors"] for r in rows)
    control_errors = sum(1 for e in events if not e[2])
    third = n // 3

    def pooled(rs):
        lat = []
        for r in rs:
            w = int(r["t_s"] // a.window) - 1
            for part in windows.get(w, {"lat": []})["lat"]:
                lat.extend(part)
        return lat

    mid_lat, last_lat = pooled(rows[third : 2 * third]), pooled(rows[2 * third :])
    p99_mid, p99_last = percentile(mid_lat, 99), percentile(last_lat, 99)
    all_lat = pooled(rows)
    total_reads = sum(r["reads"] for r in rows)
    statuses = {}
    for w, agg in windows.items():
        if w >= n:
            continue  # after the last sample
        for kk, v in agg["status"].items():
            statuses[kk] = statuses.get(kk, 0) + v
    kinds = {}
    for e in events:
        d = kinds.setdefault(e[1], [0, 0, 0.0])
        d[0 if e[2] else 1] += 1
        d[2] = max(d[2], e[3])
    gen_cpu = sum(worker_cpu)
    checks = [
        ("errors", read_errors == 0 and control_errors == 0,
         "%d read errors of %d reads, %d failed control actions" % (read_errors, total_reads, control_errors)),
        ("RSS flat", rss_slope < a.rss_slope,
         "slope %.3f MiB/min after the first %d%% (limit %.2f; anonymous %.3f MiB/min)" % (
             rss_slope, a.warmup * 100, a.rss_slope, anon_slope)),
        ("descriptors flat", fd_slope < a.fd_slope,
         "slope %.3f fd/min after the first %d%% (limit %.2f)" % (fd_slope, a.warmup * 100, a.fd_slope)),
        ("resident <= budget", not over and n > 0,
         "%d of %d samples over (max resident %.1f MiB, budget %.1f MiB)" % (
             len(over), n, max((r["resident_bytes"] for r in rows), default=0) / 2**20,
             (rows[0]["budget_bytes"] if rows else 0) / 2**20)),
        ("p99 stable", p99_last <= a.p99_ratio * p99_mid,
         "p99 last third %.1f ms, middle third %.1f ms (ratio %.2f, limit %.1f)" % (
             p99_last, p99_mid, p99_last / p99_mid if p99_mid else float("nan"), a.p99_ratio)),
    ]
    passed = all(ok for _, ok, _ in checks)
    lines = []
    lines.append("soak: %.1f min, %d samples, %d connections, %d generator processes" % (a.minutes, n, a.connections, a.processes))
    lines.append("reads: %d (%.0f/s mean, %.1f MiB/s), p50 %.2f ms, p99 %.1f ms over the run; statuses %s" % (
        total_reads, total_reads / max(1, duration), sum(r["read_mib_per_s"] for r in rows) / max(1, n),
        percentile(all_lat, 50), percentile(all_lat, 99), dict(sorted(statuses.items()))))
    lines.append("generator CPU: %.0f%% of one core over %d processes (%.0f%% each); vsmd CPU mean %.0f%% of one core" % (
        100 * gen_cpu / max(1, duration), a.processes, 100 * gen_cpu / max(1, duration) / a.processes,
        sum(r["vsmd_cpu_pct"] for r in rows[1:]) / max(1, n - 1)))
    lines.append("control: " + ", ".join("%s %d ok / %d failed (longest %.1f s)" % (k2, v[0], v[1], v[2]) for k2, v in sorted(kinds.items())))
    if rows:
        lines.append("RSS %.1f -> %.1f MiB (max %.1f; anonymous %.1f -> %.1f); descriptors %d -> %d (max %d); cache evictions %d, exhausted %d" % (
            rows[0]["rss_bytes"] / 2**20, rows[-1]["rss_bytes"] / 2**20, max(r["rss_bytes"] for r in rows) / 2**20,
            rows[0]["rss_anon_bytes"] / 2**20, rows[-1]["rss_anon_bytes"] / 2**20,
            rows[0]["fds"], rows[-1]["fds"], max(r["fds"] for r in rows), rows[-1]["evictions"], rows[-1]["exhausted"]))
    for name, ok, why in checks:
        lines.append("  %-20s %s  %s" % (name, "ok  " if ok else "FAIL", why))
    for e in worker_errors[:10]:
        lines.append("  read error at %.1f s: %s: %s" % e)
    for e in [e for e in events if not e[2]][:10]:
        lines.append("  control failure at %.1f s: %s: %s" % (e[0], e[1], e[4]))
    lines.append("PASSED" if passed else "FAILED")
    summary = "\n".join(lines)
    print(summary, flush=True)
    with open(os.path.join(a.out, "summary.txt"), "w") as f:
        f.write(summary + "\n")
    if rows:
        plot(rows, os.path.join(a.out, "soak.png"), "vsmd soak, %.0f min, %s\n%s" % (a.minutes, "PASSED" if passed else "FAILED", "\n".join(why for _, _, why in checks)))
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
