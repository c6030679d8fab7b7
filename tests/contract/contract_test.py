#!/usr/bin/python3
"""The API contract against the real daemon (ctest contract.live): every route of
proto/openapi.yaml is asked for each status it documents that a single daemon on loopback can
be made to answer, and every answer is recorded; check_exchanges.js (Ajv, JSON Schema 2020-12)
then validates each one against the contract (status, media type, body schema, headers, the
event stream's events) and fails when a documented (method, path, status) was not exercised and
is not in coverage-exclusions.txt.

Two vsmd processes on 127.0.0.1:0 (tests/integration/harness.py):
  main    a token, limits.body_bytes 4KiB, one job thread, one event subscriber; its data root
          holds PRISM (relief texture) and Jacksboro (no texture) imported by `vsm import` at
          65 x 65, a copy of Jacksboro whose writer lock this test holds (so vsmd serves it
          read-only: 409 for writes into it), an OPC below a subdirectory (opened over HTTP),
          the Jacksboro raster (imported over HTTP) and a VRT that scales PRISM up 40 x 40 (an
          import that runs for minutes: it keeps the single job thread busy while the test fills
          the job queue, and is then cancelled).
  tiny    a 1 MiB memory budget and Jacksboro as one 513 x 513 patch stored cropped, whose
          3 MB of positions can never fit: the routes that must hold patch data answer 503.

No verdict depends on timing: waits poll a state (a job final, a job running) with a generous
bound that only turns a hang into a failure. Every request goes to 127.0.0.1, one at a time
(about 200 in all, job polls included; polls back off to one every 0.5 s).

    contract_test.py --vsmd build/server/vsmd --vsm build/server/cli/vsm --data ../shared/data
        --contract proto/openapi.yaml --tools build/contract-tools --work build/.../contract
    (--keep leaves the exchanges and the daemons' directories in --work.)"""

import argparse
import base64
import fcntl
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import harness  # noqa: E402
from harness import Daemon  # noqa: E402

TOKEN = "contract-token-0123456789"
AUTH = {"Authorization": "Bearer " + TOKEN}
JSON = {"Content-Type": "application/json"}
BODY_LIMIT = 4096
WAIT = 600  # seconds: the bound of every wait for a state (a hang guard, not a verdict)


class Recorder:
    """Sends requests to a daemon and keeps every exchange for check_exchanges.js."""

    def __init__(self):
        self.exchanges = []

    def record(self, step, method, target, status, headers, body, events=None):
        path, _, query = target.partition("?")
        exchange = {"step": step, "method": method, "path": path, "query": query,
                    "status": status, "headers": headers,
                    "body_b64": base64.b64encode(body).decode("ascii")}
        if events is not None:
            exchange["events"] = events
        self.exchanges.append(exchange)

    def call(self, daemon, step, method, target, expect, body=None, headers=None):
        """One request on a fresh connection; asserts the status the step means to produce (the
        schema verdict is check_exchanges.js's). Returns (headers, body bytes)."""
        conn = daemon.connection(timeout=120)
        try:
            if isinstance(body, (dict, list)):
                body = json.dumps(body).encode()
                headers = {**JSON, **(headers or {})}
            conn.request(method, target, body=body, headers=headers or {})
            response = conn.getresponse()
            data = response.read()
            hdrs = {}
            for name, value in response.getheaders():
                name = name.lower()
                hdrs[name] = hdrs[name] + ", " + value if name in hdrs else value
            status = response.status
        finally:
            conn.close()
        self.record(step, method, target, status, hdrs, data)
        if status != expect:
            raise AssertionError("%s: %s %s answered %d, not %d: %r" %
                                 (step, method, target, status, expect, data[:300]))
        return hdrs, data

    def raw(self, daemon, step, method, target, request, expect):
        """A hand-made request on a raw socket (limits the client library would not break), read
        until the daemon closes the connection."""
        with daemon.socket(timeout=60) as sock:
            sock.sendall(request)
            data = harness.read_until_closed(sock)
        head, _, body = data.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split(" ")[1])
        hdrs = {}
        for line in lines[1:]:
            name, _, value = line.partition(":")
            hdrs[name.strip().lower()] = value.strip()
        if "content-length" in hdrs:
            body = body[:int(hdrs["content-length"])]
        self.record(step, method, target, status, hdrs, body)
        if status != expect:
            raise AssertionError("%s: %s %s answered %d, not %d: %r" %
                                 (step, method, target, status, expect, body[:300]))
        return hdrs, body


class EventStream:
    """A GET /v1/events subscriber on its own thread, read until the daemon ends the stream."""

    def __init__(self, daemon):
        self.sock = daemon.socket(timeout=WAIT)
        self.sock.sendall(b"GET /v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        self.data = b""  # what arrived so far; only the reading thread appends
        self.thread = threading.Thread(target=self.read, daemon=True)
        self.thread.start()

    def read(self):
        try:
            while len(self.data) < 64 << 20:
                chunk = self.sock.recv(65536)
                if not chunk:
                    break
                self.data += chunk
        except OSError:
            pass
        finally:
            self.sock.close()

    def finish(self, recorder):
        """After the daemon stopped: the exchange with its parsed events, recorded."""
        self.thread.join(timeout=60)
        if self.thread.is_alive():
            raise AssertionError("the event stream did not end with the daemon")
        head, _, body = self.data.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        hdrs = {}
        for line in lines[1:]:
            name, _, value = line.partition(":")
            hdrs[name.strip().lower()] = value.strip()
        events = []
        for block in body.decode("utf-8").split("\n\n"):
            event = {"id": None, "event": "message", "data": []}
            for line in block.split("\n"):
                if not line or line.startswith(":"):
                    continue
                field, _, value = line.partition(":")
                value = value[1:] if value.startswith(" ") else value
                if field == "data":
                    event["data"].append(value)
                elif field in ("id", "event"):
                    event[field] = value
            if event["data"]:
                event["data"] = json.loads("\n".join(event["data"]))
                events.append(event)
        recorder.record("the event stream of the whole run", "GET", "/v1/events",
                        int(lines[0].split(" ")[1]), hdrs, b"", events=events)
        return events


def import_opc(dem, out, size, *options):
    harness.import_dem(os.path.join(ARGS.data, dem), out, size, *options)


FINAL = ("succeeded", "failed", "cancelled")


def wait_job(recorder, daemon, job_id, states=FINAL):
    """Polls GET /v1/jobs/{j} until the job's state is one of `states` (or final); the job."""
    deadline = time.monotonic() + WAIT
    delay = 0.02
    while True:
        conn = daemon.connection(timeout=60)
        try:
            conn.request("GET", "/v1/jobs/" + job_id)
            response = conn.getresponse()
            job = json.loads(response.read())
            assert response.status == 200, job
        finally:
            conn.close()
        if job["state"] in states or job["state"] in FINAL:
            # The last answer is recorded like every other (one per wait, not one per poll).
            recorder.call(daemon, "job status", "GET", "/v1/jobs/" + job_id, 200)
            return job
        if time.monotonic() > deadline:
            raise AssertionError("job %s not %s within %d s: %r" % (job_id, states, WAIT, job))
        time.sleep(delay)
        delay = min(0.5, delay * 1.5)


def oversize_header(target):
    return (b"GET " + target.encode() + b" HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " +
            b"a" * (20 * 1024) + b"\r\n\r\n")


def oversize_body(target):
    return (b"POST " + target.encode() + b" HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer " +
            TOKEN.encode() + b"\r\nContent-Type: application/json\r\nContent-Length: " +
            str(2 * BODY_LIMIT).encode() + b"\r\n\r\n")


def exercise_main(r, d):
    """Every route of the main daemon, each documented status that one daemon can answer."""
    def etag_of(target):
        hdrs, _ = r.call(d, "for an ETag", "GET", target, 200)
        return {"If-None-Match": hdrs["etag"]}

    # System routes, and the header limit where it is an operation's only client error.
    for target in ("/healthz", "/readyz", "/metrics", "/v1/stats", "/v1/models", "/v1/jobs"):
        r.call(d, "system read", "GET", target, 200)
        r.raw(d, "header over limits.header_bytes", "GET", target, oversize_header(target), 431)
    r.raw(d, "header over limits.header_bytes", "GET", "/v1/events",
          oversize_header("/v1/events"), 431)
    r.raw(d, "a second subscriber over limits.event_subscribers", "GET", "/v1/events",
          b"GET /v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n", 503)

    # Model reads.
    m = "/v1/models/prism"
    r.call(d, "summary", "GET", m, 200)
    r.call(d, "summary revalidated", "GET", m, 304, headers=etag_of(m))
    r.call(d, "summary of a malformed revision", "GET", m + "?rev=first", 400)
    r.call(d, "summary of no model", "GET", "/v1/models/nope", 404)
    r.call(d, "a read-only model", "GET", "/v1/models/locked", 200)

    r.call(d, "hierarchy", "GET", m + "/hierarchy", 200)
    r.call(d, "hierarchy cut", "GET", m + "/hierarchy?root=0_0_0&depth=1", 200)
    r.call(d, "hierarchy revalidated", "GET", m + "/hierarchy?depth=1", 304,
           headers=etag_of(m + "/hierarchy?depth=1"))
    r.call(d, "hierarchy of a bad key", "GET", m + "/hierarchy?root=one", 400)
    r.call(d, "hierarchy of no model", "GET", "/v1/models/nope/hierarchy", 404)

    _, body = r.call(d, "leaf lookup", "GET", m + "/hierarchy", 200)
    node = json.loads(body)["root"]
    while node.get("children"):
        node = node["children"][0]
    leaf = node["key"]
    p = m + "/patches/" + leaf
    r.call(d, "patch", "GET", p, 200)
    r.call(d, "root patch", "GET", m + "/patches/0_0_0", 200)
    r.call(d, "patch revalidated", "GET", p, 304, headers=etag_of(p))
    r.call(d, "patch of a bad key", "GET", m + "/patches/leaf", 400)
    r.call(d, "patch not in the model", "GET", m + "/patches/12_0_0", 404)

    for route in ("positions", "coordinates", "texture"):
        r.call(d, route, "GET", p + "/" + route, 200)
        r.call(d, route + " revalidated", "GET", p + "/" + route, 304,
               headers=etag_of(p + "/" + route))
        r.call(d, route + " of a bad key", "GET", m + "/patches/leaf/" + route, 400)
        r.call(d, route + " of no patch", "GET", m + "/patches/12_0_0/" + route, 404)
    for route in ("coordinates", "texture"):
        r.call(d, route + " of an untextured patch", "GET",
               "/v1/models/jacksboro/patches/0_0_0/" + route, 404)
    _, body = r.call(d, "texture layer lookup", "GET", p, 200)
    layer = json.loads(body)["texture"]["layer"]
    r.call(d, "texture layer", "GET", p + "/texture/" + layer, 200)
    r.call(d, "texture layer revalidated", "GET", p + "/texture/" + layer, 304,
           headers=etag_of(p + "/texture/" + layer))
    r.call(d, "texture layer of a bad key", "GET", m + "/patches/leaf/texture/" + layer, 400)
    r.call(d, "texture of another layer", "GET", p + "/texture/Normal", 404)

    _, body = r.call(d, "bounds", "GET", m, 200)
    summary = json.loads(body)
    lo, hi = summary["bounds"]["min"], summary["bounds"]["max"]
    mid = [(a + b) / 2 for a, b in zip(lo, hi)]
    box = ",".join("%.3f" % v for v in lo + mid)
    lod = m + "/lod?box=" + box + "&resolution=5000"
    r.call(d, "lod, box form", "GET", lod, 200)
    r.call(d, "lod revalidated", "GET", lod, 304, headers=etag_of(lod))
    eye = [c * 1.3 for c in mid]
    camera = (m + "/lod?eye=%s&dir=%s&up=0,0,1&fov=60&height=600&width=800&sse=16" %
              (",".join("%.1f" % v for v in eye), ",".join("%.4f" % -v for v in mid)))
    r.call(d, "lod, camera form", "GET", camera, 200)
    r.call(d, "lod without a form", "GET", m + "/lod", 400)
    r.call(d, "lod of no model", "GET", "/v1/models/nope/lod?box=" + box + "&resolution=1", 404)

    t = m + "/3dtiles/tileset.json"
    r.call(d, "tileset", "GET", t, 200)
    r.call(d, "tileset gzipped", "GET", t + "?compress=none", 200,
           headers={"Accept-Encoding": "gzip"})
    r.call(d, "tileset revalidated", "GET", t, 304, headers=etag_of(t))
    r.call(d, "tileset, bad compress", "GET", t + "?compress=zip", 400)
    r.call(d, "tileset of no model", "GET", "/v1/models/nope/3dtiles/tileset.json", 404)
    g = m + "/3dtiles/%s.glb" % leaf
    r.call(d, "glb", "GET", g + "?v=1", 200)
    r.call(d, "glb uncompressed", "GET", g + "?compress=none", 200)
    r.call(d, "glb revalidated", "GET", g, 304, headers=etag_of(g))
    r.call(d, "glb of a bad key", "GET", m + "/3dtiles/leaf.glb", 400)
    r.call(d, "glb of no patch", "GET", m + "/3dtiles/12_0_0.glb", 404)

    lj = m + "/terrain/layer.json"
    _, layer = r.call(d, "terrain layer", "GET", lj, 200)
    layer_version = json.loads(layer)["model_version"]
    r.call(d, "terrain layer revalidated", "GET", lj, 304, headers=etag_of(lj))
    r.call(d, "terrain layer, bad revision", "GET", lj + "?rev=0", 400)
    r.call(d, "terrain layer of no model", "GET", "/v1/models/nope/terrain/layer.json", 404)
    tile = m + "/terrain/0/0/0.terrain"
    accept = {"Accept": "application/vnd.quantized-mesh;extensions=octvertexnormals-metadata",
              "Accept-Encoding": "gzip"}
    r.call(d, "terrain tile", "GET", tile + "?v=%d" % layer_version, 200, headers=accept)
    r.call(d, "terrain tile of a version not served", "GET", tile + "?v=999", 404)
    hdrs, _ = r.call(d, "terrain tile (for an ETag)", "GET", tile, 200)
    r.call(d, "terrain tile revalidated", "GET", tile, 304, headers={"If-None-Match": hdrs["etag"]})
    r.call(d, "terrain tile outside the scheme", "GET", m + "/terrain/25/0/0.terrain", 400)
    r.call(d, "terrain tile of no model", "GET", "/v1/models/nope/terrain/0/0/0.terrain", 404)

    # MapLibre's terrain-RGB (issue 29): a level-10 tile over the middle of Jacksboro.
    rj = m + "/terrain-rgb/tiles.json"
    r.call(d, "terrain-rgb tilejson", "GET", rj + "?encoding=mapbox", 200)
    r.call(d, "terrain-rgb tilejson revalidated", "GET", rj, 304, headers=etag_of(rj))
    r.call(d, "terrain-rgb tilejson, bad no-data", "GET", rj + "?nodata=x", 400)
    r.call(d, "terrain-rgb tilejson of no model", "GET", "/v1/models/nope/terrain-rgb/tiles.json",
           404)
    rgb = m + "/terrain-rgb/10/272/401.png"
    r.call(d, "terrain-rgb tile", "GET", rgb + "?nodata=-1", 200)
    r.call(d, "terrain-rgb tile revalidated", "GET", rgb, 304, headers=etag_of(rgb))
    r.call(d, "terrain-rgb tile, bad encoding", "GET", rgb + "?encoding=rgb", 400)
    r.call(d, "terrain-rgb tile off the model", "GET", m + "/terrain-rgb/10/0/0.png", 404)

    # Heights for GIS clients (issue 29).
    points = "36.3,-84.2|36.31,-84.21"
    r.call(d, "elevation", "GET", m + "/elevation?locations=" + points + "&samples=3", 200)
    r.call(d, "elevation outside the world", "GET", m + "/elevation?locations=95,10", 400)
    r.call(d, "elevation of no model", "GET", "/v1/models/nope/elevation?locations=1,1", 404)
    geojson = {"type": "MultiPoint", "coordinates": [[-84.2, 36.3], [-84.21, 36.31]]}
    r.call(d, "elevation posted", "POST", m + "/elevation", 200, body=geojson, headers=AUTH)
    r.call(d, "elevation posted without the token", "POST", m + "/elevation", 401, body=geojson)
    r.call(d, "elevation posted, no points", "POST", m + "/elevation", 400, body={"x": 1},
           headers=AUTH)
    r.call(d, "elevation posted to no model", "POST", "/v1/models/nope/elevation", 404,
           body=geojson, headers=AUTH)
    r.call(d, "profile", "GET", m + "/profile?line=" + points, 200)
    r.call(d, "profile of one point", "GET", m + "/profile?line=36.3,-84.2", 400)
    r.call(d, "profile of no model", "GET", "/v1/models/nope/profile?line=" + points, 404)
    cov = m + "/coverage?bbox=-84.3,36.2,-84.2,36.3&width=64&height=64"
    r.call(d, "coverage", "GET", cov, 200)
    r.call(d, "coverage revalidated", "GET", cov, 304, headers=etag_of(cov))
    r.call(d, "coverage, unknown CRS", "GET", cov + "&crs=EPSG:32616", 400)
    r.call(d, "coverage of no model", "GET", "/v1/models/nope/coverage", 404)
    for target in ("/ogcapi", "/ogcapi/conformance", "/ogcapi/collections",
                   "/ogcapi/collections/prism/coverage/rangetype"):
        r.call(d, "OGC API document", "GET", target, 200)
        r.raw(d, "header over limits.header_bytes", "GET", target, oversize_header(target), 431)
    r.call(d, "OGC API collection", "GET", "/ogcapi/collections/prism", 200)
    r.call(d, "OGC API collection of no model", "GET", "/ogcapi/collections/nope", 404)
    ogc = "/ogcapi/collections/prism/coverage"
    r.call(d, "OGC API coverage", "GET",
           ogc + "?subset=Lon(-84.3:-84.2),Lat(36.2:36.3)&scaleSize=Lon(32),Lat(32)", 200)
    r.call(d, "OGC API coverage, inverted", "GET", ogc + "?subset=Lon(-84.2:-84.3)", 400)
    r.call(d, "OGC API coverage of no model", "GET", "/ogcapi/collections/nope/coverage", 404)
    r.call(d, "OGC API domain set", "GET", ogc + "/domainset", 200)
    r.call(d, "OGC API domain set of no model", "GET",
           "/ogcapi/collections/nope/coverage/domainset", 404)

    # Rays (issue 29): down through PRISM's surface from 10 km above 36.3 N, 84.2 W (ECEF).
    def ecef(lon, lat, h):
        lon, lat = math.radians(lon), math.radians(lat)
        e2 = 6.69437999014e-3
        n = 6378137.0 / math.sqrt(1 - e2 * math.sin(lat) ** 2)
        return [(n + h) * math.cos(lat) * math.cos(lon), (n + h) * math.cos(lat) * math.sin(lon),
                (n * (1 - e2) + h) * math.sin(lat)]
    ray = {"origin": ecef(-84.2, 36.3, 10000), "direction": [-v for v in ecef(-84.2, 36.3, 0)]}
    query = "origin=%s&direction=%s" % (",".join("%.3f" % v for v in ray["origin"]),
                                       ",".join("%.3f" % v for v in ray["direction"]))
    _, body = r.call(d, "ray", "GET", m + "/ray?" + query + "&max_distance=20000", 200)
    assert json.loads(body)["results"][0]["hit"] is not None, body
    r.call(d, "ray, zero direction", "GET", m + "/ray?origin=1,2,3&direction=0,0,0", 400)
    r.call(d, "ray of no model", "GET", "/v1/models/nope/ray?" + query, 404)
    rays = {"rays": [ray, {**ray, "max_distance": 10}]}
    r.call(d, "rays posted", "POST", m + "/ray", 200, body=rays, headers=AUTH)
    r.call(d, "rays posted without the token", "POST", m + "/ray", 401, body=rays)
    r.call(d, "rays posted, unknown member", "POST", m + "/ray", 400,
           body={"rays": [{**ray, "colour": 1}]}, headers=AUTH)
    r.call(d, "rays posted to no model", "POST", "/v1/models/nope/ray", 404, body=rays,
           headers=AUTH)

    r.call(d, "revisions", "GET", m + "/revisions", 200)
    r.call(d, "revisions of no model", "GET", "/v1/models/nope/revisions", 404)

    # Opening and closing models.
    opened = {"id": "extra", "source": {"path": "extra/jack"}}
    r.call(d, "write without the token", "POST", "/v1/models", 401, body=opened)
    r.raw(d, "body over limits.body_bytes", "POST", "/v1/models", oversize_body("/v1/models"), 413)
    r.call(d, "open a directory", "POST", "/v1/models", 201, body=opened, headers=AUTH)
    r.call(d, "open it again", "POST", "/v1/models", 409, body=opened, headers=AUTH)
    r.call(d, "open with a typo", "POST", "/v1/models", 400,
           body={"id": "x", "source": {"paht": "extra/jack"}}, headers=AUTH)
    r.call(d, "open no directory", "POST", "/v1/models", 404,
           body={"id": "x", "source": {"path": "extra/none"}}, headers=AUTH)
    r.call(d, "close without the token", "DELETE", "/v1/models/extra", 401)
    r.call(d, "close", "DELETE", "/v1/models/extra", 204, headers=AUTH)
    r.call(d, "close again", "DELETE", "/v1/models/extra", 404, headers=AUTH)
    _, body = r.call(d, "import a raster", "POST", "/v1/models", 202, headers=AUTH,
                     body={"id": "imported", "source": {"import": "rasters/jack.tif",
                                                        "patch_size": 129, "texture": "none"}})
    job = wait_job(r, d, json.loads(body)["id"])
    assert job["state"] == "succeeded", job

    # Merge jobs and the diff of the two revisions a merge makes.
    merge = {"type": "merge", "target": "prism", "source": "jacksboro"}
    r.call(d, "merge without the token", "POST", "/v1/jobs", 401, body=merge)
    r.raw(d, "body over limits.body_bytes", "POST", "/v1/jobs", oversize_body("/v1/jobs"), 413)
    r.call(d, "merge of a wrong type", "POST", "/v1/jobs", 400, headers=AUTH,
           body={**merge, "type": "import"})
    r.call(d, "merge into no model", "POST", "/v1/jobs", 404, headers=AUTH,
           body={**merge, "target": "nope"})
    r.call(d, "merge into a model another process writes", "POST", "/v1/jobs", 409,
           headers=AUTH, body={**merge, "target": "locked"})
    _, body = r.call(d, "merge", "POST", "/v1/jobs", 202, body=merge, headers=AUTH)
    merged = json.loads(body)["id"]
    job = wait_job(r, d, merged)
    assert job["state"] == "succeeded", job
    r.call(d, "job", "GET", "/v1/jobs/" + merged, 200)
    r.call(d, "no job", "GET", "/v1/jobs/0000000000000000", 404)
    r.call(d, "jobs after the merge", "GET", "/v1/jobs", 200)
    r.call(d, "revisions after the merge", "GET", m + "/revisions", 200)
    r.call(d, "summary of revision 1", "GET", m + "?rev=1", 200)

    r.call(d, "diff", "GET", m + "/diff?from=1&to=2", 200)
    r.call(d, "diff without from", "GET", m + "/diff?to=2", 400)
    r.call(d, "diff to no kept revision", "GET", m + "/diff?from=1&to=99", 404)
    r.call(d, "diff map", "GET", m + "/diff.png?from=1&to=2&size=256", 200)
    r.call(d, "diff map of size 0", "GET", m + "/diff.png?from=1&to=2&size=0", 400)
    r.call(d, "diff map of no model", "GET", "/v1/models/nope/diff.png?from=1&to=2", 404)

    rs = m + "/revisions/1/restore"
    r.call(d, "restore without the token", "POST", rs, 401)
    r.call(d, "restore a malformed revision", "POST", m + "/revisions/one/restore", 400,
           headers=AUTH)
    r.call(d, "restore no kept revision", "POST", m + "/revisions/99/restore", 404, headers=AUTH)
    r.call(d, "restore in a model another process writes", "POST",
           "/v1/models/locked/revisions/1/restore", 409, headers=AUTH)
    _, body = r.call(d, "restore", "POST", rs, 202, headers=AUTH)
    job = wait_job(r, d, json.loads(body)["id"])
    assert job["state"] == "succeeded", job

    # A full job queue: one long import keeps the single job thread busy, merges fill the
    # queue up to its bound (16 active jobs); then writes that would queue a job answer 503,
    # closing a model a queued job holds answers 409, queued jobs are cancelled at once (200)
    # and the running import on request (202).
    _, body = r.call(d, "a long import", "POST", "/v1/models", 202, headers=AUTH,
                     body={"id": "slow", "source": {"import": "rasters/big.vrt"}})
    slow = json.loads(body)["id"]
    job = wait_job(r, d, slow, states=("running",))
    assert job["state"] == "running", job
    queued = []
    for _ in range(32):
        conn = d.connection(timeout=60)
        try:
            conn.request("POST", "/v1/jobs", body=json.dumps(merge), headers={**JSON, **AUTH})
            response = conn.getresponse()
            status, data = response.status, response.read()
        finally:
            conn.close()
        if status != 202:
            assert status == 503, (status, data)
            break
        queued.append(json.loads(data)["id"])
    else:
        raise AssertionError("32 merges queued without a 503")
    r.call(d, "merge into a full queue", "POST", "/v1/jobs", 503, body=merge, headers=AUTH)
    r.call(d, "import into a full queue", "POST", "/v1/models", 503, headers=AUTH,
           body={"id": "later", "source": {"import": "rasters/jack.tif"}})
    r.call(d, "restore into a full queue", "POST", rs, 503, headers=AUTH)
    r.call(d, "close a model queued jobs use", "DELETE", m, 409, headers=AUTH)
    r.call(d, "cancel without the token", "DELETE", "/v1/jobs/" + queued[0], 401)
    for job_id in queued:
        r.call(d, "cancel a queued job", "DELETE", "/v1/jobs/" + job_id, 200, headers=AUTH)
    r.call(d, "cancel the running import", "DELETE", "/v1/jobs/" + slow, 202, headers=AUTH)
    job = wait_job(r, d, slow)
    assert job["state"] == "cancelled", job
    r.call(d, "cancel a finished job", "DELETE", "/v1/jobs/" + slow, 409, headers=AUTH)
    r.call(d, "cancel no job", "DELETE", "/v1/jobs/0000000000000000", 404, headers=AUTH)
    r.call(d, "jobs at the end", "GET", "/v1/jobs", 200)
    r.call(d, "stats at the end", "GET", "/v1/stats", 200)
    r.call(d, "models at the end", "GET", "/v1/models", 200)


def exercise_tiny(r, d):
    """The routes that need patch data in memory, for a patch larger than the whole budget."""
    m = "/v1/models/jack513"
    _, body = r.call(d, "a patch stored cropped", "GET", m + "/patches/0_0_0", 200)
    patch = json.loads(body)
    assert patch["stored"] != {"x0": 0, "y0": 0, "x1": 513, "y1": 513}, patch["stored"]
    r.call(d, "positions over the budget", "GET", m + "/patches/0_0_0/positions", 503)
    r.call(d, "glb over the budget", "GET", m + "/3dtiles/0_0_0.glb", 503)
    r.call(d, "terrain layer over the budget", "GET", m + "/terrain/layer.json", 503)
    r.call(d, "terrain tile over the budget", "GET", m + "/terrain/0/0/0.terrain", 503)
    r.call(d, "terrain-rgb tilejson over the budget", "GET", m + "/terrain-rgb/tiles.json", 503)
    r.call(d, "terrain-rgb tile over the budget", "GET", m + "/terrain-rgb/0/0/0.png", 503)
    # A ray into the patch must read it.
    centre = [(a + b) / 2 for a, b in zip(patch["box"]["min"], patch["box"]["max"])]
    ray = {"origin": [c * 1.002 for c in centre], "direction": [-c for c in centre]}
    query = "origin=%s&direction=%s" % (",".join("%.3f" % v for v in ray["origin"]),
                                       ",".join("%.3f" % v for v in ray["direction"]))
    r.call(d, "ray over the budget", "GET", m + "/ray?" + query, 503)
    r.call(d, "rays posted over the budget", "POST", m + "/ray", 503, body={"rays": [ray]},
           headers=AUTH)
    # This daemon runs no diffs at all (limits.diffs=0): every one is over the bound.
    r.call(d, "diff over limits.diffs", "GET", m + "/diff?from=1&to=2", 503)
    r.call(d, "diff map over limits.diffs", "GET", m + "/diff.png?from=1&to=2&size=64", 503)
    r.call(d, "stats after", "GET", "/v1/stats", 200)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    for name in ("--vsmd", "--vsm", "--data", "--contract", "--tools", "--work"):
        parser.add_argument(name, required=True)
    parser.add_argument("--keep", action="store_true")
    ARGS = parser.parse_args()
    harness.configure(ARGS)
    checker = os.path.join(HERE, "check_exchanges.js")
    if not os.path.isfile(os.path.join(ARGS.tools, "node_modules", "ajv", "package.json")):
        print("contract_test: no Ajv in %s (run install-contract-tools.sh)" % ARGS.tools)
        return 1

    shutil.rmtree(ARGS.work, ignore_errors=True)
    os.makedirs(ARGS.work)
    main_root = os.path.join(ARGS.work, "main")
    tiny_root = os.path.join(ARGS.work, "tiny")
    os.makedirs(main_root)
    os.makedirs(tiny_root)

    import_opc("PRISMelevation.tif", os.path.join(main_root, "prism"), 65)
    import_opc("jacksboro_fault_dem.tif", os.path.join(main_root, "jacksboro"), 65,
               "--texture", "none")
    shutil.copytree(os.path.join(main_root, "jacksboro"), os.path.join(main_root, "locked"))
    os.makedirs(os.path.join(main_root, "extra"))
    shutil.copytree(os.path.join(main_root, "jacksboro"), os.path.join(main_root, "extra", "jack"))
    rasters = os.path.join(main_root, "rasters")
    os.makedirs(rasters)
    shutil.copy(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"),
                os.path.join(rasters, "jack.tif"))
    shutil.copy(os.path.join(ARGS.data, "PRISMelevation.tif"), os.path.join(rasters, "prism.tif"))
    subprocess.run(["gdal_translate", "-q", "-of", "VRT", "-outsize", "4000%", "4000%",
                    os.path.join(rasters, "prism.tif"), os.path.join(rasters, "big.vrt")],
                   check=True, timeout=60)
    import_opc("jacksboro_fault_dem.tif", os.path.join(tiny_root, "jack513"), 513)

    # The writer lock of `locked`, held by this process for the whole run (vsm's protocol:
    # flock on <opc>/.vsm-writer.lock, the holder's name inside).
    lock = open(os.path.join(main_root, "locked", ".vsm-writer.lock"), "a+")
    fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    lock.truncate(0)
    lock.write("contract_test pid %d\n" % os.getpid())
    lock.flush()

    recorder = Recorder()
    failed = None
    main_daemon = tiny_daemon = stream = None
    try:
        main_daemon = Daemon("--token", TOKEN, "--memory-budget", "256MiB",
                             "--set", "limits.body_bytes=%d" % BODY_LIMIT,
                             "--set", "limits.event_subscribers=1", "--set", "threads.jobs=1",
                             root=main_root)
        stream = EventStream(main_daemon)
        # The subscription counts once the daemon answered it: wait for its header.
        deadline = time.monotonic() + 60
        while b"\r\n\r\n" not in stream.data and stream.thread.is_alive():
            conn = main_daemon.connection()
            conn.request("GET", "/v1/stats")
            conn.getresponse().read()
            conn.close()
            if time.monotonic() > deadline:
                break
            time.sleep(0.05)
        exercise_main(recorder, main_daemon)
        tiny_daemon = Daemon("--memory-budget", "1MiB", "--set", "limits.diffs=0", root=tiny_root)
        exercise_tiny(recorder, tiny_daemon)
    except AssertionError as e:
        failed = str(e)
    finally:
        for daemon in (main_daemon, tiny_daemon):
            if daemon is not None:
                code = daemon.stop()
                if code != 0 and failed is None:
                    failed = "vsmd exited %d:\n%s" % (code, daemon.log())
        if stream is not None and main_daemon is not None:
            try:
                events = stream.finish(recorder)
                names = sorted({e["event"] for e in events})
                print("contract_test: %d events (%s) on the stream" %
                      (len(events), ", ".join(names)))
                for want in ("job", "job_end", "published"):
                    if want not in names and failed is None:
                        failed = "the event stream had no %r event" % want
            except AssertionError as e:
                failed = failed or str(e)
        lock.close()

    path = os.path.join(ARGS.work, "exchanges.json")
    with open(path, "w") as f:
        json.dump(recorder.exchanges, f, indent=1)
    print("contract_test: %d exchanges recorded in %s" % (len(recorder.exchanges), path))
    checked = subprocess.run(["node", checker, "--tools", ARGS.tools, "--contract", ARGS.contract,
                              "--exchanges", path,
                              "--exclusions", os.path.join(HERE, "coverage-exclusions.txt")],
                             timeout=300)
    if failed is not None:
        print("contract_test: FAILED while driving the daemon: " + failed)
        if main_daemon is not None:
            print(main_daemon.log()[-4000:])
    ok = failed is None and checked.returncode == 0
    if ok and not ARGS.keep:
        for root in (main_root, tiny_root):
            shutil.rmtree(root, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
