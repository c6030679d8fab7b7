#!/usr/bin/python3
"""Hostile clients against the real vsmd (127.0.0.1, port 0; server_test.py's harness): slow
headers from more connections of one address than limits.connections_per_client, header floods,
unauthenticated body floods (401 before the body is sent), pipelining floods, random bytes,
chunked-encoding abuse, clients that never read their responses, and one client holding its
share of the event streams (limits.event_subscribers_per_client). Each case checks that a
well-behaved client (another source address: the attacker binds 127.0.0.2) is answered 200 within
WELL_BEHAVED_BOUND meanwhile, and that the daemon's peak memory (VmHWM in /proc/<pid>/status) grew
by less than a bound derived from the limits below. Each case is bounded in time and connections;
the whole run takes well under two minutes. Run by ctest:
    hostile_test.py --vsmd build/server/vsmd --proto proto"""

import argparse
import json
import os
import random
import re
import shutil
import socket
import sys
import tempfile
import threading
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import Daemon, read_response, write_dem  # noqa: E402

KiB = 1024
MiB = 1024 * KiB
TOKEN = "test-token-0123456789"
ATTACKER = "127.0.0.2"  # the hostile clients' source address; the well-behaved one is 127.0.0.1
PER_CLIENT = 16  # limits.connections_per_client
BODY_BYTES = 4 * MiB  # limits.body_bytes
HEADER_BYTES = 8 * KiB  # limits.header_bytes
HEADER_TIMEOUT = 1.0  # limits.header_timeout, seconds
READ_TIMEOUT = 2.0  # limits.read_timeout (the body), seconds
WRITE_TIMEOUT = 2.0  # limits.write_timeout, seconds
PIPELINED = 8  # limits.pipelined_responses
# limits.event_subscribers_per_client, left at its default (so that a vsmd without the bound,
# which would refuse the key, still starts and fails the test at the bound itself), and
# limits.event_subscribers one above it: without the per-client bound one client takes them all.
EVENT_SHARE = 8
EVENT_SUBSCRIBERS = EVENT_SHARE + 1
BUDGET = 8 * MiB  # memory_budget
READ_AHEAD = 64 * KiB  # what a connection's read buffer holds beyond a header (server.cpp)
# A well-behaved client's requests must each be answered within this many seconds.
WELL_BEHAVED_BOUND = 2.0
# What the attacker's connections may make the daemon hold: a read buffer each (a header and the
# read-ahead), the patch cache's budget (the big responses are patch data) and a fixed allowance
# for the allocator's arenas and the threads' stacks. It leaves out BODY_BYTES per connection on
# purpose: bodies of unauthenticated requests are never read, so a server that read them (16 x 4
# MiB = 64 MiB) fails the bound.
SLACK = 24 * MiB
MEMORY_BOUND = PER_CLIENT * (HEADER_BYTES + READ_AHEAD) + BUDGET + SLACK
PATCH = 257  # patch size of the test model: 257 x 257 x 12 bytes of positions (775 KiB)


def attacker_socket(port, timeout=5):
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind((ATTACKER, 0))
    sock.settimeout(timeout)
    sock.connect(("127.0.0.1", port))
    return sock


def memory(pid):
    """VmRSS and VmHWM of `pid` in bytes."""
    with open("/proc/%d/status" % pid) as f:
        text = f.read()
    return tuple(int(re.search(r"(?m)^%s:\s+(\d+) kB" % name, text).group(1)) * KiB
                 for name in ("VmRSS", "VmHWM"))


def recv_until_closed(sock, deadline):
    """Everything the server sends until it closes (b"" or a reset) or `deadline` passes: (data,
    closed)."""
    data = b""
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return data, False
        sock.settimeout(remaining)
        try:
            chunk = sock.recv(65536)
        except (ConnectionResetError, BrokenPipeError):
            return data, True
        except socket.timeout:
            return data, False
        if not chunk:
            return data, True
        data += chunk


def send_for(sock, chunks, seconds, closed=None):
    """Sends `chunks` (an iterator of bytes) without blocking for at most `seconds` or until the
    server stops taking them; returns the bytes sent. Appends to `closed` the seconds after which
    the server closed the connection (a reset or a broken pipe), if it did."""
    start = time.monotonic()
    sock.setblocking(False)
    sent = 0
    deadline = time.monotonic() + seconds
    pending = b""
    try:
        while time.monotonic() < deadline:
            if not pending:
                pending = next(chunks, b"")
                if not pending:
                    break
            try:
                n = sock.send(pending)
            except BlockingIOError:
                time.sleep(0.005)  # the socket is full: the peer is not reading (rate, not sync)
                continue
            sent += n
            pending = pending[n:]
    except (ConnectionResetError, BrokenPipeError):
        if closed is not None:
            closed.append(time.monotonic() - start)
    finally:
        sock.setblocking(True)
    return sent


def status_of(data):
    match = re.match(rb"HTTP/1\.1 (\d{3}) ", data)
    return int(match.group(1)) if match else None


class Hostile(unittest.TestCase):
    daemon = None

    @classmethod
    def setUpClass(cls):
        cls.token_dir = tempfile.mkdtemp(prefix="vsmd-hostile-")
        token_file = os.path.join(cls.token_dir, "token")
        with open(token_file, "w") as f:
            f.write(TOKEN + "\n")
        os.chmod(token_file, 0o600)
        config = {"memory_budget": BUDGET,
                  "limits": {"body_bytes": BODY_BYTES, "header_bytes": HEADER_BYTES,
                             "header_timeout": "%gs" % HEADER_TIMEOUT,
                             "read_timeout": "%gs" % READ_TIMEOUT,
                             "write_timeout": "%gs" % WRITE_TIMEOUT, "idle_timeout": "5s",
                             "connections": 256, "connections_per_client": PER_CLIENT,
                             "pipelined_responses": PIPELINED,
                             "event_subscribers": EVENT_SUBSCRIBERS},
                  "threads": {"cpu": 2, "io": 2, "jobs": 1}}
        cls.daemon = Daemon("--token-file", token_file, config=config, token=TOKEN,
                            prepare=lambda root: write_dem(os.path.join(root, "hills.asc"),
                                                           2 * PATCH - 1))
        cls.daemon.import_model("hills", "hills.asc", PATCH)
        status, _, hierarchy = cls.daemon.get_json("/v1/models/hills/hierarchy")
        assert status == 200, hierarchy
        cls.leaves = [child["key"] for child in hierarchy["root"]["children"]]
        assert len(cls.leaves) == 4, hierarchy
        for key in cls.leaves:  # warm up: what the well-behaved client asks for is cached
            assert cls.daemon.request("GET", cls.positions(key))[0] == 200
        cls.well_behaved_answered()

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.token_dir, ignore_errors=True)
        if cls.daemon is not None:
            code = cls.daemon.stop()
            log = cls.daemon.log()
            cls.daemon.cleanup(keep=code != 0)
            if code != 0:
                raise AssertionError("vsmd exited %d after SIGTERM:\n%s" % (code, log[-4000:]))
            if TOKEN in log:
                raise AssertionError("the token appears in the log")

    @staticmethod
    def positions(key):
        return "/v1/models/hills/patches/%s/positions" % key

    @classmethod
    def well_behaved_answered(cls):
        """A well-behaved client's GET /healthz and patch GET, each answered 200 in time."""
        for path in ("/healthz", "/v1/models/hills/patches/%s" % cls.leaves[0]):
            start = time.monotonic()
            conn = cls.daemon.connection(timeout=WELL_BEHAVED_BOUND)
            try:
                conn.request("GET", path)
                response = conn.getresponse()
                response.read()
            finally:
                conn.close()
            elapsed = time.monotonic() - start
            assert response.status == 200, (path, response.status)
            assert elapsed < WELL_BEHAVED_BOUND, (path, elapsed)

    def setUp(self):
        self.rss, self.hwm = memory(self.daemon.proc.pid)

    def tearDown(self):
        rss, hwm = memory(self.daemon.proc.pid)
        print("  memory: VmRSS %+.1f MiB, VmHWM %+.1f MiB (bound %.1f MiB)"
              % ((rss - self.rss) / MiB, (hwm - self.hwm) / MiB, MEMORY_BOUND / MiB),
              file=sys.stderr)
        self.assertLess(hwm - self.hwm, MEMORY_BOUND)
        self.assertLess(rss - self.rss, MEMORY_BOUND)
        self.well_behaved_answered()
        self.assertIsNone(self.daemon.proc.poll(), "vsmd died")

    def served_meanwhile(self, stop, failures):
        """Runs in a thread while an attack goes on: the well-behaved client, until `stop`."""
        while not stop.is_set():
            try:
                self.well_behaved_answered()
            except Exception as e:  # noqa: BLE001  (reported by the test thread)
                failures.append(repr(e))
                return
            stop.wait(0.1)

    def under_attack(self, attack):
        """Runs `attack()` while the well-behaved client keeps asking; fails when it was not
        answered in time at any point."""
        stop = threading.Event()
        failures = []
        checker = threading.Thread(target=self.served_meanwhile, args=(stop, failures))
        checker.start()
        try:
            return attack()
        finally:
            stop.set()
            checker.join()
            self.assertEqual(failures, [], "a well-behaved client was not served in time")

    def test_slow_headers_from_more_connections_than_the_per_client_limit(self):
        extra = 8

        def attack():
            socks = [attacker_socket(self.daemon.port) for _ in range(PER_CLIENT + extra)]
            start = time.monotonic()
            try:
                for sock in socks:
                    sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
                # The connections over the limit are answered 503 at once; the others wait for
                # their header, which trickles in a byte at a time, until the header timeout.
                rejected, closed = 0, 0
                deadline = start + HEADER_TIMEOUT + 2
                open_socks = list(socks)
                while open_socks and time.monotonic() < deadline:
                    for sock in list(open_socks):
                        sock.setblocking(False)
                        try:
                            data = sock.recv(65536)
                        except BlockingIOError:
                            try:
                                sock.send(b"X")
                            except OSError:
                                pass
                            continue
                        except OSError:
                            data = b""
                        finally:
                            sock.setblocking(True)
                        open_socks.remove(sock)
                        if data:
                            self.assertEqual(status_of(data), 503, data[:200])
                            self.assertRegex(data, rb"(?i)\r\nretry-after: 1\r\n")
                            rejected += 1
                        else:
                            closed += 1
                    time.sleep(0.1)  # trickle rate, not synchronisation
                elapsed = time.monotonic() - start
                self.assertEqual(open_socks, [], "slow headers still open after %.1f s" % elapsed)
                self.assertEqual(rejected, extra)
                self.assertEqual(closed, PER_CLIENT)
                self.assertLess(elapsed, HEADER_TIMEOUT + 2)
            finally:
                for sock in socks:
                    sock.close()
        self.under_attack(attack)

    def subscribe(self, source):
        """GET /v1/events from a socket bound to `source`: (socket, status, header bytes)."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.bind((source, 0))
        sock.settimeout(5)
        sock.connect(("127.0.0.1", self.daemon.port))
        sock.sendall(b"GET /v1/events HTTP/1.1\r\nHost: x\r\nAccept: text/event-stream\r\n\r\n")
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = sock.recv(4096)
            if not chunk:
                break
            head += chunk
        return sock, status_of(head), head

    def test_one_clients_event_subscribers_leave_the_others_a_stream(self):
        # One client (127.0.0.1) fills its share of the /v1/events slots: its next subscriber is
        # answered 503 with Retry-After, while another client (127.0.0.2) still gets a stream.
        socks = []
        try:
            for i in range(EVENT_SHARE):
                sock, status, head = self.subscribe("127.0.0.1")
                socks.append(sock)
                self.assertEqual(status, 200, "subscriber %d of 127.0.0.1: %r" % (i, head[:200]))
                self.assertRegex(head, rb"(?i)\r\ncontent-type: text/event-stream\r\n")
            sock, status, head = self.subscribe("127.0.0.1")
            socks.append(sock)
            self.assertEqual(status, 503, "subscriber %d of 127.0.0.1 (over its share of %d): %r"
                             % (EVENT_SHARE, EVENT_SHARE, head[:300]))
            self.assertRegex(head, rb"(?i)\r\nretry-after: 1\r\n")
            sock, status, head = self.subscribe(ATTACKER)
            socks.append(sock)
            self.assertEqual(status, 200, "127.0.0.2 while 127.0.0.1 holds %d streams: %r"
                             % (EVENT_SHARE, head[:300]))
            self.assertRegex(head, rb"(?i)\r\ncontent-type: text/event-stream\r\n")
        finally:
            for sock in socks:
                sock.close()

    def test_header_floods_get_431_and_are_closed(self):
        def flood(sock):
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
            send_for(sock, iter(lambda: b"X-Flood: " + b"a" * 100 + b"\r\n", None), 2)
            return recv_until_closed(sock, time.monotonic() + 3)

        def long_line(sock):
            sock.sendall(b"GET /healthz HTTP/1.1\r\nX-Long: ")
            send_for(sock, iter(lambda: b"b" * 4096, None), 2)
            return recv_until_closed(sock, time.monotonic() + 3)

        def attack():
            socks = [attacker_socket(self.daemon.port) for _ in range(PER_CLIENT)]
            results = [None] * len(socks)
            threads = [threading.Thread(target=lambda i=i: results.__setitem__(
                i, (flood if i % 2 else long_line)(socks[i]))) for i in range(len(socks))]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            for sock in socks:
                sock.close()
            for data, closed in results:
                self.assertEqual(status_of(data), 431, data[:200])
                self.assertTrue(closed)
        self.under_attack(attack)

    def test_an_unauthenticated_body_is_refused_before_it_is_sent(self):
        def ask(sock, headers):
            sock.sendall(b"POST /v1/models HTTP/1.1\r\nHost: x\r\nContent-Type: application/json"
                         b"\r\n" + headers + b"\r\n")
            # Nothing of the body is sent yet: the answer must come on the header alone.
            return read_response(sock)

        def one(sock, headers, expect_status):
            status, head, body = ask(sock, headers)
            self.assertEqual(status, expect_status, head)
            return head, body

        def attack():
            near_limit = b"Content-Length: %d\r\n" % (BODY_BYTES - 1)
            cases = [
                (near_limit, 401),  # no token
                (near_limit + b"Authorization: Bearer wrong-token\r\n", 401),
                (near_limit + b"Expect: 100-continue\r\n", 401),  # not 100 Continue
                (b"Content-Length: %d\r\n" % (100 * BODY_BYTES), 401),  # 401 before the 413
                (b"Transfer-Encoding: chunked\r\n", 401),
                # With the token: a body over the limit is refused on its Content-Length.
                (b"Content-Length: %d\r\nAuthorization: Bearer %s\r\n"
                 % (BODY_BYTES + 1, TOKEN.encode()), 413),
            ]
            socks = []
            try:
                for headers, status in cases:
                    sock = attacker_socket(self.daemon.port)
                    socks.append(sock)
                    head, body = one(sock, headers, status)
                    self.assertRegex(head, r"(?im)^connection: close")
                    if status == 401:
                        self.assertRegex(head, r"(?im)^www-authenticate: Bearer")
                        self.assertEqual(json.loads(body)["error"]["code"], "unauthorized")
                # A flood: as many unauthenticated uploads as the address may open, each sending
                # its body at full speed after the 401. The server never buffers them: it
                # discards what arrives for the linger (a second) after its answer, then resets
                # the connection; the memory bound holds.
                for sock in socks:
                    sock.close()
                # The server forgets a closed connection when it reads the close, which may come
                # after the new connections are accepted: until then a new one is over the limit
                # and answered 503 with Retry-After, and is opened again, for a bounded time.
                socks = []
                deadline = time.monotonic() + 3
                while len(socks) < PER_CLIENT:
                    sock = attacker_socket(self.daemon.port)
                    status, head, _ = ask(sock, near_limit)
                    if status == 503 and time.monotonic() < deadline:
                        self.assertRegex(head, r"(?im)^retry-after: 1")
                        sock.close()
                        time.sleep(0.05)  # a retry's pace, not synchronisation
                        continue
                    self.assertEqual(status, 401, head)
                    socks.append(sock)
                closed = []
                threads = [threading.Thread(target=lambda s=s: send_for(
                    s, iter(lambda: b"{" * 65536, None), 5, closed)) for s in socks]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                self.assertEqual(len(closed), PER_CLIENT, "uploads still taken after 5 s")
                self.assertLess(max(closed), 1 + 2)  # the linger, and a margin
            finally:
                for sock in socks:
                    sock.close()
        self.under_attack(attack)

    def test_expect_100_continue_is_answered_after_authentication(self):
        sock = attacker_socket(self.daemon.port)
        with sock:
            body = json.dumps({"id": "nothing", "source": {"path": "/nonexistent"}}).encode()
            sock.sendall(b"POST /v1/models HTTP/1.1\r\nHost: x\r\nContent-Type: application/json"
                         b"\r\nAuthorization: Bearer %s\r\nExpect: 100-continue\r\n"
                         b"Content-Length: %d\r\n\r\n" % (TOKEN.encode(), len(body)))
            interim = b""
            while b"\r\n\r\n" not in interim:
                chunk = sock.recv(4096)
                self.assertTrue(chunk, "closed before 100 Continue")
                interim += chunk
            self.assertEqual(interim, b"HTTP/1.1 100 Continue\r\n\r\n")
            sock.sendall(body)
            status, head, answer = read_response(sock)
            # The request was read and handled: the route's own answer, not a protocol error.
            self.assertIn(status, (400, 404), (head, answer))
            self.assertIn(json.loads(answer)["error"]["code"], ("invalid_argument", "not_found"))

    def test_pipelining_floods_are_bounded_and_a_reading_pipeliner_gets_every_answer(self):
        request = b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n"

        def attack():
            socks = [attacker_socket(self.daemon.port) for _ in range(PER_CLIENT - 1)]
            for sock in socks:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            try:
                sent = [send_for(s, iter(lambda: request * 256, None), 1.5) for s in socks]
                # The server stops reading once PIPELINED answers wait for a reader that never
                # comes: only socket buffers took the rest.
                self.assertLess(max(sent), 8 * MiB)
            finally:
                for sock in socks:
                    sock.close()
            # One that reads as it goes gets every answer, in order.
            count = 2000
            sock = attacker_socket(self.daemon.port)
            with sock:
                writer = threading.Thread(target=lambda: sock.sendall(request * count))
                writer.start()
                data = b""
                deadline = time.monotonic() + 20
                while data.count(b"HTTP/1.1 200 ") < count and time.monotonic() < deadline:
                    sock.settimeout(max(0.1, deadline - time.monotonic()))
                    chunk = sock.recv(1 << 20)
                    if not chunk:
                        break
                    data += chunk
                writer.join()
            self.assertEqual(len(re.findall(rb"HTTP/1\.1 (\d{3}) ", data)), count)
            self.assertEqual(data.count(b"HTTP/1.1 200 "), count)
        self.under_attack(attack)

    def test_random_bytes_get_400_and_a_close(self):
        rng = random.Random(12)

        def attack():
            socks = [attacker_socket(self.daemon.port) for _ in range(PER_CLIENT)]
            try:
                for sock in socks:
                    # Printable noise too: it gets past the method before failing.
                    noise = rng.randbytes(64 * KiB) if rng.random() < 0.5 else bytes(
                        rng.choice(b"ABC /:\r\n\t xyz019-") for _ in range(64 * KiB))
                    send_for(sock, iter([noise]), 1)
                for sock in socks:
                    data, closed = recv_until_closed(sock, time.monotonic() + HEADER_TIMEOUT + 2)
                    self.assertTrue(closed)
                    # A 400 (or a 431 when noise without an end of line outgrew the header).
                    self.assertIn(status_of(data), (400, 431), data[:200])
            finally:
                for sock in socks:
                    sock.close()
        self.under_attack(attack)

    def chunked(self, chunks, seconds=2):
        """An authenticated chunked POST whose body is `chunks`: the server's answer (data, closed)."""
        sock = attacker_socket(self.daemon.port)
        with sock:
            sock.sendall(b"POST /v1/models HTTP/1.1\r\nHost: x\r\nContent-Type: application/json"
                         b"\r\nAuthorization: Bearer %s\r\nTransfer-Encoding: chunked\r\n\r\n"
                         % TOKEN.encode())
            send_for(sock, chunks, seconds)
            return recv_until_closed(sock, time.monotonic() + READ_TIMEOUT + 2)

    def test_chunked_encoding_abuse_is_refused(self):
        def attack():
            # A chunk larger than the body limit: refused on its size line.
            data, closed = self.chunked(iter([b"%x\r\n" % (BODY_BYTES + 1), b"a" * 65536]))
            self.assertEqual(status_of(data), 413, data[:200])
            self.assertTrue(closed)
            # A size that does not fit 64 bits, bad syntax, an extension that never ends.
            for junk in (iter([b"F" * 40 + b"\r\n"]), iter([b"zz\r\nabc\r\n"]),
                         iter([b"1\r\na\r\n2\r\nabcd\r\n"]),  # 2 announced, 4 sent
                         iter([b"1;ext="] + [b"e" * 4096] * 64)):
                data, closed = self.chunked(junk)
                self.assertEqual(status_of(data), 400, data[:200])
                self.assertTrue(closed)
            # Endless small chunks: 413 once they add up to the limit.
            data, closed = self.chunked(iter(lambda: b"1000\r\n" + b"c" * 4096 + b"\r\n", None),
                                        seconds=3)
            self.assertEqual(status_of(data), 413, data[:200])
            self.assertTrue(closed)
            # Trailers without end after the last chunk: Beast does not count them against the
            # header limit, the connection's read buffer bounds them (400 when it overflows).
            data, closed = self.chunked(
                iter([b"0\r\n"] + [b"X-Trailer: " + b"t" * 100 + b"\r\n"] * 2000))
            self.assertEqual(status_of(data), 400, data[:200])
            self.assertTrue(closed)
        self.under_attack(attack)

    def test_clients_that_never_read_big_responses_are_bounded_and_cut_off(self):
        paths = [self.positions(key) for key in self.leaves] + ["/v1/models/hills/hierarchy"]
        requests = b"".join(b"GET %s HTTP/1.1\r\nHost: x\r\n\r\n" % p.encode()
                            for p in (paths * PIPELINED)[:PIPELINED])

        def metric(name, labels=""):
            status, _, text = self.daemon.request("GET", "/metrics")
            self.assertEqual(status, 200)
            return harness.metric(text.decode(), name, labels)

        def write_timeouts():
            return metric("vsm_http_timeouts_total", '{phase="write"}')

        def attack():
            before = write_timeouts()
            socks = []
            for _ in range(PER_CLIENT):
                sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
                sock.bind((ATTACKER, 0))
                sock.connect(("127.0.0.1", self.daemon.port))
                sock.sendall(requests * 4)  # more than the server answers at once
                socks.append(sock)
            try:
                # Nobody reads: the server gives up on each after the write timeout (once its
                # socket's send buffer is full) and closes it. (What the kernel had queued is
                # still delivered if the client reads: that is the kernel's, bounded by tcp_wmem.)
                deadline = time.monotonic() + WRITE_TIMEOUT + 10
                while write_timeouts() < before + PER_CLIENT and time.monotonic() < deadline:
                    time.sleep(0.1)  # polls the metric until the deadline
                self.assertEqual(write_timeouts(), before + PER_CLIENT)
                # None of them is open any more: only this request's and the well-behaved
                # client's connections (at most one each) are. A timed-out connection leaves the
                # gauge when its session is destroyed, once its other pending operation (the
                # read) has been cancelled, just after the timeout is counted: wait for it the
                # same way (CI once saw 3 at the first look).
                while (metric("vsm_http_connections_open") > 2
                       and time.monotonic() < deadline):
                    time.sleep(0.1)  # polls the metric until the deadline
                self.assertLessEqual(metric("vsm_http_connections_open"), 2)
            finally:
                for sock in socks:
                    sock.close()
        self.under_attack(attack)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--proto", required=True)
    args, rest = parser.parse_known_args()
    harness.configure(args)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
