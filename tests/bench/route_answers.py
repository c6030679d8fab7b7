#!/usr/bin/env python3
"""Records what a vsmd binary answers to a fixed list of requests on the demo models, and compares
two such records byte for byte: the check that a change of structure changed no behaviour
(issue 30: "/v1/stats and the routes answer byte for byte the same on the demo model").

  route_answers.py record --vsmd BUILD/server/vsmd --models DEMO/models --out answers.jsonl
  route_answers.py compare before.jsonl after.jsonl

`record` copies the models directory (deploy/demo-setup.sh imports PRISMelevation with its
texture and jacksboro_fault_dem into DEMO/models) into a temporary directory, starts the binary on
it (127.0.0.1, port 0, --port-file, as the integration tests do), and sends, one at a time on one
connection, every request of the list twice (the first answer is made on the CPU pool, the second
comes from the budget on a network thread): the model list and summaries, hierarchy, LOD cuts,
every patch's metadata, positions, coordinates, texture (and by layer), GLB (compressed and not),
tileset.json and the terrain's layer.json (gzipped and not), terrain tiles of the first levels
(with and without extensions), 304s, errors, and /v1/stats. Then it merges jacksboro_fault_dem
into PRISMelevation through the jobs API and sends the list again (version 2: ?rev=1, ?v=1, the
diff and diff.png of revisions 1 and 2), and /v1/stats last. Each answer is one JSON line: status,
headers (but Date), the body's SHA-256, and the body itself when it is short text.

`compare` prints every answer that differs, after masking what legitimately differs between two
runs (MASKS below: job ids, times, and /v1/stats fields that count requests or time), and exits 1
when any does.
"""

import argparse
import gzip
import hashlib
import http.client
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

START_DEADLINE = 60
JOB_DEADLINE = 600
TEXT_LIMIT = 65536

# What differs between two runs without a change of behaviour, by request name prefix: JSON paths
# ("a.b.c") whose values are replaced by "<masked>" before comparing, and headers dropped.
MASKS = {
    # Job ids are random, created/started/finished times are the clock's.
    "job": ["id", "created_at", "started_at", "finished_at", "result.merge_seconds"],
    # A revision records when it was published.
    "revisions": ["revisions.*.time", "revisions.*.job"],
    # Nothing in /v1/stats counts requests or time today; list such fields here if added.
    "stats": [],
}
# After the merge (phase 2) the folders of the rewritten patches carry a random suffix
# (".../0_0_0-v2-02068d14"), so every ETag digesting them (patch, model, view, tileset, terrain
# tile), the patches' "folder" and the tileset's asset.tilesetVersion differ between two runs of
# one binary: these are masked in phase 2, and the JSON bodies compared once parsed and masked
# (every other byte of every body is compared as recorded).
PHASE2_JSON_MASKS = ["**.folder", "asset.tilesetVersion"]
PHASE2_HEADER_MASKS = {"etag"}
# A folder name where a message names it: "4_7_3-v2-f5552abf".
FOLDER = re.compile(r"(\d+_\d+_\d+-v\d+)-[0-9a-f]{8}")
# Date is the clock's, X-Request-Id a random prefix per process and a counter, Location names the job id.
DROPPED_HEADERS = {"date", "location", "x-request-id"}


def request(conn, method, target, headers=None):
    conn.request(method, target, headers=headers or {})
    response = conn.getresponse()
    body = response.read()
    return response.status, [(k.lower(), v) for k, v in response.getheaders()], body


PHASE = [1]


def record_one(conn, out, name, target, headers=None, method="GET"):
    status, response_headers, body = request(conn, method, target, headers)
    entry = {
        "phase": PHASE[0],
        "name": name,
        "method": method,
        "target": target,
        "request_headers": headers or {},
        "status": status,
        "headers": [[k, v] for k, v in response_headers if k not in DROPPED_HEADERS],
        "sha256": hashlib.sha256(body).hexdigest(),
        "size": len(body),
    }
    text = body
    if ("content-encoding", "gzip") in response_headers:
        text = gzip.decompress(body)
    try:
        if len(text) <= TEXT_LIMIT:
            entry["body"] = text.decode("utf-8")
    except UnicodeDecodeError:
        pass
    out.write(json.dumps(entry, sort_keys=True) + "\n")
    return status, response_headers, body


def twice(conn, out, name, target, headers=None):
    """The pool's answer, then the network thread's (the same bytes, from the budget)."""
    record_one(conn, out, name, target, headers)
    return record_one(conn, out, name + " (again)", target, headers)


def keys_of(node):
    yield node["key"]
    for child in node.get("children", []):
        yield from keys_of(child)


def read_requests(conn, out, model, suffix, version=None):
    """Every read route of `model`; `suffix` is a query added to every target ("?rev=1")."""
    def q(target, extra=""):
        parts = [p for p in (suffix, extra) if p]
        return target + ("?" + "&".join(parts) if parts else "")

    base = "/v1/models/" + model
    twice(conn, out, "model", q(base))
    status, _, body = record_one(conn, out, "hierarchy", q(base + "/hierarchy"))
    record_one(conn, out, "hierarchy depth", q(base + "/hierarchy", "depth=1"))
    record_one(conn, out, "hierarchy root", q(base + "/hierarchy", "root=1_0_0&depth=1"))
    record_one(conn, out, "hierarchy bad root", q(base + "/hierarchy", "root=x"))
    tree = json.loads(body)["root"]
    keys = list(keys_of(tree))
    record_one(conn, out, "lod box", q(base + "/lod", "box=-1e7,-1e7,-1e7,1e7,1e7,1e7&resolution=5000"))
    record_one(conn, out, "lod camera", q(base + "/lod", "eye=0,-9e6,5e6&dir=0,1,-0.5&up=0,0,1&fov=60"
                                          "&width=800&height=600&sse=16"))
    record_one(conn, out, "lod bad", q(base + "/lod", "box=1,2"))
    for key in keys:
        p = base + "/patches/" + key
        _, headers, _ = twice(conn, out, "patch", q(p))
        etag = dict(headers).get("etag")
        twice(conn, out, "positions", q(p + "/positions"))
        record_one(conn, out, "positions 304", q(p + "/positions"), {"If-None-Match": etag or ""})
        twice(conn, out, "coordinates", q(p + "/coordinates"))
        twice(conn, out, "texture", q(p + "/texture"))
        twice(conn, out, "texture layer", q(p + "/texture/Diffuse"))
        record_one(conn, out, "texture other layer", q(p + "/texture/Normals"))
        twice(conn, out, "glb", q(base + "/3dtiles/" + key + ".glb"))
        twice(conn, out, "glb raw", q(base + "/3dtiles/" + key + ".glb", "compress=none"))
        record_one(conn, out, "glb bad", q(base + "/3dtiles/" + key + ".glb", "compress=zip"))
    record_one(conn, out, "patch missing", q(base + "/patches/9_0_0/positions"))
    record_one(conn, out, "patch bad key", q(base + "/patches/nokey/positions"))
    record_one(conn, out, "version too new", q(base + "/patches/0_0_0/positions", "v=99"))
    twice(conn, out, "tileset", q(base + "/3dtiles/tileset.json"))
    twice(conn, out, "tileset gzip", q(base + "/3dtiles/tileset.json"), {"Accept-Encoding": "gzip"})
    twice(conn, out, "tileset raw gzip", q(base + "/3dtiles/tileset.json", "compress=none"),
          {"Accept-Encoding": "gzip"})
    status, _, body = twice(conn, out, "terrain layer", q(base + "/terrain/layer.json"))
    twice(conn, out, "terrain layer gzip", q(base + "/terrain/layer.json"), {"Accept-Encoding": "gzip"})
    if status == 200:
        layer = json.loads(body)
        for z, ranges in enumerate(layer["available"][:4]):
            for r in ranges[:2]:
                for x in range(r["startX"], min(r["endX"], r["startX"] + 2) + 1):
                    for y in range(r["startY"], min(r["endY"], r["startY"] + 1) + 1):
                        t = q("%s/terrain/%d/%d/%d.terrain" % (base, z, x, y))
                        twice(conn, out, "terrain tile", t)
                        twice(conn, out, "terrain tile ext gzip", t,
                              {"Accept": "application/vnd.quantized-mesh;"
                                         "extensions=octvertexnormals-metadata",
                               "Accept-Encoding": "gzip"})
        record_one(conn, out, "terrain tile outside", q(base + "/terrain/0/5/0.terrain"))
    return keys


def record(args):
    work = tempfile.mkdtemp(prefix="route-answers-")
    proc = None
    try:
        models = os.path.join(work, "models")
        shutil.copytree(args.models, models, symlinks=True)
        port_file = os.path.join(work, "port")
        log = open(os.path.join(work, "vsmd.log"), "wb")
        proc = subprocess.Popen([args.vsmd, "--listen", "127.0.0.1:0", "--data-root", models,
                                 "--port-file", port_file, "--memory-budget", args.budget],
                                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + START_DEADLINE
        while not os.path.exists(port_file) or os.path.getsize(port_file) == 0:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("vsmd did not start (see %s)" % log.name)
            time.sleep(0.05)
        with open(port_file) as f:
            port = int(f.read())
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
        with open(args.out, "w") as out:
            record_one(conn, out, "stats", "/v1/stats")
            twice(conn, out, "models", "/v1/models")
            record_one(conn, out, "model missing", "/v1/models/nosuch")
            record_one(conn, out, "revisions", "/v1/models/PRISMelevation/revisions")
            for model in ("jacksboro_fault_dem", "PRISMelevation"):
                read_requests(conn, out, model, "")
            record_one(conn, out, "stats", "/v1/stats")
            # A merge, then the same reads of both versions.
            body = json.dumps({"type": "merge", "target": "PRISMelevation",
                               "source": "jacksboro_fault_dem"})
            conn.request("POST", "/v1/jobs", body=body,
                         headers={"Content-Type": "application/json"})
            response = conn.getresponse()
            job = json.loads(response.read())
            deadline = time.monotonic() + JOB_DEADLINE
            while True:
                status, _, body = request(conn, "GET", "/v1/jobs/" + job["id"])
                state = json.loads(body)
                if state["state"] in ("succeeded", "failed", "cancelled"):
                    break
                if time.monotonic() > deadline:
                    raise SystemExit("the merge did not finish")
                time.sleep(0.2)
            PHASE[0] = 2
            record_one(conn, out, "job", "/v1/jobs/" + job["id"])
            record_one(conn, out, "revisions", "/v1/models/PRISMelevation/revisions")
            read_requests(conn, out, "PRISMelevation", "")
            read_requests(conn, out, "PRISMelevation", "rev=1")
            read_requests(conn, out, "PRISMelevation", "v=1")
            twice(conn, out, "diff", "/v1/models/PRISMelevation/diff?from=1&to=2")
            twice(conn, out, "diff png", "/v1/models/PRISMelevation/diff.png?from=1&to=2&size=256")
            record_one(conn, out, "diff bad", "/v1/models/PRISMelevation/diff?from=1")
            record_one(conn, out, "stats", "/v1/stats")
        conn.close()
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(timeout=60)
        shutil.rmtree(work, ignore_errors=True)


def mask(value, path):
    head, _, rest = path.partition(".")
    if head == "**":  # the key `rest` at any depth
        if isinstance(value, dict):
            if rest in value:
                value[rest] = "<masked>"
            for item in value.values():
                mask(item, path)
        elif isinstance(value, list):
            for item in value:
                mask(item, path)
        return
    if isinstance(value, list) and head == "*":
        for item in value:
            if rest:
                mask(item, rest)
    elif isinstance(value, dict) and head in value:
        if rest:
            mask(value[head], rest)
        else:
            value[head] = "<masked>"


def normalised(entry):
    masks = [m for prefix, ms in MASKS.items() if entry["name"] == prefix
             or entry["name"].startswith(prefix + " ") for m in ms]
    json_body = entry.get("body", "").startswith(("{", "["))
    if entry["phase"] == 2:
        entry = dict(entry)
        entry["headers"] = [[k, "<masked>" if k in PHASE2_HEADER_MASKS else v]
                            for k, v in entry["headers"]]
        entry["request_headers"] = {k: "<masked>" if k.lower() == "if-none-match" else v
                                    for k, v in entry["request_headers"].items()}
        if "body" in entry and FOLDER.search(entry["body"]):
            entry["body"] = FOLDER.sub(r"\1-<random>", entry["body"])
            entry.pop("sha256", None)
            entry.pop("size", None)
            entry["headers"] = [h for h in entry["headers"] if h[0] != "content-length"]
        if json_body:
            masks += PHASE2_JSON_MASKS
    if not masks or not json_body:
        return entry
    entry = dict(entry)
    body = json.loads(entry["body"])
    for m in masks:
        mask(body, m)
    if entry["name"] == "job":
        entry.pop("target")  # names the job's id
    entry["body"] = json.dumps(body, sort_keys=True)
    entry.pop("sha256", None)
    entry.pop("size", None)
    # The length and the ETag of a masked body follow what was masked.
    entry["headers"] = [h for h in entry["headers"] if h[0] not in ("content-length", "etag")]
    return entry


def compare(args):
    with open(args.before) as f:
        before = [json.loads(line) for line in f]
    with open(args.after) as f:
        after = [json.loads(line) for line in f]
    differ = 0
    if len(before) != len(after):
        print("%d answers before, %d after" % (len(before), len(after)))
        differ += 1
    for a, b in zip(before, after):
        na, nb = normalised(a), normalised(b)
        if na != nb:
            differ += 1
            print("DIFFERS: %s %s (%s)" % (a["method"], a["target"], a["name"]))
            for key in sorted(set(na) | set(nb)):
                if na.get(key) != nb.get(key):
                    print("  %s:\n    before %s\n    after  %s" % (key, str(na.get(key))[:400],
                                                                  str(nb.get(key))[:400]))
    masked = sum(1 for a in before if normalised(a) is not a)
    print("%d answers compared (%d with masked fields: %s; after the merge: ETag, %s), %d differ"
          % (len(before), masked, "; ".join("%s: %s" % (k, ", ".join(v) or "none")
                                            for k, v in MASKS.items()),
             ", ".join(PHASE2_JSON_MASKS), differ))
    return 1 if differ else 0


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("record")
    r.add_argument("--vsmd", required=True)
    r.add_argument("--models", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--budget", default="1GiB")
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    args = parser.parse_args()
    if args.command == "record":
        record(args)
        return 0
    return compare(args)


if __name__ == "__main__":
    sys.exit(main())
