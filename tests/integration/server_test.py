#!/usr/bin/python3
"""End-to-end tests of the daemon: the real vsmd binary on 127.0.0.1, port 0, found through
--port-file, driven over real HTTP with the standard library only (http.client, socket,
subprocess, signal). Response bodies are compared with the examples in proto/examples.

Every daemon runs in a temporary directory (its data root) and is stopped with SIGTERM; each
wait is bounded. Run by ctest:
    server_test.py --vsmd build/server/vsmd --proto proto"""

import argparse
import http.client
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import unittest

ARGS = None
# How long a process may take to start (port file, health): a bound that only ends a hang, far
# above what a loaded machine or a sanitizer build needs.
START_DEADLINE = 120
TOKEN = "test-token-0123456789"
MiB = 1024 * 1024
BODY_LIMIT = 1024  # the main daemon's limits.body_bytes
IDLE_TIMEOUT = 1.0  # the main daemon's limits.idle_timeout, seconds
HEADER_TIMEOUT = 1.5  # the main daemon's limits.header_timeout, seconds


class Daemon:
    """One vsmd process on 127.0.0.1:0 with its own data root; the port comes from --port-file."""

    def __init__(self, *flags, config=None, prepare=None, root=None, env=None):
        """`prepare(dir)` fills the data root before the daemon starts; `root` reuses one; `env`
        is the process's environment (default: this one's)."""
        self.dir = root or tempfile.mkdtemp(prefix="vsmd-test-")
        if prepare is not None:
            prepare(self.dir)
        self.port_file = os.path.join(self.dir, "port")
        self.log_path = os.path.join(self.dir, "vsmd.log")
        args = [ARGS.vsmd, "--listen", "127.0.0.1:0", "--data-root", self.dir,
                "--port-file", self.port_file, *flags]
        if config is not None:
            path = os.path.join(self.dir, "vsmd.json")
            with open(path, "w") as f:
                json.dump(config, f)
            args += ["--config", path]
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=log,
                                         stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + START_DEADLINE
        while not os.path.exists(self.port_file):
            if self.proc.poll() is not None:
                raise AssertionError("vsmd exited with %d:\n%s" % (self.proc.returncode, self.log()))
            if time.monotonic() > deadline:
                self.kill()
                raise AssertionError("vsmd wrote no port file within %d s:\n" % START_DEADLINE
                                     + self.log())
            time.sleep(0.02)
        with open(self.port_file) as f:
            self.port = int(f.read())

    def log(self):
        with open(self.log_path, errors="replace") as f:
            return f.read()

    def connection(self, timeout=10):
        return http.client.HTTPConnection("127.0.0.1", self.port, timeout=timeout)

    def socket(self, timeout=10):
        return socket.create_connection(("127.0.0.1", self.port), timeout=timeout)

    def request(self, method, path, body=None, headers=None, timeout=10):
        """One request on a fresh connection: (status, headers, body bytes)."""
        conn = self.connection(timeout)
        try:
            conn.request(method, path, body=body, headers=headers or {})
            response = conn.getresponse()
            return response.status, response.headers, response.read()
        finally:
            conn.close()

    def get_json(self, path, timeout=10):
        status, headers, body = self.request("GET", path, timeout=timeout)
        return status, headers, json.loads(body)

    def stop(self, timeout=20):
        """SIGTERM and the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError("vsmd did not exit within %d s of SIGTERM:\n%s" % (timeout, self.log()))

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def cleanup(self, keep=False):
        self.kill()
        if not keep:
            shutil.rmtree(self.dir, ignore_errors=True)


def example(name):
    with open(os.path.join(ARGS.proto, "examples", name)) as f:
        return json.load(f)


def shape(value, maps=("resident_bytes_by_model",), key=None):
    """The structure of a JSON value: dict keys and value kinds, recursively. Objects named in
    `maps` are maps (any keys, possibly none) of numbers."""
    if isinstance(value, dict):
        if key in maps:
            if any(shape(v) != "number" for v in value.values()):
                return "map with other values than numbers"
            return "map of numbers"
        return {k: shape(v, maps, k) for k, v in value.items()}
    if isinstance(value, list):
        return "list"
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, (int, float)):
        return "number"
    return type(value).__name__


def read_until_closed(sock, limit=1 << 20):
    chunks = []
    while sum(map(len, chunks)) < limit:
        try:
            data = sock.recv(65536)
        except ConnectionResetError:
            break
        if not data:
            break
        chunks.append(data)
    return b"".join(chunks)


def read_response(sock):
    """Reads one response with a Content-Length (or none) from a raw socket: (status, headers
    text, body)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            raise AssertionError("connection closed before a response: %r" % data)
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    head = head.decode("latin-1")
    match = re.search(r"(?im)^content-length:\s*(\d+)", head)
    length = int(match.group(1)) if match else 0
    while len(body) < length:
        chunk = sock.recv(65536)
        if not chunk:
            break
        body += chunk
    return int(head.split(" ")[1]), head, body


class MainDaemon(unittest.TestCase):
    """One daemon with a token, a 1 KiB body limit and a 1 s idle timeout, configured through a
    file whose memory budget the --memory-budget flag overrides."""

    daemon = None

    @classmethod
    def setUpClass(cls):
        config = {"memory_budget": "1GiB",
                  "limits": {"body_bytes": BODY_LIMIT, "idle_timeout": "%gs" % IDLE_TIMEOUT,
                             "header_timeout": "%gs" % HEADER_TIMEOUT},
                  "threads": {"cpu": 2, "io": 2}}
        cls.daemon = Daemon("--memory-budget", "64MiB", "--token", TOKEN, config=config)

    @classmethod
    def tearDownClass(cls):
        try:
            code = cls.daemon.stop()
            log = cls.daemon.log()
            if code != 0:
                raise AssertionError("vsmd exited %d after SIGTERM:\n%s" % (code, log))
            if TOKEN in log:
                raise AssertionError("the token appears in the log")
            if os.path.exists(cls.daemon.port_file):
                raise AssertionError("the port file outlived the daemon")
        finally:
            cls.daemon.cleanup()

    def assert_error(self, body, code, status=None, headers=None):
        error = json.loads(body)
        self.assertEqual(shape(error), shape(example("error-not-found.json")))
        self.assertEqual(error["error"]["code"], code)
        self.assertTrue(error["error"]["message"])
        if headers is not None:
            self.assertEqual(headers["Content-Type"], "application/json")

    def test_healthz_answers_ok(self):
        status, headers, body = self.daemon.get_json("/healthz")
        self.assertEqual(status, 200)
        self.assertEqual(body, example("healthz.json"))
        self.assertEqual(headers["Content-Type"], "application/json")
        self.assertEqual(headers["Cache-Control"], "no-store")
        self.assertEqual(headers["Access-Control-Allow-Origin"], "*")
        self.assertRegex(headers["X-Request-Id"], r"^[0-9a-f]{16}$")

    def test_readyz_answers_ready_once_started(self):
        status, _, body = self.daemon.get_json("/readyz")
        self.assertEqual(status, 200)
        self.assertEqual(body, example("readyz.json"))

    def test_head_has_the_length_of_get_and_no_body(self):
        status, headers, body = self.daemon.request("HEAD", "/healthz")
        self.assertEqual(status, 200)
        self.assertEqual(int(headers["Content-Length"]), len(json.dumps({"status": "ok"},
                                                                       separators=(",", ":"))))
        self.assertEqual(body, b"")

    def test_a_sane_client_request_id_is_echoed(self):
        _, headers, _ = self.daemon.request("GET", "/healthz", headers={"X-Request-Id": "abc-42"})
        self.assertEqual(headers["X-Request-Id"], "abc-42")

    def test_metrics_are_prometheus_text(self):
        self.daemon.request("GET", "/healthz")
        status, headers, body = self.daemon.request("GET", "/metrics")
        self.assertEqual(status, 200)
        self.assertTrue(headers["Content-Type"].startswith("text/plain; version=0.0.4"))
        text = body.decode()
        sample = re.compile(r'^[a-zA-Z_:][a-zA-Z0-9_:]*(\{([a-zA-Z_][a-zA-Z0-9_]*="([^"\\]|\\.)*",?)*\})? '
                            r'(-?[0-9.e+-]+|[+-]Inf|NaN)$')
        for line in text.splitlines():
            if not line.startswith("#"):
                self.assertRegex(line, sample)
        for needle in ("# TYPE vsm_http_requests_total counter",
                       'vsm_http_requests_total{method="GET",route="/healthz",status="200"}',
                       "# TYPE vsm_http_request_duration_seconds histogram",
                       'vsm_http_request_duration_seconds_bucket{route="/healthz",status="200",le="+Inf"}',
                       "vsm_memory_budget_bytes %d" % (64 * MiB),
                       'vsm_memory_resident_bytes{category="positions"} 0',
                       'vsm_pool_threads{pool="cpu"} 2',
                       "vsm_ready 1", "vsm_http_connections_open "):
            self.assertIn(needle, text)

    def test_stats_show_the_budget_from_the_flag_not_the_file(self):
        status, headers, stats = self.daemon.get_json("/v1/stats")
        self.assertEqual(status, 200)
        self.assertEqual(shape(stats), shape(example("stats.json")))
        self.assertEqual(stats["memory"]["budget_bytes"], 64 * MiB)
        self.assertEqual(stats["memory"]["resident_bytes"], 0)
        self.assertEqual(stats["memory"]["resident_bytes_by_model"], {})
        self.assertEqual(stats["cache"]["policy"], "cost-aware-clock")
        self.assertEqual(headers["Cache-Control"], "no-store")

    def test_models_start_empty(self):
        status, headers, body = self.daemon.get_json("/v1/models")
        self.assertEqual(status, 200)
        self.assertEqual(body, {"models": []})
        self.assertEqual(headers["Cache-Control"], "no-cache")

    def test_an_unknown_route_is_a_json_404(self):
        status, headers, body = self.daemon.request("GET", "/v1/nothing?x=1")
        self.assertEqual(status, 404)
        self.assert_error(body, "not_found", headers=headers)
        self.assertEqual(headers["Access-Control-Allow-Origin"], "*")

    def test_a_wrong_method_is_405_with_allow(self):
        status, headers, body = self.daemon.request(
            "PUT", "/v1/stats", body=b"{}", headers={"Authorization": "Bearer " + TOKEN})
        self.assertEqual(status, 405)
        self.assert_error(body, "method_not_allowed")
        self.assertEqual(headers["Allow"], "GET, HEAD, OPTIONS")

    def test_cors_preflight_is_answered(self):
        status, headers, body = self.daemon.request(
            "OPTIONS", "/v1/models",
            headers={"Origin": "https://viewer.example", "Access-Control-Request-Method": "GET",
                     "Access-Control-Request-Headers": "authorization, if-none-match"})
        self.assertEqual(status, 204)
        self.assertEqual(body, b"")
        self.assertEqual(headers["Access-Control-Allow-Origin"], "*")
        self.assertIn("GET", headers["Access-Control-Allow-Methods"])
        allowed = headers["Access-Control-Allow-Headers"].lower()
        self.assertIn("authorization", allowed)
        self.assertIn("if-none-match", allowed)
        self.assertIn("GET", headers["Allow"])

    def test_writes_need_the_bearer_token(self):
        status, headers, body = self.daemon.request("POST", "/v1/models", body=b"{}")
        self.assertEqual(status, 401)
        self.assert_error(body, "unauthorized")
        self.assertTrue(headers["WWW-Authenticate"].startswith("Bearer"))
        status, _, _ = self.daemon.request("POST", "/v1/models", body=b"{}",
                                           headers={"Authorization": "Bearer wrong-token"})
        self.assertEqual(status, 401)
        status, _, _ = self.daemon.request("DELETE", "/v1/models/x")
        self.assertEqual(status, 401)
        status, _, body = self.daemon.request("POST", "/v1/models", body=b"{}",
                                              headers={"Authorization": "Bearer " + TOKEN,
                                                       "Content-Type": "application/json"})
        # Authorized, so the handler saw the body: {} has no "id".
        self.assertEqual(status, 400, body)
        self.assert_error(body, "invalid_argument")
        # Neither a token of another length nor a longer one with the right prefix.
        for credentials in (TOKEN[:-1], TOKEN + "x", "x" * 5000, ""):
            status, _, _ = self.daemon.request("POST", "/v1/models", body=b"{}",
                                               headers={"Authorization": "Bearer " + credentials})
            self.assertEqual(status, 401, credentials[:20])

    def test_an_unauthorized_write_is_answered_on_its_header_alone(self):
        with self.daemon.socket() as sock:
            # The body is announced but never sent: the 401 must not wait for it.
            sock.sendall(b"POST /v1/models HTTP/1.1\r\nHost: x\r\nContent-Length: 1000\r\n"
                         b"Expect: 100-continue\r\n\r\n")
            status, head, body = read_response(sock)
            self.assertEqual(status, 401, head)
            self.assert_error(body, "unauthorized")
            self.assertRegex(head, r"(?im)^connection: close")
            self.assertEqual(read_until_closed(sock), b"")  # and no 100 Continue before it
        # Without a body the connection stays usable.
        with self.daemon.socket() as sock:
            sock.sendall(b"DELETE /v1/models/x HTTP/1.1\r\nHost: x\r\n\r\n"
                         b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            data = read_until_closed(sock).decode()
        self.assertEqual(re.findall(r"HTTP/1.1 (\d{3})", data), ["401", "200"])

    def test_an_oversize_body_is_413_and_the_server_goes_on(self):
        status, headers, body = self.daemon.request(
            "POST", "/v1/models", body=b"x" * (4 * BODY_LIMIT),
            headers={"Authorization": "Bearer " + TOKEN, "Content-Type": "application/json"})
        self.assertEqual(status, 413)
        self.assert_error(body, "payload_too_large")
        self.assertEqual(headers["Connection"], "close")
        self.assertEqual(self.daemon.request("GET", "/healthz")[0], 200)

    def test_an_oversize_header_is_431(self):
        with self.daemon.socket() as sock:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * (20 * 1024) +
                         b"\r\n\r\n")
            status, _, body = read_response(sock)
        self.assertEqual(status, 431)
        self.assert_error(body, "headers_too_large")

    def test_keep_alive_serves_several_requests_on_one_connection(self):
        conn = self.daemon.connection()
        try:
            first_socket = None
            for path, expected in (("/healthz", 200), ("/readyz", 200), ("/v1/stats", 200),
                                   ("/nothing", 404), ("/v1/models", 200), ("/metrics", 200)):
                conn.request("GET", path)
                response = conn.getresponse()
                response.read()
                self.assertEqual(response.status, expected, path)
                self.assertFalse(response.will_close, path)
                first_socket = first_socket or conn.sock
                self.assertIs(conn.sock, first_socket, "the connection was reopened")
        finally:
            conn.close()

    def test_pipelined_requests_are_answered_in_order(self):
        with self.daemon.socket() as sock:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Request-Id: one\r\n\r\n"
                         b"GET /nothing HTTP/1.1\r\nHost: x\r\nX-Request-Id: two\r\n\r\n"
                         b"GET /readyz HTTP/1.1\r\nHost: x\r\nX-Request-Id: three\r\n"
                         b"Connection: close\r\n\r\n")
            data = read_until_closed(sock).decode()
        self.assertEqual(re.findall(r"HTTP/1.1 (\d{3})", data), ["200", "404", "200"])
        self.assertEqual(re.findall(r"(?i)X-Request-Id: (\S+)", data), ["one", "two", "three"])

    def test_a_malformed_request_gets_400_and_a_close_and_the_server_goes_on(self):
        # Another HTTP major version parses (Beast reads any digit.digit) but is not HTTP/1:
        # 505 (RFC 9110 15.6.6), then the connection closes like after every protocol error.
        for junk, status, code in (
                (b"THIS IS NOT HTTP\r\n\r\n", 400, "invalid_argument"),
                (b"GET / HTTP/9.9\r\n\r\n", 505, "http_version_not_supported"),
                (b"GET /healthz HTTP/2.0\r\nHost: x\r\n\r\n", 505, "http_version_not_supported"),
                (b"\x00\x01\x02\xff\r\n\r\n", 400, "invalid_argument"),
                (b"GET /healthz HTTP/1.1\r\nBad Header\r\n\r\n", 400, "invalid_argument")):
            with self.daemon.socket() as sock:
                sock.sendall(junk)
                data = read_until_closed(sock)  # the server closes: a timeout here fails
            head, _, body = data.partition(b"\r\n\r\n")
            self.assertTrue(head.startswith(b"HTTP/1.1 %d " % status), data)
            self.assertRegex(head.decode(), r"(?im)^connection: close")
            self.assert_error(body, code)
            self.assertEqual(self.daemon.request("GET", "/healthz")[0], 200, junk)

    def test_an_idle_connection_is_closed_after_the_idle_timeout(self):
        with self.daemon.socket() as sock:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            self.assertEqual(read_response(sock)[0], 200)
            start = time.monotonic()
            sock.settimeout(IDLE_TIMEOUT + 5)
            self.assertEqual(sock.recv(1), b"")  # closed by the server, not by our timeout
            elapsed = time.monotonic() - start
        self.assertGreater(elapsed, IDLE_TIMEOUT * 0.8)
        self.assertLess(elapsed, IDLE_TIMEOUT + 3)
        # A new connection that never sends anything is closed after the header timeout (its
        # first request's header deadline counts from the accept).
        with self.daemon.socket() as sock:
            start = time.monotonic()
            sock.settimeout(HEADER_TIMEOUT + 5)
            self.assertEqual(sock.recv(1), b"")
            elapsed = time.monotonic() - start
        self.assertGreater(elapsed, HEADER_TIMEOUT * 0.8)
        self.assertLess(elapsed, HEADER_TIMEOUT + 3)

    def test_a_header_trickling_in_is_cut_off_by_the_header_timeout(self):
        with self.daemon.socket() as sock:
            sock.sendall(b"GET /healthz HTTP/1.1\r\n")
            start = time.monotonic()
            sock.settimeout(0.2)
            closed = False
            while not closed and time.monotonic() - start < HEADER_TIMEOUT + 3:
                try:
                    closed = sock.recv(1) == b""
                except socket.timeout:
                    try:
                        sock.sendall(b"X")  # a byte of a header field every 0.2 s
                    except OSError:
                        closed = True
                except ConnectionResetError:
                    closed = True
            elapsed = time.monotonic() - start
        self.assertTrue(closed)
        self.assertLess(elapsed, HEADER_TIMEOUT + 1)

    def test_the_log_names_the_port_redacts_the_token_and_logs_each_request(self):
        self.daemon.request("GET", "/healthz", headers={"X-Request-Id": "log-check"})
        deadline = time.monotonic() + 60  # a bound that only ends a hang
        while "req=log-check" not in self.daemon.log() and time.monotonic() < deadline:
            time.sleep(0.05)
        log = self.daemon.log()
        self.assertIn("listening on 127.0.0.1:%d" % self.daemon.port, log)
        self.assertIn("config token=(redacted)", log)
        self.assertIn("config memory_budget=64MiB", log)
        self.assertIn("config limits.body_bytes=1KiB", log)
        self.assertNotIn(TOKEN, log)
        self.assertRegex(log, r'access req=log-check method=GET target="/healthz" status=200 '
                              r'bytes=15 ms=[0-9.]+ peer=127\.0\.0\.1:\d+')


def write_dem(path, size, cell=0.0005, west=10.0, south=45.0):
    """A synthetic DEM of size x size samples (smooth hills, metres) as an ESRI ASCII grid with a
    WGS 84 .prj beside it: a raster GDAL reads, written with the standard library only."""
    with open(path, "w") as f:
        f.write("ncols %d\nnrows %d\nxllcorner %r\nyllcorner %r\ncellsize %r\n"
                % (size, size, west, south, cell))
        for row in range(size):
            f.write(" ".join("%.2f" % (500 + 40 * math.sin(col / 9.0) * math.cos(row / 13.0)
                                       + 0.5 * row) for col in range(size)))
            f.write("\n")
    with open(os.path.splitext(path)[0] + ".prj", "w") as f:
        f.write('GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
                'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]]')


def import_model(daemon, model_id, raster, patch_size, timeout=300):
    """Imports `raster` (in the data root) as `model_id` through the jobs API and waits for it."""
    status, _, body = daemon.request(
        "POST", "/v1/models",
        body=json.dumps({"id": model_id, "source": {"import": raster, "patch_size": patch_size}}),
        headers={"Authorization": "Bearer " + TOKEN, "Content-Type": "application/json"})
    assert status == 202, body
    job_id = json.loads(body)["id"]
    deadline = time.monotonic() + timeout
    while True:
        status, _, job = daemon.get_json("/v1/jobs/" + job_id)
        assert status == 200, job
        if job["state"] not in ("queued", "running"):
            assert job["state"] == "succeeded", job
            return
        assert time.monotonic() < deadline, job
        time.sleep(0.05)


def metric(text, name, labels=""):
    """The value of one sample of the Prometheus text, e.g. metric(t, "x", '{a="b"}')."""
    match = re.search(r"(?m)^%s%s (\S+)$" % (re.escape(name), re.escape(labels)), text)
    assert match, "no sample %s%s" % (name, labels)
    return float(match.group(1))


class EncodedResponses(unittest.TestCase):
    """Stored positions files held open (sent with sendfile), encodings of cropped patches and
    GLBs are cached inside the one memory budget: charged by category, shown in /v1/stats and
    /metrics, evicted under pressure. A 241 x 241 DEM imported at 65 x 65 (21 patches of 50 KB of
    positions each) into a daemon with a 1 MiB budget."""

    BUDGET = 1 * MiB
    daemon = None

    @classmethod
    def setUpClass(cls):
        # 241 samples across: the patches at the east and north edges are padded, so stored
        # cropped; the others are stored whole.
        cls.daemon = Daemon("--memory-budget", "1MiB", "--token", TOKEN,
                            prepare=lambda root: write_dem(os.path.join(root, "hills.asc"), 241))
        import_model(cls.daemon, "hills", "hills.asc", 65)
        status, _, hierarchy = cls.daemon.get_json("/v1/models/hills/hierarchy")
        assert status == 200, hierarchy

        def walk(node):
            yield node
            for child in node.get("children", []):
                yield from walk(child)
        cls.keys = [node["key"] for node in walk(hierarchy["root"])]
        assert len(cls.keys) == 21, cls.keys

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is not None:
            code = cls.daemon.stop()
            cls.daemon.cleanup(keep=code != 0)
            if code != 0:
                raise AssertionError("vsmd exited %d after SIGTERM" % code)

    def stats(self):
        status, _, stats = self.daemon.get_json("/v1/stats")
        self.assertEqual(status, 200)
        self.assertEqual(shape(stats), shape(example("stats.json")))
        memory = stats["memory"]
        self.assertLessEqual(memory["resident_bytes"], memory["budget_bytes"])
        self.assertEqual(sum(memory["resident_bytes_by_category"].values()),
                         memory["resident_bytes"])
        return stats

    def positions(self, key):
        status, headers, body = self.daemon.request(
            "GET", "/v1/models/hills/patches/%s/positions" % key)
        self.assertEqual(status, 200, body[:200])
        self.assertEqual(int(headers["Content-Length"]), len(body))
        return body

    def patch_stored_whole(self, key):
        status, _, patch = self.daemon.get_json("/v1/models/hills/patches/%s" % key)
        self.assertEqual(status, 200)
        stored = patch["stored"]
        return stored == {"x0": 0, "y0": 0, "x1": 65, "y1": 65}

    def test_a_patch_stored_whole_is_sent_from_its_file_and_a_cropped_one_encoded_in_budget(self):
        whole = [key for key in self.keys if self.patch_stored_whole(key)]
        cropped = [key for key in self.keys if key not in whole]
        # The padded edges leave some patches cropped; the others are whole.
        self.assertTrue(whole and cropped, (whole, cropped))
        before = self.stats()["memory"]
        body = self.positions(whole[0])
        self.assertEqual(len(body), 13 + 65 * 65 * 12)
        with open(os.path.join(self.daemon.dir, "hills", "Patches", whole[0],
                               "Positions.aara"), "rb") as stored:
            self.assertEqual(body, stored.read())  # the stored file, byte for byte
        stats = self.stats()
        memory = stats["memory"]
        # An open file is charged its bookkeeping, not its bytes (those are the page cache's).
        self.assertGreaterEqual(memory["open_files"], 1)
        self.assertLessEqual(memory["open_files"], memory["open_files_limit"])
        self.assertGreater(memory["resident_bytes_by_category"]["open_files"], 0)
        self.assertLess(memory["resident_bytes_by_category"]["open_files"], 4096 * memory["open_files"])
        self.assertEqual(memory["resident_bytes_by_category"]["positions"],
                         before["resident_bytes_by_category"]["positions"])
        # A cropped patch is encoded once, as the full grid, and that encoding is charged.
        body = self.positions(cropped[0])
        self.assertEqual(len(body), 13 + 65 * 65 * 12)
        encoded = self.stats()["memory"]["resident_bytes_by_category"]["encoded"]
        self.assertGreaterEqual(encoded, len(body))
        self.assertGreaterEqual(self.stats()["memory"]["resident_bytes_by_model"]["hills"], encoded)
        # A second request is answered from the cache: a hit, the same bytes.
        hits = stats["cache"]["hits"]
        self.assertEqual(self.positions(cropped[0]), body)
        self.assertGreater(self.stats()["cache"]["hits"], hits)
        status, _, text = self.daemon.request("GET", "/metrics")
        self.assertEqual(status, 200)
        text = text.decode()
        self.assertGreaterEqual(metric(text, "vsm_memory_resident_bytes", '{category="encoded"}'),
                                len(body))
        self.assertGreaterEqual(metric(text, "vsm_cache_open_files"), 1)
        self.assertLessEqual(metric(text, "vsm_memory_model_resident_bytes", '{model="hills"}'),
                             self.BUDGET)

    def test_a_first_request_counts_one_miss_and_a_repeat_one_hit(self):
        # A patch no other test has asked for: the network thread's look misses, the pool opens
        # its file (or encodes it) and caches that; the pool's own look is the same request's and
        # not counted again. The repeat is one hit on the network thread.
        key = self.keys[-1]
        before = self.stats()["cache"]
        self.positions(key)
        after = self.stats()["cache"]
        self.assertEqual(after["misses"] - before["misses"], 1)
        self.positions(key)
        again = self.stats()["cache"]
        self.assertEqual(again["misses"], after["misses"])
        self.assertEqual(again["hits"] - after["hits"], 1)

    def test_encoded_responses_stay_within_the_budget_and_are_evicted_under_pressure(self):
        first = {key: self.positions(key) for key in self.keys}
        glbs = {}
        for key in self.keys:
            status, headers, body = self.daemon.request(
                "GET", "/v1/models/hills/3dtiles/%s.glb" % key)
            self.assertEqual(status, 200, body[:200])
            self.assertEqual(headers["Content-Type"], "model/gltf-binary")
            glbs[key] = body
        stats = self.stats()
        self.assertGreater(stats["cache"]["evictions"], 0)
        self.assertGreater(stats["memory"]["encoded_bytes_by_encoding"]["glb_meshopt"], 0)
        self.assertEqual(sum(stats["memory"]["encoded_bytes_by_encoding"].values()),
                         stats["memory"]["resident_bytes_by_category"]["encoded"])
        # Evicted or not, every answer stays the same.
        for key in reversed(self.keys):
            self.assertEqual(self.positions(key), first[key], key)
            status, _, body = self.daemon.request("GET", "/v1/models/hills/3dtiles/%s.glb" % key)
            self.assertEqual(status, 200)
            self.assertEqual(body, glbs[key], key)
        self.stats()


class ConnectionCap(unittest.TestCase):
    def test_connections_over_the_cap_get_503_with_retry_after(self):
        daemon = Daemon("--set", "limits.connections=2")
        try:
            held = [daemon.socket(), daemon.socket()]
            for sock in held:  # a response proves the server counts the connection
                sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
                self.assertEqual(read_response(sock)[0], 200)
            status, headers, body = daemon.request("GET", "/healthz")
            self.assertEqual(status, 503)
            self.assertEqual(headers["Retry-After"], "1")
            self.assertEqual(json.loads(body)["error"]["code"], "unavailable")
            held.pop().close()
            deadline = time.monotonic() + 60  # a bound that only ends a hang
            while True:  # the server notices the close asynchronously
                status = daemon.request("GET", "/healthz")[0]
                if status == 200 or time.monotonic() > deadline:
                    break
                time.sleep(0.05)
            self.assertEqual(status, 200)
            # Asked on a held connection: a new one could race the server's noticing of the
            # previous close and be over the cap again.
            held[0].sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
            status, _, metrics = read_response(held[0])
            self.assertEqual(status, 200)
            self.assertRegex(metrics.decode(), r"vsm_http_connections_rejected_total [1-9]")
            for sock in held:
                sock.close()
            self.assertEqual(daemon.stop(), 0)
        finally:
            daemon.cleanup()


class TokenFile(unittest.TestCase):
    def test_the_token_comes_from_a_file_and_a_world_readable_one_is_warned_about(self):
        root = tempfile.mkdtemp(prefix="vsmd-token-")
        token = "file-token-0123456789"
        path = os.path.join(root, "token")
        with open(path, "w") as f:
            f.write(token + "\n")
        os.chmod(path, 0o644)
        daemon = Daemon("--token-file", path)
        try:
            headers = {"Content-Type": "application/json"}
            status, _, _ = daemon.request("POST", "/v1/models", body=b"{}", headers=headers)
            self.assertEqual(status, 401)
            headers["Authorization"] = "Bearer " + token
            status, _, body = daemon.request("POST", "/v1/models", body=b"{}", headers=headers)
            self.assertEqual(status, 400, body)  # authorized: the handler says what is missing
            self.assertEqual(daemon.stop(), 0)
            log = daemon.log()
            self.assertIn("can be read by every user", log)
            self.assertIn("config token=(from token_file)", log)
            self.assertIn("config token_file=" + path, log)
            self.assertNotIn(token, log)
        finally:
            daemon.cleanup()
            shutil.rmtree(root, ignore_errors=True)


class Shutdown(unittest.TestCase):
    def test_sigterm_finishes_the_request_in_flight_and_exits_0(self):
        daemon = Daemon("--set", "limits.shutdown_grace=10s")
        try:
            idle = daemon.socket()  # an idle keep-alive connection is closed at once
            with daemon.socket() as sock:
                # A request whose body is still arriving when SIGTERM comes. "100 Continue" says
                # the server has read its header and waits for the body.
                sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nContent-Length: 10\r\n"
                             b"Expect: 100-continue\r\n\r\n12345")
                interim = b""
                while not interim.endswith(b"\r\n\r\n"):
                    chunk = sock.recv(1)
                    self.assertTrue(chunk, "closed before 100 Continue")
                    interim += chunk
                self.assertEqual(interim, b"HTTP/1.1 100 Continue\r\n\r\n")
                daemon.proc.send_signal(signal.SIGTERM)
                idle.settimeout(5)
                self.assertEqual(idle.recv(1), b"")  # the server is stopping
                deadline = time.monotonic() + 5
                refused = False
                while not refused and time.monotonic() < deadline:  # the acceptor closes soon
                    try:
                        socket.create_connection(("127.0.0.1", daemon.port), timeout=2).close()
                    except OSError:
                        refused = True
                    else:
                        time.sleep(0.01)  # the poll interval
                self.assertTrue(refused, "new connections still accepted while stopping")
                self.assertIsNone(daemon.proc.poll(), "vsmd exited with a request in flight")
                sock.sendall(b"67890")
                status, head, body = read_response(sock)
            self.assertEqual(status, 200)
            self.assertRegex(head, r"(?im)^connection: close")
            self.assertEqual(json.loads(body), example("healthz.json"))
            self.assertEqual(daemon.proc.wait(timeout=15), 0)
            self.assertIn("stopped", daemon.log())
            idle.close()
        finally:
            daemon.cleanup()


class CommandLine(unittest.TestCase):
    def run_vsmd(self, *args):
        return subprocess.run([ARGS.vsmd, *args], capture_output=True, text=True, timeout=30)

    def test_bad_flags_exit_2_with_one_line(self):
        result = self.run_vsmd("--memory-budget", "12XB")
        self.assertEqual(result.returncode, 2)
        self.assertIn("memory_budget", result.stderr)
        result = self.run_vsmd("--no-such-flag")
        self.assertEqual(result.returncode, 2)

    def test_a_missing_data_root_exits_1(self):
        result = self.run_vsmd("--listen", "127.0.0.1:0", "--data-root", "/nonexistent/vsm")
        self.assertEqual(result.returncode, 1)
        self.assertIn("data root", result.stderr)

    def test_a_bad_token_file_is_a_clear_error_at_start(self):
        root = tempfile.mkdtemp(prefix="vsmd-token-")
        try:
            missing = os.path.join(root, "missing")
            result = self.run_vsmd("--token-file", missing)
            self.assertEqual(result.returncode, 2)
            self.assertIn("token file '%s' not found" % missing, result.stderr)
            empty = os.path.join(root, "empty")
            with open(empty, "w") as f:
                f.write("\n")
            result = self.run_vsmd("--token-file", empty)
            self.assertEqual(result.returncode, 2)
            self.assertIn("is empty", result.stderr)
            good = os.path.join(root, "token")
            with open(good, "w") as f:
                f.write("abc\n")
            result = self.run_vsmd("--token-file", good, "--token", "abc")
            self.assertEqual(result.returncode, 2)
            self.assertIn("not both", result.stderr)
            with open(good, "w") as f:
                f.write("not a token\n")
            result = self.run_vsmd("--token-file", good)
            self.assertEqual(result.returncode, 2)
            self.assertIn("token", result.stderr)
            self.assertNotIn("not a token", result.stderr)
        finally:
            shutil.rmtree(root, ignore_errors=True)

    def test_help_and_version(self):
        result = self.run_vsmd("--help")
        self.assertEqual(result.returncode, 0)
        self.assertIn("--listen HOST:PORT", result.stdout)
        result = self.run_vsmd("--version")
        self.assertEqual(result.returncode, 0)
        self.assertTrue(result.stdout.startswith("vsmd "))


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--proto", required=True)
    parser.add_argument("--vsm", help="the vsm command (model tests are skipped without it)")
    parser.add_argument("--data", help="the shared real data (../shared/data)")
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
