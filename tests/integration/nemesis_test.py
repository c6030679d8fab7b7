#!/usr/bin/python3
"""No lost write under concurrency (issue 32): a randomized fault run of a three-node cluster.

    /usr/bin/python3 nemesis_test.py --vsm <vsm> --vsmd <vsmd> --lib <libvsm_fault_inject.so>
                                     --work <dir> --repo <source tree>
                                     [--seconds S] [--seed N] [--lanes L]

S (default 60, or VSM_NEMESIS_SECONDS; 600 is the long mode) is how long the nemesis acts; the
seed (VSM_NEMESIS_SEED, else random) is printed, and given again it replays the same choices:
the same faults in the same order with the same parameters per lane, the same operations per
client thread (what happens between threads still depends on timing). L (default 2,
VSM_NEMESIS_LANES) lanes of faults act side by side.

The cluster is deploy/local-cluster.sh's (cluster_support.LocalCluster): real etcd, three vsmd
nodes over one data root (lease TTL 5 s, --keep-revisions 10000 so that every revision stays
readable to the checker), real nginx in front. Each node is then restarted by the test behind a
TCP proxy of its own to etcd (EtcdProxy, here) and with tests/fault's LD_PRELOAD library, so that
the nemesis can cut one node off etcd and hold its reads.

Models (synthetic, GDAL): three targets t0, t1, t2 (the same flat surface at 100 m, 257 x 257
samples of 2^-12 degrees, patches of 65) and twelve details d0..d11 (33 x 33 samples at a quarter
of that spacing, each in its own place inside the targets and flat at 1000 + 100 i m). A merge of
di into a target is seen in any revision by reading the height at di's centre: 1000 + 100 i when
di is in, 100 when not (read from the OPC files by check_import.py's reader, none of vsm's code).

Clients through the front (nginx), every operation recorded with its start and end, result,
version seen and body digest:
- two writers: merge jobs (a random detail into a random target) and restores of a random kept
  revision (1 in 6), each job followed until it ends or is lost with its node;
- three readers: a tileset.json and three of its GLBs (each by its `?v=`), the hierarchy, the
  hierarchy again by `?v=` its version, and the positions of three of its patches by `?v=`.

The nemesis, in each lane one fault after another at random (a pause of 0.2 to 1.5 s between),
until the time is up:
- kill_writer, kill_replica: kill -9 of the node writing a random model (or of one that does
  not), restarted after 0 to 2 s;
- disk_fault: the fault library of a writer armed (VSM_FAULT_ARM, a file the test writes): its
  next call of a random class (create, write, rename, sync, mkdir, unlink) fails with ENOSPC or
  EIO, or the next open for reading (`read`) of any node with EIO; disarmed after 5 s if no such
  call came;
- pause_etcd, pause_node: SIGSTOP for 1 to 10 s (twice the TTL), then SIGCONT;
- cut_etcd: one node's proxy to etcd cut for 1 to 10 s, either reset (connections closed and
  refused) or a black hole (connections kept, nothing goes through), while the others reach it;
- slow_reads: a replica's reads held for 0.5 to 3 s: the fault library's gate on its `read`
  class (every open for reading under the data root waits while the gate file says 0), released
  by the nemesis's timer.
A node that exits by itself is restarted and counted (not a check).

Then everything is healed (proxies open, processes continued, gates removed), the clients stop,
the test waits until no job is queued or running, and checks:
1. acknowledged merges: every merge job that ended succeeded is the revision its result names
   (the revision list records the job) and that revision has the detail; every revision's
   details are what the chain of revisions says (a merge adds its detail to its parent's, a
   restore has the restored revision's), the final model's included; no revision was made by a
   job no client submitted (beyond the submissions the front answered with an error or not at
   all), or by a job that ended failed or cancelled; no job made two, and no two acknowledged
   jobs name one version;
2. one content per version: every hierarchy read as version N (unversioned through the front,
   by ?v=N through the front, and by ?rev=N from each node at the end) has the same bytes; every
   tileset of model version N the same bytes; every GLB and positions of one patch version the
   same bytes;
3. convergence: every node serves, for every model, the version etcd's writer serves, with the
   same hierarchy bytes;
4. no mix: a GLB read by a tileset's `?v=K` answers patch version K, positions read by `?v=N`
   (N the version of the hierarchy that listed the patch) the patch version that hierarchy says,
   from a snapshot of N or later (X-VSM-Patch-Version, X-VSM-Model-Version), or not at all; a
   hierarchy by ?v=N says N; a tileset's X-VSM-Model-Version is its document's model_version;
5. `vsm validate` passes for every model.
The counts are printed: operations by kind and result, faults by kind (and injected disk faults
that fired), each check. Exit 1 when a check fails.
"""

import argparse
import collections
import hashlib
import json
import os
import random
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.parse

import numpy as np
from osgeo import gdal, osr

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cluster_support  # noqa: E402
from check_import import Patch, ecef_to_geodetic, read_hierarchy  # noqa: E402

gdal.UseExceptions()
ARGS = None
TOKEN = "nemesis-token"
LEASE_TTL = 5  # seconds
TARGETS = ["t0", "t1", "t2"]
DETAILS = 12
PIXEL = 2.0 ** -12  # degrees, the targets' spacing (about 27 m)
WEST, NORTH = 10.0, 0.05
BASE_HEIGHT = 100.0
FAULT_CLASSES = ["create", "write", "rename", "sync", "mkdir", "unlink", "read"]


def detail_height(i):
    return 1000.0 + 100.0 * i


def detail_place(i):
    """(column, row) of the target pixel under detail i's first pixel."""
    return 20 + 56 * (i % 4), 20 + 70 * (i // 4)


def detail_centre(i):
    """(lon, lat) of detail i's centre: 33 samples of a quarter pixel, 8.25 target pixels."""
    c, r = detail_place(i)
    return WEST + (c + 4.125) * PIXEL, NORTH - (r + 4.125) * PIXEL


def digest(body):
    return hashlib.sha256(body).hexdigest()[:16]


def write_raster(path, heights, west, north, pixel):
    rows, cols = heights.shape
    ds = gdal.GetDriverByName("GTiff").Create(path, cols, rows, 1, gdal.GDT_Float32)
    ds.SetGeoTransform((west, pixel, 0.0, north, 0.0, -pixel))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ds.SetProjection(srs.ExportToWkt())
    ds.GetRasterBand(1).WriteArray(heights.astype(np.float32))
    ds = None


def make_models(data, work):
    def vsm_import(raster, model, size):
        subprocess.run([ARGS.vsm, "import", raster, os.path.join(data, model), "--patch-size",
                        str(size)], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)

    base = os.path.join(work, "base.tif")
    write_raster(base, np.full((257, 257), BASE_HEIGHT), WEST, NORTH, PIXEL)
    for target in TARGETS:
        vsm_import(base, target, 65)
    for i in range(DETAILS):
        c, r = detail_place(i)
        raster = os.path.join(work, "d%d.tif" % i)
        write_raster(raster, np.full((33, 33), detail_height(i)), WEST + c * PIXEL,
                     NORTH - r * PIXEL, PIXEL / 4)
        vsm_import(raster, "d%d" % i, 33)


LEAF_HEIGHTS = {}  # (opc, folder) -> {detail: (distance in degrees, height)}: folders are shared


def leaf_heights(opc, patches_dir, folder):
    """{detail: (distance, height)} of the vertex of a leaf patch nearest each detail's centre
    (for the centres inside the patch's lon/lat range)."""
    if (opc, folder) not in LEAF_HEIGHTS:
        patch = Patch(patches_dir, folder, None)
        patch.expand(patch.vsm_size or 65)
        g = patch.grid.reshape(-1, 3)
        g = g[~np.isnan(g[:, 0])]
        found = {}
        if len(g):
            lon, lat, h = ecef_to_geodetic(g[:, 0], g[:, 1], g[:, 2])
            for i in range(DETAILS):
                x, y = detail_centre(i)
                if lon.min() <= x <= lon.max() and lat.min() <= y <= lat.max():
                    d = np.hypot(lon - x, lat - y)
                    j = int(np.argmin(d))
                    found[i] = (float(d[j]), float(h[j]))
        LEAF_HEIGHTS[(opc, folder)] = found
    return LEAF_HEIGHTS[(opc, folder)]


def details_in(opc, hierarchy_file):
    """{detail index: True (in), False (not in), or the height found} of one revision of a
    target, from its hierarchy file and leaf patches alone (check_import.py's reader): the height
    of the leaf vertex nearest each detail's centre."""
    patches_dir, root, children = read_hierarchy(opc, hierarchy_file)
    best = {}
    stack = [root]
    seen = set()
    while stack:
        folder = stack.pop()
        if folder in seen:
            raise AssertionError("%s %s: %s twice in the tree" % (opc, hierarchy_file, folder))
        seen.add(folder)
        if children.get(folder):
            stack.extend(children[folder].values())
            continue
        for i, (d, h) in leaf_heights(opc, patches_dir, folder).items():
            if i not in best or d < best[i][0]:
                best[i] = (d, h)
    result = {}
    for i in range(DETAILS):
        h = best.get(i, (None, None))[1]
        if h is not None and abs(h - detail_height(i)) < 1.0:
            result[i] = True
        elif h is not None and abs(h - BASE_HEIGHT) < 1.0:
            result[i] = False
        else:
            result[i] = h
    return result


# -- the proxy to etcd ------------------------------------------------------------------------

class EtcdProxy:
    """A TCP proxy on 127.0.0.1 in front of etcd for one node. cut("reset") closes its
    connections and refuses new ones; cut("blackhole") keeps them but lets nothing through;
    restore() lets everything through again."""

    def __init__(self, target):
        parsed = urllib.parse.urlparse(target)
        self.target = (parsed.hostname, parsed.port)
        self.listener = socket.socket()
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(64)
        self.url = "http://127.0.0.1:%d" % self.listener.getsockname()[1]
        self.mode = "open"
        self.lock = threading.Lock()
        self.connections = set()  # sockets, both ends
        self.closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while not self.closed:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            with self.lock:
                mode = self.mode
            if mode == "reset":
                client.close()
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=2)
            except OSError:
                client.close()
                continue
            with self.lock:
                self.connections.update((client, upstream))
            threading.Thread(target=self._pump, args=(client, upstream), daemon=True).start()

    def _pump(self, a, b):
        try:
            while not self.closed:
                with self.lock:
                    if a not in self.connections:
                        return
                    mode = self.mode
                if mode == "blackhole":
                    time.sleep(0.05)
                    continue
                readable, _, _ = select.select([a, b], [], [], 0.1)
                for source in readable:
                    data = source.recv(65536)
                    if not data:
                        return
                    (b if source is a else a).sendall(data)
        except OSError:
            pass
        finally:
            with self.lock:
                self.connections.discard(a)
                self.connections.discard(b)
            for s in (a, b):
                try:
                    s.close()
                except OSError:
                    pass

    def cut(self, mode):
        with self.lock:
            self.mode = mode
            victims = list(self.connections) if mode == "reset" else []
            if mode == "reset":
                self.connections.clear()
        for s in victims:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def restore(self):
        with self.lock:
            self.mode = "open"

    def close(self):
        self.closed = True
        self.cut("reset")
        self.listener.close()


# -- the nodes --------------------------------------------------------------------------------

class Node:
    """One vsmd node, restarted by the test with its own proxy to etcd and the fault library."""

    def __init__(self, name, url, argv, proxy, directory, cluster):
        self.name = name
        self.url = url
        self.proxy = proxy
        self.cluster = cluster
        self.argv = list(argv)
        i = self.argv.index("--coordinator")
        self.argv[i + 1] = proxy.url
        self.gate = os.path.join(directory, "gates", name)
        self.reports = os.path.join(directory, "gates", name + ".report")
        self.arm = os.path.join(directory, "gates", name + ".arm")
        self.log = os.path.join(directory, "logs", name + ".log")
        self.proc = None
        self.stopped = False
        self.lock = threading.Lock()  # held while the nemesis restarts it

    def env(self, fault=None):
        env = dict(os.environ)
        env["LD_PRELOAD"] = ARGS.lib
        env["VSM_FAULT_PREFIX"] = os.path.join(self.cluster.dir, "data")
        env["VSM_FAULT_HOLD"] = "read"
        env["VSM_FAULT_GATE"] = self.gate
        env["VSM_FAULT_REPORT"] = self.reports
        env["VSM_FAULT_ARM"] = self.arm
        env["ASAN_OPTIONS"] = (env.get("ASAN_OPTIONS", "") + ":verify_asan_link_order=0").lstrip(":")
        if fault is not None:
            env["VSM_FAULT_CLASS"], env["VSM_FAULT_N"], env["VSM_FAULT_ERRNO"] = fault
        return env

    def start(self, fault=None):
        with open(self.log, "a") as log:
            log.write("=== nemesis: started%s\n" % (" with fault %s" % (fault,) if fault else ""))
            self.proc = subprocess.Popen(self.argv, env=self.env(fault), stdout=log,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         start_new_session=True)
        self.stopped = False
        self.cluster.set_pid(self.name, self.proc.pid)

    def pid(self):
        return self.proc.pid if self.proc else self.cluster.pids[self.name]

    def signal(self, sig):
        try:
            os.kill(self.pid(), sig)
        except ProcessLookupError:
            pass

    def kill9(self):
        if self.stopped:
            self.signal(signal.SIGCONT)
        self.signal(signal.SIGKILL)
        if self.proc:
            self.proc.wait()
        self.stopped = False

    def exited(self):
        """The exit status when the node ended by itself, else None."""
        return self.proc.poll() if self.proc else None

    def ready(self, timeout=60):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if cluster_support.request(self.url + "/readyz", timeout=2)[0] == 200:
                    return True
            except OSError:
                pass
            if self.exited() is not None:
                return False
            time.sleep(0.1)
        return False


# -- the history ------------------------------------------------------------------------------

class History:
    def __init__(self):
        self.lock = threading.Lock()
        self.ops = []
        self.faults = []
        self.t0 = time.monotonic()

    def now(self):
        return time.monotonic() - self.t0

    def op(self, **fields):
        """Records an operation; returns its record (the caller may add to it)."""
        with self.lock:
            self.ops.append(fields)
        return fields

    def restart_clock(self):
        self.t0 = time.monotonic()

    def fault(self, **fields):
        fields["lane"] = getattr(NEMESIS_LANE, "number", 0)
        with self.lock:
            self.faults.append(fields)
        print("%7.2f fault %s" % (fields["start"], " ".join(
            "%s=%s" % (k, v) for k, v in fields.items() if k not in ("start",))), flush=True)


def front_get(path, timeout=15):
    """(status, headers, body) through the front, (None, None, error text) when it could not
    answer at all."""
    try:
        return cluster_support.request(FRONT + path, timeout=timeout)
    except OSError as e:
        return None, None, str(e).encode()


FRONT = None
NEMESIS_LANE = None  # the Nemesis's thread-local lane


class Clients:
    def __init__(self, history, seed, stop):
        self.history = history
        self.seed = seed
        self.stop = stop
        self.threads = []

    def start(self):
        for i in range(2):
            self.threads.append(threading.Thread(target=self.writer, args=(i,), daemon=True))
        for i in range(3):
            self.threads.append(threading.Thread(target=self.reader, args=(i,), daemon=True))
        for t in self.threads:
            t.start()

    def join(self):
        for t in self.threads:
            t.join(timeout=300)
            if t.is_alive():
                raise AssertionError("a client thread did not end")

    # Writers --------------------------------------------------------------------------------

    def writer(self, index):
        rng = random.Random(self.seed * 1000 + index)
        h = self.history
        while not self.stop.is_set():
            target = rng.choice(TARGETS)
            if rng.random() < 1 / 6:
                start = h.now()
                status, _, body = front_get("/v1/models/%s/revisions" % target)
                if status != 200:
                    h.op(kind="revisions", start=start, end=h.now(), status=status, model=target)
                    time.sleep(0.2)
                    continue
                revisions = [r["revision"] for r in json.loads(body)["revisions"]
                             if not r["latest"]]
                if not revisions:
                    continue
                revision = rng.choice(revisions)
                self.job(kind="restore", model=target, revision=revision,
                         path="/v1/models/%s/revisions/%d/restore" % (target, revision), body={})
            else:
                source = "d%d" % rng.randrange(DETAILS)
                self.job(kind="merge", model=target, source=source, path="/v1/jobs",
                         body={"type": "merge", "target": target, "source": source})

    def job(self, kind, path, body, **fields):
        h = self.history
        start = h.now()
        try:
            status, headers, answer = cluster_support.request(FRONT + path, "POST", body,
                                                              timeout=30, token=TOKEN)
        except OSError as e:
            status, headers, answer = None, None, str(e).encode()
        if status != 202:
            h.op(kind=kind, start=start, end=h.now(), status=status, result="refused",
                 answer=answer[:200].decode(errors="replace"), **fields)
            time.sleep(0.3)  # a refused write (no writer now): ask again a little later
            return
        job_id = json.loads(answer)["id"]
        node = headers.get("X-VSM-Node")
        # Followed until it ends, or until its node is gone (404 for 5 s) or for 120 s.
        deadline = time.monotonic() + 120
        missing_since = None
        final = None
        while time.monotonic() < deadline:
            status, _, answer = front_get("/v1/jobs/" + job_id)
            if status == 200:
                missing_since = None
                job = json.loads(answer)
                if job["state"] in ("succeeded", "failed", "cancelled"):
                    final = job
                    break
            elif status == 404:
                missing_since = missing_since or time.monotonic()
                if time.monotonic() - missing_since > 5:
                    break
            time.sleep(0.1)
        result = final["state"] if final else ("lost" if missing_since else "unknown")
        outcome = (final or {}).get("result") or {}
        h.op(kind=kind, start=start, end=h.now(), status=202, result=result, job=job_id,
             node=node, version=outcome.get("version"), base=outcome.get("base_version"),
             error=(final or {}).get("error"), **fields)

    # Readers --------------------------------------------------------------------------------

    def reader(self, index):
        rng = random.Random(self.seed * 1000 + 100 + index)
        while not self.stop.is_set():
            target = rng.choice(TARGETS)
            if rng.random() < 0.5:
                self.read_tileset(rng, target)
            else:
                self.read_hierarchy(rng, target)

    def read(self, kind, model, path, **fields):
        h = self.history
        start = h.now()
        status, headers, body = front_get(path)
        op = dict(kind=kind, start=start, end=h.now(), status=status, model=model, path=path,
                  **fields)
        if status != 200:
            op["answer"] = body[:200].decode(errors="replace")
        if status == 200:
            op["digest"] = digest(body)
            op["node"] = headers.get("X-VSM-Node")
            op["model_version"] = headers.get("X-VSM-Model-Version")
            op["patch_version"] = headers.get("X-VSM-Patch-Version")
        return status, body, h.op(**op)

    def read_tileset(self, rng, target):
        status, body, op = self.read("tileset", target, "/v1/models/%s/3dtiles/tileset.json"
                                     % target)
        if status != 200:
            return
        tileset = json.loads(body)
        op["version"] = tileset["asset"]["extras"]["model_version"]
        uris = []
        stack = [tileset["root"]]
        while stack:
            tile = stack.pop()
            if "content" in tile:
                uris.append(tile["content"]["uri"])
            stack.extend(tile.get("children", []))
        for uri in rng.sample(uris, min(3, len(uris))):
            key, _, query = uri.partition(".glb?v=")
            self.read("glb", target, "/v1/models/%s/3dtiles/%s" % (target, uri), key=key,
                      want=int(query), tileset_version=op["version"])

    def read_hierarchy(self, rng, target):
        status, body, op = self.read("hierarchy", target, "/v1/models/%s/hierarchy" % target)
        if status != 200:
            return
        hierarchy = json.loads(body)
        version = hierarchy["version"]
        op["version"] = version
        status, again, op = self.read("hierarchy_v", target, "/v1/models/%s/hierarchy?v=%d"
                                      % (target, version), want=version)
        if status == 200:
            op["version"] = json.loads(again)["version"]
        patches = []
        stack = [hierarchy["root"]]
        while stack:
            node = stack.pop()
            patches.append((node["key"], node["version"]))
            stack.extend(node.get("children", []))
        for key, patch_version in rng.sample(patches, min(3, len(patches))):
            self.read("positions", target, "/v1/models/%s/patches/%s/positions?v=%d"
                      % (target, key, version), key=key, want=version,
                      want_patch=patch_version)


# -- the nemesis ------------------------------------------------------------------------------

class Nemesis:
    KINDS = ["kill_writer", "kill_replica", "disk_fault", "pause_etcd", "pause_node", "cut_etcd",
             "slow_reads"]

    def __init__(self, history, seed, nodes, etcd_pid, etcd_url, directory):
        self.history = history
        self.seed = seed
        self.lane = threading.local()  # rng, number: each lane's own
        self.nodes = nodes
        self.etcd_pid = etcd_pid
        self.etcd_url = etcd_url
        self.dir = directory
        self.exits = []

    def writer_of(self, model):
        try:
            return cluster_support.etcd_value(self.etcd_url, "/vsm/writers/" + model)
        except (OSError, AssertionError):
            return None

    def pick(self, writer):
        """A node: the writer of a random model (writer=True) or one that does not write it."""
        model = self.lane.rng.choice(TARGETS)
        names = sorted(self.nodes)
        holder = self.writer_of(model)
        if writer:
            return self.nodes[holder] if holder in self.nodes else self.nodes[self.lane.rng.choice(names)]
        others = [n for n in names if n != holder]
        return self.nodes[self.lane.rng.choice(others)]

    def supervise(self):
        """Restarts a node that exited by itself (counted)."""
        for node in self.nodes.values():
            if not node.lock.acquire(blocking=False):
                continue  # a lane is restarting it
            try:
                code = node.exited()
                if code is not None:
                    self.exits.append((node.name, code, self.history.now()))
                    print("%7.2f %s exited by itself (status %s): restarted" %
                          (self.history.now(), node.name, code), flush=True)
                    node.start()
                    node.ready()
            finally:
                node.lock.release()

    def run(self, seconds, lanes):
        """`lanes` threads, each choosing faults one after the other (so up to `lanes` act at
        once), lane i with its own generator seeded from the seed and i."""
        end = time.monotonic() + seconds
        errors = []

        def lane(number):
            self.lane.rng = random.Random(self.seed if number == 0 else self.seed * 7919 + number)
            self.lane.number = number
            try:
                while time.monotonic() < end:
                    kind = self.lane.rng.choice(self.KINDS)
                    getattr(self, kind)(kind)
                    self.supervise()
                    time.sleep(self.lane.rng.uniform(0.2, 1.5))
            except Exception as e:  # noqa: BLE001 (raised again below)
                errors.append(e)

        threads = [threading.Thread(target=lane, args=(i,)) for i in range(lanes)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if errors:
            raise errors[0]

    def restart(self, node, kind, fault=None):
        with node.lock:
            start = self.history.now()
            node.kill9()
            down = self.lane.rng.uniform(0, 2)
            time.sleep(down)  # how long the node stays down: a fault's duration, not a wait
            node.start(fault)
            ready = node.ready()
        self.history.fault(kind=kind, node=node.name, start=start, end=self.history.now(),
                           down=round(down, 2), ready=ready)

    def kill_writer(self, kind):
        self.restart(self.pick(True), kind)

    def kill_replica(self, kind):
        self.restart(self.pick(False), kind)

    def disk_fault(self, kind):
        """Arms the fault library of a writer (VSM_FAULT_ARM): its next call of the class fails.
        Disarmed when it has not fired within 5 s (no write came)."""
        cls = self.lane.rng.choice(FAULT_CLASSES)
        error = "EIO" if cls == "read" else self.lane.rng.choice(["ENOSPC", "EIO"])
        node = self.pick(cls != "read")
        start = self.history.now()
        with open(node.arm + ".new", "w") as f:
            f.write("%s %s\n" % (cls, error))
        os.replace(node.arm + ".new", node.arm)
        deadline = time.monotonic() + 5
        while os.path.exists(node.arm) and time.monotonic() < deadline:
            time.sleep(0.05)
        try:
            os.remove(node.arm)
            fired = False
        except FileNotFoundError:
            fired = True
        self.history.fault(kind=kind, node=node.name, start=start, end=self.history.now(),
                           fault="%s %s" % (cls, error), fired=fired)

    def pause_etcd(self, kind):
        start = self.history.now()
        seconds = self.lane.rng.uniform(1, 2 * LEASE_TTL)
        os.kill(self.etcd_pid, signal.SIGSTOP)
        try:
            time.sleep(seconds)  # the fault's duration
        finally:
            os.kill(self.etcd_pid, signal.SIGCONT)
        self.history.fault(kind=kind, start=start, end=self.history.now(),
                           seconds=round(seconds, 2))

    def pause_node(self, kind):
        node = self.pick(self.lane.rng.random() < 0.5)
        start = self.history.now()
        seconds = self.lane.rng.uniform(1, 2 * LEASE_TTL)
        node.signal(signal.SIGSTOP)
        node.stopped = True
        try:
            time.sleep(seconds)  # the fault's duration
        finally:
            node.signal(signal.SIGCONT)
            node.stopped = False
        self.history.fault(kind=kind, node=node.name, start=start, end=self.history.now(),
                           seconds=round(seconds, 2))

    def cut_etcd(self, kind):
        node = self.pick(self.lane.rng.random() < 0.5)
        mode = self.lane.rng.choice(["reset", "blackhole"])
        start = self.history.now()
        seconds = self.lane.rng.uniform(1, 2 * LEASE_TTL)
        node.proxy.cut(mode)
        try:
            time.sleep(seconds)  # the fault's duration
        finally:
            node.proxy.restore()
        self.history.fault(kind=kind, node=node.name, mode=mode, start=start,
                           end=self.history.now(), seconds=round(seconds, 2))

    def slow_reads(self, kind):
        node = self.pick(False)
        start = self.history.now()
        seconds = self.lane.rng.uniform(0.5, 3)
        with open(node.gate + ".new", "w") as f:
            f.write("0\n")
        os.replace(node.gate + ".new", node.gate)  # every read-open from now on waits
        try:
            time.sleep(seconds)  # the fault's duration
        finally:
            try:
                os.remove(node.gate)
            except FileNotFoundError:
                pass  # another lane's slow_reads of this node ended first
        held = [n for n in os.listdir(os.path.dirname(node.gate))
                if n.startswith(node.name + ".held-")]
        self.history.fault(kind=kind, node=node.name, start=start, end=self.history.now(),
                           seconds=round(seconds, 2), held_now=len(held))

    def heal(self):
        os.kill(self.etcd_pid, signal.SIGCONT)
        for node in self.nodes.values():
            node.proxy.restore()
            node.signal(signal.SIGCONT)
            for path in (node.gate, node.arm):
                try:
                    os.remove(path)
                except FileNotFoundError:
                    pass
        self.supervise()


# -- the checks -------------------------------------------------------------------------------

class Checks:
    def __init__(self):
        self.results = collections.OrderedDict()

    def add(self, name, failures, counted):
        self.results[name] = (failures, counted)
        print("check %-34s %s: %s" % (name, "FAILED" if failures else "ok", counted), flush=True)
        for f in failures[:20]:
            print("    " + f, flush=True)
        if len(failures) > 20:
            print("    ... %d more" % (len(failures) - 20), flush=True)

    def failed(self):
        return [name for name, (failures, _) in self.results.items() if failures]


def quiesce(nodes, timeout=180):
    """Waits until no node has a queued or running job."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        busy = 0
        for node in nodes.values():
            try:
                status, _, body = cluster_support.request(node.url + "/v1/jobs", timeout=5)
            except OSError:
                busy += 1
                continue
            if status != 200:
                busy += 1
                continue
            busy += sum(1 for j in json.loads(body)["jobs"] if j["state"] in ("queued", "running"))
        if busy == 0:
            return True
        time.sleep(0.2)
    return False


def converge(cluster, nodes, models, checks, timeout=120):
    """Check 3, and the final versions by model."""
    deadline = time.monotonic() + timeout
    failures = []
    while True:
        failures = []
        finals = {}
        for model in models:
            writer = cluster_support.etcd_value(cluster.etcd, "/vsm/writers/" + model)
            if writer not in nodes:
                failures.append("%s: no writer in etcd (%s)" % (model, writer))
                continue
            answers = {}
            for name, node in nodes.items():
                try:
                    status, _, body = cluster_support.request(
                        node.url + "/v1/models/%s/hierarchy" % model, timeout=10)
                except OSError as e:
                    status, body = None, str(e).encode()
                answers[name] = (status, body)
            status, body = answers[writer]
            if status != 200:
                failures.append("%s: the writer %s answers %s" % (model, writer, status))
                continue
            version = json.loads(body)["version"]
            finals[model] = (writer, version, body)
            for name, (s, b) in answers.items():
                if s != 200 or b != body:
                    failures.append("%s: %s answers %s (version %s), the writer %s version %d%s" % (
                        model, name, s, json.loads(b)["version"] if s == 200 else "-", writer,
                        version, ", other bytes" if s == 200 else ""))
        if not failures or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    checks.add("3 replicas converge", failures,
               "%d models on 3 nodes, versions %s" % (
                   len(models), {m: v for m, (_, v, _) in sorted(finals.items())}))
    return finals


def check_history(history, cluster, nodes, finals, data, checks):
    ops = history.ops
    by_kind = collections.Counter((op["kind"], op.get("result") or op["status"]) for op in ops)
    print("operations: %d" % len(ops), flush=True)
    for (kind, result), n in sorted(by_kind.items(), key=str):
        print("    %-12s %-10s %d" % (kind, result, n), flush=True)

    # 1. Acknowledged merges, and the chain of revisions.
    failures = []
    jobs = {op["job"]: op for op in ops if op.get("job")}
    acked = [op for op in ops if op["kind"] == "merge" and op.get("result") == "succeeded"]
    restored = [op for op in ops if op["kind"] == "restore" and op.get("result") == "succeeded"]
    revisions_seen = 0
    indeterminate = 0
    published_unsure = 0
    for target in TARGETS:
        status, _, body = cluster_support.request(
            nodes[finals[target][0]].url + "/v1/models/%s/revisions" % target
            if target in finals else cluster.front + "/v1/models/%s/revisions" % target)
        if status != 200:
            failures.append("%s: revisions answer %s" % (target, status))
            continue
        revisions = json.loads(body)["revisions"]
        revisions_seen += len(revisions)
        by_number = {r["revision"]: r for r in revisions}
        made_by = collections.Counter(r["job"] for r in revisions if r["job"])
        # A write the front answered with an error or not at all (the node killed or paused
        # meanwhile) may have been taken: its job id is unknown, and so may be one revision.
        unsure = [op for op in ops if op["kind"] in ("merge", "restore") and op["model"] == target
                  and op.get("result") == "refused" and (op["status"] is None or op["status"] >= 500)]
        unknown = 0
        for job, n in made_by.items():
            if n > 1:
                failures.append("%s: job %s made %d revisions" % (target, job, n))
            if job not in jobs:
                unknown += 1
                if unknown > len(unsure):
                    failures.append("%s: revision by job %s, which no client submitted" % (
                        target, job))
            elif jobs[job].get("result") in ("failed", "cancelled"):
                message = (jobs[job].get("error") or {}).get("message", "")
                if jobs[job]["result"] == "failed" and " is published, but " in message:
                    # vsmd's own answer for a commit that took whose directory sync then failed
                    # (ENOSPC/EIO after the rename): published, its durability unknown, and
                    # said so. Not acknowledged, so not a lost write either way.
                    published_unsure += 1
                else:
                    failures.append("%s: job %s %s (%s), but its revision is published" % (
                        target, job, jobs[job]["result"], message[:100]))
        indeterminate += unknown
        opc = os.path.join(data, target)
        latest = max(by_number)
        expected = {}
        for number in sorted(by_number):
            r = by_number[number]
            if r["parent"] is None:
                want = set()
            elif r["restored_from"] is not None:
                want = expected.get(r["restored_from"])
            else:
                job = jobs.get(r["job"])
                parent = expected.get(r["parent"])
                want = None if job is None or parent is None or job["kind"] != "merge" else \
                    parent | {int(job["source"][1:])}
            if r["parent"] is not None and r["job"] is None:
                failures.append("%s: revision %d was made by no job" % (target, number))
            if r["parent"] is not None and r["parent"] != number - 1:
                failures.append("%s: revision %d has parent %s" % (target, number, r["parent"]))
            name = "patchhierarchy.xml" if number == latest else "vsm-revision-%d.xml" % number
            found = details_in(opc, name)
            have = {i for i, v in found.items() if v is True}
            odd = {i: v for i, v in found.items() if v not in (True, False)}
            if odd:
                failures.append("%s revision %d: heights at details' centres that are neither "
                                "the detail's nor the target's: %s" % (target, number, odd))
            if want is not None and have != want:
                failures.append("%s revision %d (%s): details %s, the chain says %s" % (
                    target, number, r["job"], sorted(have), sorted(want)))
            expected[number] = have if want is None else want
        for op in acked + restored:
            if op["model"] != target:
                continue
            r = by_number.get(op["version"])
            if r is None or r["job"] != op["job"]:
                failures.append("%s: job %s (%s %s) succeeded with version %s, but that revision "
                                "is %s" % (target, op["job"], op["kind"],
                                           op.get("source", op.get("revision")), op["version"], r))
            elif op["kind"] == "merge" and int(op["source"][1:]) not in expected[op["version"]]:
                failures.append("%s: job %s merged %s into version %s, which lacks it" % (
                    target, op["job"], op["source"], op["version"]))
        if finals.get(target) and finals[target][1] != latest:
            failures.append("%s: the writer serves version %d, the latest revision is %d" % (
                target, finals[target][1], latest))
    versions = collections.Counter((op["model"], op["version"]) for op in acked + restored)
    for (model, version), n in versions.items():
        if n > 1:
            failures.append("%s: %d acknowledged jobs name version %d" % (model, n, version))
    ended = collections.Counter("%s %s: %s" % (op["kind"], op["result"], (op.get("error") or {}).get(
        "message", "")[:90]) for op in ops if op.get("result") in ("failed", "cancelled"))
    for line, n in sorted(ended.items()):
        print("    %3d x %s" % (n, line), flush=True)
    checks.add("1 acknowledged merges kept", failures,
               "%d merges acknowledged, %d restores, %d revisions checked (%d by a job whose "
               "submission the front answered with an error or not at all, %d by a job that "
               "failed saying its version is published but not known durable)" % (
                   len(acked), len(restored), revisions_seen, indeterminate, published_unsure))

    # 2. One content per version.
    failures = []
    contents = collections.defaultdict(set)  # (what, model, version[, key]) -> digests
    for op in ops:
        if op["status"] != 200 or "digest" not in op:
            continue
        if op["kind"] == "hierarchy":
            contents[("hierarchy", op["model"], op["version"])].add(op["digest"])
        elif op["kind"] == "hierarchy_v":
            contents[("hierarchy", op["model"], op["want"])].add(op["digest"])
        elif op["kind"] == "tileset":
            contents[("tileset", op["model"], op["version"])].add(op["digest"])
        elif op["kind"] == "glb" and op["patch_version"] == str(op["want"]):
            contents[("glb", op["model"], op["want"], op["key"])].add(op["digest"])
        elif op["kind"] == "positions" and op["patch_version"] is not None:
            contents[("positions", op["model"], int(op["patch_version"]), op["key"])].add(
                op["digest"])
    finals_read = 0
    for target in TARGETS:
        status, _, body = cluster_support.request(cluster.front + "/v1/models/%s/revisions"
                                                  % target)
        for r in json.loads(body)["revisions"] if status == 200 else []:
            for name, node in nodes.items():
                s, _, b = cluster_support.request(node.url + "/v1/models/%s/hierarchy?rev=%d"
                                                  % (target, r["revision"]))
                if s == 200:
                    contents[("hierarchy", target, r["revision"])].add(digest(b))
                    finals_read += 1
                else:
                    failures.append("%s: %s answers %d to hierarchy?rev=%d" % (
                        target, name, s, r["revision"]))
    for what, digests in sorted(contents.items(), key=str):
        if len(digests) > 1:
            failures.append("%s: %d different bodies %s" % (what, len(digests), sorted(digests)))
    checks.add("2 one content per version", failures,
               "%d (document, model, version) seen, %d of them at the end from each node" % (
                   len(contents), finals_read))

    # 4. No read returned a mix of versions.
    failures = []
    counted = collections.Counter()
    for op in ops:
        if op["kind"] == "glb":
            counted["glb %s" % op["status"]] += 1
            if op["status"] == 200 and op["patch_version"] != str(op["want"]):
                failures.append("%s: patch version %s for ?v=%s (tileset of version %s)" % (
                    op["path"], op["patch_version"], op["want"], op["tileset_version"]))
        elif op["kind"] == "positions":
            counted["positions %s" % op["status"]] += 1
            # From any snapshot holding the patch as version N holds it: the patch's version
            # as the hierarchy of N says, a snapshot of N or later (proto/openapi.yaml, `v`).
            if op["status"] == 200 and (op["patch_version"] != str(op["want_patch"]) or
                                        int(op["model_version"]) < op["want"]):
                failures.append("%s: model version %s patch version %s, the hierarchy of "
                                "version %s said patch version %s" % (
                                    op["path"], op["model_version"], op["patch_version"],
                                    op["want"], op["want_patch"]))
        elif op["kind"] == "hierarchy_v":
            counted["hierarchy?v= %s" % op["status"]] += 1
            if op["status"] == 200 and op["version"] != op["want"]:
                failures.append("%s: the hierarchy of version %s" % (op["path"], op["version"]))
        elif op["kind"] == "tileset" and op["status"] == 200:
            counted["tileset 200"] += 1
            if op["model_version"] != str(op["version"]):
                failures.append("%s: X-VSM-Model-Version %s, the document says %s" % (
                    op["path"], op["model_version"], op["version"]))
    checks.add("4 no read mixes versions", failures, dict(sorted(counted.items())))


def main():
    global ARGS, FRONT
    parser = argparse.ArgumentParser()
    for name in ("--vsm", "--vsmd", "--lib", "--work", "--repo"):
        parser.add_argument(name, required=True)
    parser.add_argument("--seconds", type=float,
                        default=float(os.environ.get("VSM_NEMESIS_SECONDS", "60")))
    parser.add_argument("--lanes", type=int, default=int(os.environ.get("VSM_NEMESIS_LANES", "2")),
                        help="faults acting at once at most (each lane one after the other)")
    parser.add_argument("--seed", type=int, default=int(os.environ.get(
        "VSM_NEMESIS_SEED", str(int.from_bytes(os.urandom(4), "little")))))
    ARGS = parser.parse_args()
    print("nemesis: seed %d, %g s, %d lanes (replay: --seed %d or VSM_NEMESIS_SEED=%d)" % (
        ARGS.seed, ARGS.seconds, ARGS.lanes, ARGS.seed, ARGS.seed), flush=True)
    directory = os.path.abspath(ARGS.work)
    shutil.rmtree(directory, ignore_errors=True)
    data = os.path.join(directory, "data")
    os.makedirs(data)
    os.makedirs(os.path.join(directory, "gates"))
    make_models(data, directory)
    token = cluster_support.write_token(directory, TOKEN)
    env = dict(os.environ, VSMD=ARGS.vsmd, VSM_LEASE_TTL="%ds" % LEASE_TTL,
               VSM_MEMORY_BUDGET="128MiB", VSM_TOKEN_FILE=token,
               VSMD_ARGS="--keep-revisions 10000")
    cluster = cluster_support.LocalCluster(ARGS.repo, directory, env)
    proxies = []
    nodes = {}
    history = History()
    stop = threading.Event()
    clients = None
    try:
        cluster.up()
        FRONT = cluster.front
        etcd_pid = int(cluster.values["PID_ETCD"])
        # Each node again, with its own proxy to etcd and the fault library.
        for name in sorted(cluster.nodes):
            pid = cluster.pids[name]
            with open("/proc/%d/cmdline" % pid, "rb") as f:
                argv = [a.decode() for a in f.read().split(b"\0") if a]
            proxy = EtcdProxy(cluster.etcd)
            proxies.append(proxy)
            node = Node(name, cluster.nodes[name], argv, proxy, directory, cluster)
            os.kill(pid, signal.SIGTERM)
            deadline = time.monotonic() + 30
            while os.path.exists("/proc/%d" % pid) and time.monotonic() < deadline:
                time.sleep(0.05)
            node.start()
            if not node.ready():
                raise AssertionError(name + " did not start again behind its proxy")
            nodes[name] = node
        print("nodes behind their proxies to etcd: %s" % {n: p.proxy.url for n, p in nodes.items()},
              flush=True)

        global NEMESIS_LANE
        nemesis = Nemesis(history, ARGS.seed, nodes, etcd_pid, cluster.etcd, directory)
        NEMESIS_LANE = nemesis.lane
        clients = Clients(history, ARGS.seed, stop)
        history.restart_clock()
        clients.start()
        started = time.monotonic()
        try:
            nemesis.run(ARGS.seconds, ARGS.lanes)
        finally:
            nemesis.heal()
        print("nemesis over after %.1f s; healed" % (time.monotonic() - started), flush=True)
        stop.set()
        clients.join()
        for node in nodes.values():
            if not node.ready():
                raise AssertionError(node.name + " is not ready after the heal")
        if not quiesce(nodes):
            raise AssertionError("jobs still queued or running 180 s after the clients stopped")

        faults = collections.Counter(f["kind"] for f in history.faults)
        fired = []
        for node in nodes.values():
            if os.path.exists(node.reports):
                with open(node.reports) as f:
                    fired += [line.strip() for line in f if line.strip()]
        print("faults: %d %s; injected disk faults that fired: %d %s; nodes that exited by "
              "themselves: %s" % (sum(faults.values()), dict(sorted(faults.items())), len(fired),
                                  fired, nemesis.exits), flush=True)

        checks = Checks()
        models = TARGETS + ["d%d" % i for i in range(DETAILS)]
        finals = converge(cluster, nodes, models, checks)
        check_history(history, cluster, nodes, finals, data, checks)
    finally:
        stop.set()
        with open(os.path.join(directory, "history.json"), "w") as f:
            json.dump({"seed": ARGS.seed, "ops": history.ops, "faults": history.faults}, f)
        for node in nodes.values():
            node.signal(signal.SIGCONT)
        cluster.down()
        for node in nodes.values():
            if node.proc:
                try:
                    node.proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    node.kill9()
        for proxy in proxies:
            proxy.close()

    # 5. Every model validates (the cluster stopped: the files as they stay).
    failures = []
    for model in models:
        out = subprocess.run([ARGS.vsm, "validate", os.path.join(data, model)],
                             capture_output=True, text=True, timeout=300)
        if out.returncode != 0:
            failures.append("%s: %s" % (model, (out.stdout + out.stderr).strip()[-300:]))
    checks.add("5 vsm validate", failures, "%d models" % len(models))

    failed = checks.failed()
    print("nemesis: seed %d, %d operations, %d faults, checks %s" % (
        ARGS.seed, len(history.ops), len(history.faults),
        "all passed" if not failed else "FAILED: " + ", ".join(failed)), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
