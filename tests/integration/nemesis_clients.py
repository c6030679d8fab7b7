"""The nemesis's clients (nemesis_test.py) and the history they and the nemesis record: two
writers (merges, and restores 1 in 6) and three readers (a tileset and three of its GLBs; the
hierarchy, again by ?v=, and three patches' positions), all through the front."""

import hashlib
import json
import os
import random
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cluster_support  # noqa: E402
from nemesis_cluster import TOKEN  # noqa: E402
from nemesis_models import DETAILS, TARGETS  # noqa: E402


def digest(body):
    return hashlib.sha256(body).hexdigest()[:16]


# -- the history ------------------------------------------------------------------------------

class History:
    def __init__(self):
        self.lock = threading.Lock()
        self.lane = None  # the Nemesis's thread-local lane (its `number`), set by the test
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
        fields["lane"] = getattr(self.lane, "number", 0)
        with self.lock:
            self.faults.append(fields)
        print("%7.2f fault %s" % (fields["start"], " ".join(
            "%s=%s" % (k, v) for k, v in fields.items() if k not in ("start",))), flush=True)


def front_get(front, path, timeout=15):
    """(status, headers, body) through the front, (None, None, error text) when it could not
    answer at all."""
    try:
        return cluster_support.request(front + path, timeout=timeout)
    except OSError as e:
        return None, None, str(e).encode()


# -- the clients ------------------------------------------------------------------------------

class Clients:
    def __init__(self, history, seed, stop, front):
        self.history = history
        self.front = front
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
                status, _, body = front_get(self.front, "/v1/models/%s/revisions" % target)
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
            status, headers, answer = cluster_support.request(self.front + path, "POST", body,
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
            status, _, answer = front_get(self.front, "/v1/jobs/" + job_id)
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
        status, headers, body = front_get(self.front, path)
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

