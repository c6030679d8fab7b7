#!/usr/bin/env python3
"""A client of vsmd's HTTP API using only the Python standard library.

    vsm_client.py [--url URL] [--token TOKEN] models
    vsm_client.py [--url URL] walk MODEL [--depth N]
    vsm_client.py [--url URL] patch MODEL [KEY] [--out FILE]
    vsm_client.py [--url URL] --token TOKEN merge TARGET SOURCE [--register]
    vsm_client.py [--url URL] [--token TOKEN] tour [MODEL [DETAIL]]

URL defaults to $VSM_URL or http://127.0.0.1:8080, TOKEN to $VSM_TOKEN. `patch` without a KEY
takes the middle leaf of the tree; `tour` does models, walk, patch and (with DETAIL) merge.

Import it to use the Client class and decode_aara() in your own code; the API is described in
proto/openapi.yaml.
"""

import argparse
import array
import json
import math
import os
import sys
import time
import urllib.error
import urllib.parse
import urllib.request

FINAL_STATES = ("succeeded", "failed", "cancelled")


class ApiError(Exception):
    """A JSON error answer: {"error": {"code", "message"}} with its HTTP status."""

    def __init__(self, status, code, message):
        super().__init__("HTTP %d %s: %s" % (status, code, message))
        self.status, self.code, self.message = status, code, message


class Response:
    def __init__(self, status, headers, body):
        self.status, self.headers, self.body = status, headers, body

    def json(self):
        return json.loads(self.body)


class Client:
    """One vsmd. Each call is one HTTP request (urllib keeps no connection open between them)."""

    def __init__(self, url="http://127.0.0.1:8080", token=None, timeout=60):
        self.url = url.rstrip("/")
        self.token = token
        self.timeout = timeout
        # No proxy from the environment: the daemon is addressed directly (often on loopback).
        self.opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))

    def request(self, method, path, body=None, headers=None, ok=(200,)):
        """Sends one request; returns a Response whose status is in `ok`, raises ApiError else."""
        headers = dict(headers or {})
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
        if self.token and method not in ("GET", "HEAD"):
            headers["Authorization"] = "Bearer " + self.token
        url = self.url + path
        # In a cluster, a node that does not write the model answers a write with 307 naming the
        # node that does: the same request, body and all, goes there (urllib follows 307 only for
        # GET). A few hops at most.
        for _ in range(4):
            req = urllib.request.Request(url, data=data, method=method, headers=headers)
            try:
                with self.opener.open(req, timeout=self.timeout) as r:
                    response = Response(r.status, r.headers, r.read())
            except urllib.error.HTTPError as e:  # 3xx (304, 307), 4xx and 5xx land here
                response = Response(e.code, e.headers, e.read())
            location = response.headers.get("Location") if response.headers else None
            if response.status not in (307, 308) or not location or response.status in ok:
                break
            url = urllib.parse.urljoin(url, location)
        if response.status not in ok:
            try:
                error = response.json()["error"]
                code, message = error["code"], error["message"]
            except (ValueError, KeyError, TypeError):
                code, message = "http_%d" % response.status, response.body[:200].decode(errors="replace")
            raise ApiError(response.status, code, message)
        return response

    def get_json(self, path):
        return self.request("GET", path).json()

    # ---- reads ---------------------------------------------------------------------------

    def models(self):
        return self.get_json("/v1/models")["models"]

    def model(self, model):
        return self.get_json("/v1/models/" + quote(model))

    def hierarchy(self, model, root=None, depth=None):
        query = {k: v for k, v in (("root", root), ("depth", depth)) if v is not None}
        suffix = "?" + urllib.parse.urlencode(query) if query else ""
        return self.get_json("/v1/models/%s/hierarchy%s" % (quote(model), suffix))

    def patch(self, model, key):
        return self.get_json("/v1/models/%s/patches/%s" % (quote(model), quote(key)))

    def positions(self, model, key, etag=None):
        """(Grid, ETag) of a patch's positions, or (None, ETag) when `etag` is still current."""
        headers = {"If-None-Match": etag} if etag else {}
        r = self.request("GET", "/v1/models/%s/patches/%s/positions" % (quote(model), quote(key)),
                         headers=headers, ok=(200, 304))
        if r.status == 304:
            return None, r.headers["ETag"]
        grid = decode_aara(r.body)
        grid.local2global = [float(v) for v in r.headers["X-VSM-Local2Global"].split(",")]
        return grid, r.headers["ETag"]

    def revisions(self, model):
        """The kept revisions of a model, oldest first (the latest has "latest": true)."""
        return self.get_json("/v1/models/%s/revisions" % quote(model))["revisions"]

    def restore(self, model, revision):
        """Submits a job publishing revision `revision`'s content as the model's next revision."""
        return self.request("POST", "/v1/models/%s/revisions/%d/restore" % (quote(model), revision),
                            ok=(202,)).json()

    def diff(self, model, from_revision, to_revision):
        """What changed between two kept revisions: the displacement (metres, along the surface
        normal, + = outward) per changed patch and in "totals" (proto/openapi.yaml, Diff)."""
        query = urllib.parse.urlencode({"from": int(from_revision), "to": int(to_revision)})
        return self.get_json("/v1/models/%s/diff?%s" % (quote(model), query))

    def diff_png(self, model, from_revision, to_revision, size=1024):
        """(PNG bytes, R): the diff seen from above, blue -R .. white 0 .. red +R metres."""
        query = urllib.parse.urlencode({"from": int(from_revision), "to": int(to_revision),
                                        "size": int(size)})
        r = self.request("GET", "/v1/models/%s/diff.png?%s" % (quote(model), query))
        return r.body, float(r.headers["X-VSM-Diff-Range"])

    def lod(self, model, box, resolution):
        query = urllib.parse.urlencode({"box": ",".join(repr(float(v)) for v in box),
                                        "resolution": repr(float(resolution))})
        return self.get_json("/v1/models/%s/lod?%s" % (quote(model), query))

    # ---- jobs ----------------------------------------------------------------------------

    def submit_merge(self, target, source, register=False):
        body = {"type": "merge", "target": target, "source": source, "register": register}
        return self.request("POST", "/v1/jobs", body=body, ok=(202,)).json()

    def job(self, job_id):
        return self.get_json("/v1/jobs/" + quote(job_id))

    def wait(self, job_id, interval=0.1, timeout=3600, on_progress=None, use_events=True):
        """Waits until a job is final; calls on_progress(job) whenever state, stage or progress
        changed. Returns the final job (as GET /v1/jobs/{j} has it).

        Listens to the event stream (GET /v1/events) when it can, and polls every `interval`
        seconds when it cannot (an older daemon, the subscriber limit reached, the stream
        dropped or silent for longer than its heartbeat)."""
        deadline = time.monotonic() + timeout
        last = [None]

        def report(job):
            seen = (job["state"], job["stage"], job["progress"])
            if seen != last[0] and on_progress is not None:
                on_progress(job)
            last[0] = seen

        if use_events:
            try:
                job = self._wait_events(job_id, deadline, report)
                if job is not None:
                    return job
            except (ApiError, OSError, ValueError):
                pass  # no stream (or it broke): poll
        while True:
            job = self.job(job_id)
            report(job)
            if job["state"] in FINAL_STATES:
                return job
            if time.monotonic() > deadline:
                raise TimeoutError("job %s not final after %d s" % (job_id, timeout))
            time.sleep(interval)

    def _wait_events(self, job_id, deadline, report):
        """wait() on the event stream; None when the stream ended before the job did."""
        # Subscribed first, then the job read once: an end between the two is not missed.
        stream = self.events(timeout=max(1.0, min(40.0, deadline - time.monotonic())))
        try:
            next(stream)  # the subscription is live once the stream answered
            job = self.job(job_id)
            report(job)
            if job["state"] in FINAL_STATES:
                return job
            for event in stream:
                data = event["data"]
                if event["event"] == "dropped":
                    return None
                if not isinstance(data, dict) or data.get("job") != job_id:
                    continue
                if event["event"] == "job":
                    job = dict(job, state=data["state"], stage=data["stage"],
                               progress=data["progress"])
                    report(job)
                elif event["event"] == "job_end":
                    job = self.job(job_id)
                    report(job)
                    return job
                if time.monotonic() > deadline:
                    raise TimeoutError("job %s not final" % job_id)
            return None
        finally:
            stream.close()

    def events(self, timeout=40.0):
        """The event stream (GET /v1/events, Server-Sent Events) as a generator of dicts
        {"id": str or None, "event": name, "data": parsed JSON}. It first yields
        {"event": "open", ...} once the daemon answered (from then on nothing is missed), then
        every event. Heartbeats (comments) are skipped but reset the read `timeout`, which should
        exceed the daemon's heartbeat (15 s). Ends when the daemon closes the stream (after an
        event "dropped" when this client read too slowly); raises ApiError when the daemon
        refuses (503 over the subscriber limit), OSError when the connection fails."""
        req = urllib.request.Request(self.url + "/v1/events",
                                     headers={"Accept": "text/event-stream"})
        try:
            r = self.opener.open(req, timeout=timeout)
        except urllib.error.HTTPError as e:
            body = e.read()
            try:
                error = json.loads(body)["error"]
                raise ApiError(e.code, error["code"], error["message"]) from None
            except (ValueError, KeyError, TypeError):
                raise ApiError(e.code, "http_%d" % e.code, body[:200].decode(errors="replace"))
        with r:
            yield {"id": None, "event": "open", "data": None}
            event = {"id": None, "event": "message", "data": []}
            for raw in r:
                line = raw.decode("utf-8").rstrip("\r\n")
                if not line:
                    if event["data"]:
                        text = "\n".join(event["data"])
                        yield {"id": event["id"], "event": event["event"], "data": json.loads(text)}
                    event = {"id": None, "event": "message", "data": []}
                    continue
                if line.startswith(":"):
                    continue  # a comment: the heartbeat
                name, _, value = line.partition(":")
                value = value[1:] if value.startswith(" ") else value
                if name == "data":
                    event["data"].append(value)
                elif name in ("id", "event"):
                    event[name] = value


def quote(segment):
    return urllib.parse.quote(segment, safe="")


class Grid:
    """A decoded .aara array: its element type ("V3f"), sizes (columns, rows) and the values as a
    flat array of floats (x0, y0, z0, x1, ...), row-major with x fastest; NaN = undefined."""

    def __init__(self, type_name, sizes, values):
        self.type_name, self.sizes, self.values = type_name, sizes, values
        self.local2global = None

    def vertices(self):
        v = self.values
        return (tuple(v[i:i + 3]) for i in range(0, len(v), 3))

    def defined(self):
        return [p for p in self.vertices() if not math.isnan(p[0])]

    def to_global(self, p):
        m = self.local2global
        return tuple(m[4 * r] * p[0] + m[4 * r + 1] * p[1] + m[4 * r + 2] * p[2] + m[4 * r + 3]
                     for r in range(3))


def decode_aara(data):
    """Decodes .aara bytes (../shared/docs/OPC.md): one byte n, the type name (n ASCII bytes, e.g.
    "V3f"), one byte with the number of dimensions d, d little-endian int32 sizes, then the
    elements, little-endian. Supports the float types V3f, V2f and f (what vsmd serves)."""
    if len(data) < 2:
        raise ValueError(".aara: %d bytes is too short" % len(data))
    n = data[0]
    type_name = data[1:1 + n].decode("ascii")
    dims = data[1 + n]
    header = 2 + n + 4 * dims
    if len(data) < header:
        raise ValueError(".aara: truncated header")
    sizes = tuple(int.from_bytes(data[2 + n + 4 * i:6 + n + 4 * i], "little", signed=True)
                  for i in range(dims))
    components = {"V3f": 3, "V2f": 2, "f": 1}.get(type_name)
    if components is None:
        raise ValueError(".aara: element type %r is not supported here" % type_name)
    count = components * math.prod(sizes)
    if len(data) != header + 4 * count:
        raise ValueError(".aara: %d bytes, expected %d for %s %r"
                         % (len(data), header + 4 * count, type_name, sizes))
    values = array.array("f")
    values.frombytes(data[header:])
    if sys.byteorder != "little":
        values.byteswap()
    return Grid(type_name, sizes, values)


def walk(node):
    yield node
    for child in node.get("children", []):
        yield from walk(child)


# ---- commands -------------------------------------------------------------------------------

def cmd_models(client, args):
    models = client.models()
    for m in models:
        print("model %s: version %d, %d patches (%d leaves), depth %d, grid %d x %d"
              % (m["id"], m["version"], m["patches"], m["leaves"], m["depth"], m["grid_size"],
                 m["grid_size"]))
    print("models: %d" % len(models))
    return models


def cmd_walk(client, args):
    tree = client.hierarchy(args.model, depth=args.depth)
    nodes = list(walk(tree["root"]))
    per_level = {}
    for node in nodes:
        depth = int(node["key"].split("_")[0])
        count, leaves, res = per_level.get(depth, (0, 0, math.inf))
        per_level[depth] = (count + 1, leaves + node["leaf"],
                            min(res, node["resolution"] or math.inf))
    for depth in sorted(per_level):
        count, leaves, res = per_level[depth]
        print("level %d: %d patches, %d leaves, finest %.3f m" % (depth, count, leaves, res))
    leaves = [n for n in nodes if n["leaf"]]
    print("hierarchy %s version %d: %d nodes, %d leaves"
          % (args.model, tree["version"], len(nodes), len(leaves)))
    return tree


def cmd_patch(client, args):
    key = args.key
    if key is None:
        leaves = [n for n in walk(client.hierarchy(args.model)["root"]) if n["leaf"]]
        key = leaves[len(leaves) // 2]["key"]
    meta = client.patch(args.model, key)
    grid, etag = client.positions(args.model, key)
    defined = grid.defined()
    print("patch %s/%s: depth %d, version %d, resolution %.3f m, etag %s"
          % (args.model, key, meta["depth"], meta["version"], meta["resolution"], etag))
    print("aara: type %s, sizes %s, %d vertices, %d defined"
          % (grid.type_name, "x".join(map(str, grid.sizes)), len(grid.values) // 3, len(defined)))
    if defined:
        centre = [sum(p[i] for p in defined) / len(defined) for i in range(3)]
        g = grid.to_global(centre)
        lo, hi = meta["box"]["min"], meta["box"]["max"]
        inside = all(lo[i] - 0.01 <= g[i] <= hi[i] + 0.01 for i in range(3))
        print("centre (ECEF m): %.2f %.2f %.2f, %.0f km from the earth's centre, inside box: %s"
              % (*g, math.dist(g, (0, 0, 0)) / 1000, "yes" if inside else "NO"))
    again, _ = client.positions(args.model, key, etag=etag)
    print("conditional GET with the etag: %s" % ("304 not modified" if again is None else "200"))
    if args.out:
        with open(args.out, "wb") as f:
            f.write(client.request("GET", "/v1/models/%s/patches/%s/positions"
                                   % (quote(args.model), quote(key))).body)
        print("written: %s" % args.out)
    return grid


def cmd_merge(client, args):
    job = client.submit_merge(args.target, args.source, register=args.register)
    print("job %s submitted: merge %s into %s" % (job["id"], args.source, args.target))
    started = time.monotonic()

    def show(j):
        print("progress %.3f %s %s" % (j["progress"], j["state"], j["stage"]), flush=True)

    final = client.wait(job["id"], on_progress=show)
    seconds = time.monotonic() - started
    if final["state"] == "succeeded":
        r = final["result"]
        print("result: version %d -> %d, %d new patches, %d vertices from the detail"
              % (r["base_version"], r["version"], r["new_patches"], r["vertices_from_detail"]))
    else:
        print("error: %s" % json.dumps(final["error"]))
    print("job %s %s in %.1f s" % (final["id"], final["state"], seconds))
    return final


def cmd_diff(client, args):
    d = client.diff(args.model, args.from_revision, args.to_revision)
    t = d["totals"]
    print("diff %s %d -> %d: %d patches changed, %d removed, %d shared"
          % (d["model"], d["from"], d["to"], t["changed_patches"], t["removed_patches"],
             t["shared_patches"]))
    if t["samples"]:
        print("displacement m: min %.4f, max %.4f, rms %.4f; changed area %.6g m^2"
              % (t["min"], t["max"], t["rms"], t["changed_area"]))
    if args.png:
        png, limit = client.diff_png(args.model, args.from_revision, args.to_revision, args.size)
        with open(args.png, "wb") as f:
            f.write(png)
        print("written: %s (blue -%.4g m, white 0, red +%.4g m)" % (args.png, limit, limit))
    return d


def cmd_tour(client, args):
    models = cmd_models(client, args)
    if not models:
        raise SystemExit("no model is open")
    model = args.model or models[0]["id"]
    cmd_walk(client, argparse.Namespace(model=model, depth=None))
    cmd_patch(client, argparse.Namespace(model=model, key=None, out=None))
    if args.detail:
        final = cmd_merge(client, argparse.Namespace(target=model, source=args.detail,
                                                     register=False))
        if final["state"] != "succeeded":
            raise SystemExit(1)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default=os.environ.get("VSM_URL", "http://127.0.0.1:8080"))
    parser.add_argument("--token", default=os.environ.get("VSM_TOKEN"))
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("models", help="list the open models")
    p = sub.add_parser("walk", help="walk a model's hierarchy")
    p.add_argument("model")
    p.add_argument("--depth", type=int)
    p = sub.add_parser("patch", help="download a patch's positions and decode them")
    p.add_argument("model")
    p.add_argument("key", nargs="?")
    p.add_argument("--out", help="also write the .aara bytes there")
    p = sub.add_parser("merge", help="merge SOURCE into TARGET as a job, printing progress")
    p.add_argument("target")
    p.add_argument("source")
    p.add_argument("--register", action="store_true", help="register (ICP) before merging")
    p = sub.add_parser("diff", help="what changed between two kept revisions of a model")
    p.add_argument("model")
    p.add_argument("from_revision", type=int)
    p.add_argument("to_revision", type=int)
    p.add_argument("--png", help="also write the top-down map there")
    p.add_argument("--size", type=int, default=1024, help="the map's longer side in pixels")
    p = sub.add_parser("tour", help="models, walk, patch and (with DETAIL) merge")
    p.add_argument("model", nargs="?")
    p.add_argument("detail", nargs="?")
    args = parser.parse_args(argv)
    client = Client(args.url, args.token)
    try:
        result = {"models": cmd_models, "walk": cmd_walk, "patch": cmd_patch, "merge": cmd_merge,
                  "diff": cmd_diff, "tour": cmd_tour}[args.command](client, args)
    except ApiError as e:
        print("vsm_client: %s" % e, file=sys.stderr)
        return 1
    except (urllib.error.URLError, OSError) as e:
        print("vsm_client: cannot reach %s: %s" % (args.url, e), file=sys.stderr)
        return 1
    if args.command == "merge" and result["state"] != "succeeded":
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
