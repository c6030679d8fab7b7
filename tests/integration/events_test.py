#!/usr/bin/python3
"""GET /v1/events end to end: the real vsmd on 127.0.0.1:0 and real data (PRISM and Jacksboro
imported by the real `vsm` at --patch-size 65).

    /usr/bin/python3 events_test.py --vsm <vsm> --vsmd <vsmd> --lib <libvsm_fault_inject.so>
                                    --data <shared/data> --clients <client-examples> --work <dir>

1. Three subscribers read the stream while a merge of Jacksboro into PRISM runs (POST /v1/jobs).
   The merge is held at chosen points (its file creations under PRISM wait at a gate of the
   LD_PRELOAD library tests/fault/fault_inject.c, tests/integration/hold.py) until each
   subscriber has received the progress the job has there, at HELD_POINTS points of increasing
   progress; so the progress events checked below exist on any machine, however fast the merge.
   Each sees the job's progress events ("job", coalesced: at most ~4 a second), then "published"
   for PRISM with the job's new version and the changed keys, then the job's "job_end"
   (succeeded), with strictly increasing ids, all three the same events.
2. A fourth subscriber with a tiny receive buffer never reads while a flood of events is produced
   (FLOOD_JOBS import jobs of a file that is no raster, each failing at once) and the merge is held
   at its last point: the daemon logs that it dropped it and closes its connection; the three
   others keep receiving every event (no gap in the ids); the daemon's VmRSS stays below its level
   before the flood plus RSS_BOUND.
3. The Python client's wait() follows a job on the stream and returns its final state.
4. SIGTERM ends every stream at once: vsmd exits well within its grace period.
5. With limits.event_subscribers=2 a third subscriber gets 503 with Retry-After, and once one
   leaves, a new one is taken.
"""

import argparse
import functools
import json
import os
import re
import shutil
import signal
import socket
import sys
import threading
import time
import unittest
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import Daemon  # noqa: E402
from hold import Hold, poll  # noqa: E402

MiB = 1024 * 1024
# What the flood may add to the daemon's resident memory. The never-reading subscriber's share is
# bounded by its queue (256 events or 256 KiB) plus one write in flight (at most as much again);
# the rest is slack for allocator noise and the failing imports.
RSS_BOUND = 48 * MiB
FLOOD_JOBS = 1500
# Points of distinct progress at which the merge is held until every subscriber has that progress.
HELD_POINTS = 3
# File creations under the target let through between two looks at the held merge (a batch of
# the merge's placing creates a few dozen; a point whose progress did not move is passed over).
HOLD_STEP = 8
# A bound on waits for things a correct daemon does on any machine: only ends a test that hangs.
DEADLINE = 300
# limits.shutdown_grace of the daemon that SIGTERM stops with streams open (4.).
GRACE = 120


class Reader(threading.Thread):
    """A subscriber that reads and parses the stream as it comes."""

    def __init__(self, base, name):
        super().__init__(daemon=True)
        self.name = name
        self.events = []  # (id, event, data, monotonic time)
        self.status = None
        self.headers = None
        self.ended = threading.Event()
        self.opened = threading.Event()
        self.error = None
        self.sock = socket.create_connection(("127.0.0.1", int(base.rsplit(":", 1)[1])), timeout=60)
        self.sock.sendall(b"GET /v1/events HTTP/1.1\r\nHost: test\r\nAccept: text/event-stream\r\n\r\n")

    def run(self):
        try:
            f = self.sock.makefile("rb")
            status_line = f.readline().decode()
            self.status = int(status_line.split()[1])
            headers = {}
            while True:
                line = f.readline().decode().rstrip("\r\n")
                if not line:
                    break
                name, _, value = line.partition(":")
                headers[name.strip().lower()] = value.strip()
            self.headers = headers
            self.opened.set()
            current = {}
            for raw in f:
                line = raw.decode().rstrip("\r\n")
                if not line:
                    if "data" in current:
                        self.events.append((int(current["id"]) if "id" in current else None,
                                            current.get("event", "message"),
                                            json.loads(current["data"]), time.monotonic()))
                    current = {}
                elif not line.startswith(":"):
                    key, _, value = line.partition(": ")
                    current[key] = value
        except Exception as e:  # noqa: BLE001 - reported by the test
            self.error = e
        finally:
            self.opened.set()
            self.ended.set()

    def close(self):
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


def rss(pid):
    with open("/proc/%d/status" % pid) as f:
        return int(re.search(r"(?m)^VmRSS:\s+(\d+) kB", f.read()).group(1)) * 1024


ARGS = None


class Events(unittest.TestCase):
    """1. to 4. on one daemon over PRISM and Jacksboro (imported once), 5. on another."""

    @classmethod
    def setUpClass(cls):
        cls.work = work = os.path.abspath(ARGS.work)
        shutil.rmtree(work, ignore_errors=True)
        cls.root = root = os.path.join(work, "root")
        os.makedirs(root)
        for tif, name in (("PRISMelevation.tif", "prism"), ("jacksboro_fault_dem.tif", "jacksboro")):
            harness.import_dem(os.path.join(ARGS.data, tif), os.path.join(root, name), 65)
        # The flood's file: no raster, at the end of a long path, so that each of its events is a few
        # KiB (the job's parameters and its error name the path) and the flood outgrows what the
        # kernel buffers for the subscriber that does not read (up to its 4 MiB send buffer on loopback).
        junk_dir = os.path.join(*(["d" * 200] * 12))
        os.makedirs(os.path.join(root, junk_dir))
        junk = os.path.join(junk_dir, "junk.txt")
        with open(os.path.join(root, junk), "w") as f:
            f.write("not a raster\n")
        cls.junk = junk

    def test_1_to_4_a_merge_a_flood_the_client_and_sigterm(self):
        import vsm_client
        work, root, junk = self.work, self.root, self.junk
        check = functools.partial(harness.check, self)
        # The merge's file creations under PRISM go through a gate the test opens step by step.
        hold = Hold(ARGS.lib, os.path.join(root, "prism"), "create", os.path.join(work, "gate"))
        # A long grace, so that "the streams end at once" (4.) is far from "vsmd waited for it".
        daemon = Daemon("--memory-budget", "64MiB", "--set", "limits.shutdown_grace=%ds" % GRACE,
                        root=root, env=hold.env(), port_file=os.path.join(work, "vsmd.port"),
                        log_path=os.path.join(work, "vsmd.log"))
        try:
            base = daemon.base
            # A texture tile first: the daemon loads OpenImageIO's module (~260 libraries, ~85 MiB
            # resident) for the first one it reads or writes, a one-time step the flood's bound below
            # is not about.
            with urllib.request.urlopen(base + "/v1/models/prism/patches/0_0_0/texture",
                                        timeout=60) as r:
                check(r.status == 200 and r.read(8) == b"\x89PNG\r\n\x1a\n",
                      "a texture tile is served (PNG) before the flood")
            readers = [Reader(base, "reader%d" % i) for i in range(3)]
            for reader in readers:
                reader.start()
            for reader in readers:
                reader.opened.wait(DEADLINE)
            check(all(r.status == 200 and r.headers.get("content-type") == "text/event-stream"
                      for r in readers), "three subscribers get 200 text/event-stream")
            check(all(r.headers.get("connection", "").lower() == "close" and
                      "content-length" not in r.headers for r in readers),
                  "the stream has no length and ends with the connection")

            # The never-reading subscriber: a receive buffer as small as the kernel allows.
            stuck = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
            stuck.connect(("127.0.0.1", int(base.rsplit(":", 1)[1])))
            stuck.sendall(b"GET /v1/events HTTP/1.1\r\nHost: test\r\n\r\n")

            # 1. A merge seen by the three, held at points of increasing progress: from now on the
            # next file creation under PRISM (the merge's first) waits at the gate.
            allowed = hold.let_through(hold.calls())
            submitted = time.monotonic()
            status, _, job = daemon.json("POST", "/v1/jobs",
                                         {"type": "merge", "target": "prism", "source": "jacksboro"})
            check(status == 202, "merge submitted (202)")
            job_id = job["id"]

            def merge_end():
                return next((e[2] for e in list(readers[0].events)
                             if e[1] == "job_end" and e[2]["job"] == job_id), None)

            def has_progress(reader, fraction):
                return any(e[1] == "job" and e[2].get("job") == job_id and
                           e[2].get("progress") == fraction for e in list(reader.events))

            held = []  # (progress, stage, call) at each point where every subscriber saw it
            while len(held) < HELD_POINTS:
                if hold.wait_held(allowed + 1, ended=lambda: merge_end() is not None,
                                  timeout=DEADLINE) is None:
                    break  # the merge made no further creation: it ended
                # Nothing moves now: the job's progress is what its last report said, and the hub
                # sends a held-back progress event at the end of its interval.
                _, _, now = daemon.json("GET", "/v1/jobs/" + job_id)
                fraction = now.get("progress", 0)
                if now.get("state") == "running" and 0 < fraction < 1 and \
                        (not held or fraction > held[-1][0]):
                    seen = poll(lambda: all(has_progress(r, fraction) for r in readers), DEADLINE)
                    check(seen, "merge held at creation %d (%s, progress %.4f): every subscriber "
                          "received that progress" % (allowed + 1, now["stage"], fraction))
                    if not seen:
                        break
                    held.append((fraction, now["stage"], allowed + 1))
                if len(held) < HELD_POINTS:
                    allowed = hold.let_through(allowed + HOLD_STEP)
            check(len(held) == HELD_POINTS, "the merge was held at %d points of increasing progress "
                  "(%s)" % (len(held), ", ".join("%.4f %s" % h[:2] for h in held)))

            # 2. The flood, while the merge stays held at its last point: import jobs that fail at
            # once. A full job queue (503) is waited out and the same job submitted again, so that
            # every one of them is submitted on any machine.
            rss_before = rss(daemon.proc.pid)
            peak = [rss_before]
            sampling = threading.Event()

            def sample():
                while not sampling.is_set():
                    peak[0] = max(peak[0], rss(daemon.proc.pid))
                    time.sleep(0.02)

            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()
            flood_ids = set()
            deadline = time.monotonic() + 4 * DEADLINE
            for i in range(FLOOD_JOBS):
                while time.monotonic() < deadline:
                    status, _, body = daemon.json(
                        "POST", "/v1/models",
                        {"id": "junk%04d" % i, "source": {"import": junk, "patch_size": 65}})
                    if status == 202:
                        flood_ids.add(body["id"])
                    if status != 503:
                        break
                    time.sleep(0.05)  # the job queue is full: a retry's pace, not synchronisation
            check(len(flood_ids) == FLOOD_JOBS, "%d failing import jobs submitted" % len(flood_ids))
            # Every flood job ends too (the merge is still held).
            poll(lambda: sum(1 for e in list(readers[0].events)
                             if e[1] == "job_end" and e[2]["job"] in flood_ids) == len(flood_ids),
                 DEADLINE)
            ended = sum(1 for e in list(readers[0].events)
                        if e[1] == "job_end" and e[2]["job"] in flood_ids)
            sampling.set()
            sampler.join()
            grown = peak[0] - rss_before
            print("     VmRSS before the flood %.1f MiB, peak %.1f MiB (+%.1f MiB, bound +%d MiB)"
                  % (rss_before / MiB, peak[0] / MiB, grown / MiB, RSS_BOUND // MiB))
            check(grown < RSS_BOUND, "the daemon's VmRSS stays below its level before the flood + %d MiB"
                  % (RSS_BOUND // MiB))
            _, _, now = daemon.json("GET", "/v1/jobs/" + job_id)
            check(now.get("state") == "running" and merge_end() is None,
                  "the merge was running (held) all through the flood")

            # The merge's end, as the stream tells it (the flood pushed it out of GET /v1/jobs's
            # last 100 finished jobs).
            hold.release()
            final = poll(merge_end, 2 * DEADLINE)
            merge_seconds = time.monotonic() - submitted
            check(final is not None and final["state"] == "succeeded",
                  "the merge succeeded in %.1f s" % merge_seconds)
            new_version = final["result"]["version"] if final and "result" in final else -1
            status, _, model = daemon.json("GET", "/v1/models/prism")
            check(model.get("version") == new_version, "prism is at version %d" % new_version)
            # Its last events (published, job_end) reached the other two as well.
            poll(lambda: all(len(r.events) >= len(readers[0].events) for r in readers), DEADLINE)

            for reader in readers:
                events = reader.events
                ids = [e[0] for e in events]
                check(ids == sorted(set(ids)) and len(ids) > 0, "%s: ids strictly increase (%d events)"
                      % (reader.name, len(ids)))
                check(ids == list(range(ids[0], ids[0] + len(ids))),
                      "%s: no event missing (ids %d..%d without a gap)" % (reader.name, ids[0], ids[-1]))
                mine = [e for e in events if isinstance(e[2], dict) and e[2].get("job") == job_id]
                progress = [e for e in mine if e[1] == "job"]
                ends = [e for e in mine if e[1] == "job_end"]
                published = [e for e in events if e[1] == "published" and e[2]["model"] == "prism"]
                check(len(progress) >= 3, "%s: %d progress events of the merge" % (reader.name, len(progress)))
                check(all(p[2]["models"] == ["prism", "jacksboro"] and p[2]["type"] == "merge"
                          for p in progress), "%s: progress names the job's type and models" % reader.name)
                fractions = [p[2]["progress"] for p in progress]
                check(fractions == sorted(fractions), "%s: progress never decreases" % reader.name)
                running = [p for p in progress if p[2]["state"] == "running"]
                span = running[-1][3] - running[0][3] if len(running) > 1 else 0
                check(len(running) <= 4 * span + 4,
                      "%s: progress coalesced: %d running events over %.1f s"
                      % (reader.name, len(running), span))
                check(len(ends) == 1 and ends[0][2]["state"] == "succeeded" and
                      ends[0][2]["result"]["version"] == new_version,
                      "%s: one job_end, succeeded, with the result" % reader.name)
                check(len(published) == 1 and published[0][2]["version"] == new_version and
                      published[0][2]["changed_count"] > 0 and
                      (not published[0][2]["changed_complete"] or
                       len(published[0][2]["changed"]) == published[0][2]["changed_count"]),
                      "%s: published prism version %d with %d changed keys"
                      % (reader.name, new_version, published[0][2]["changed_count"] if published else -1))
                if ends and published:
                    check(all(p[0] < ends[0][0] for p in progress) and published[0][0] < ends[0][0],
                          "%s: progress and published come before job_end" % reader.name)
                    check(progress[0][0] < published[0][0],
                          "%s: progress starts before published" % reader.name)
            check(all([e[:3] for e in r.events] == [e[:3] for e in readers[0].events] for r in readers),
                  "the three subscribers got the same events")
            check(ended == len(flood_ids), "every flood job's end reached the readers (%d)" % ended)
            total = len(readers[0].events)
            size = sum(len(json.dumps(e[2])) for e in readers[0].events)
            print("     %d events, %.0f KiB of data, in the run" % (total, size / 1024))

            log = daemon.log()
            dropped_lines = [line for line in log.splitlines() if "dropped: it fell behind" in line]
            check(len(dropped_lines) == 1, "the daemon logs one dropped subscriber: %s"
                  % (dropped_lines[0].split(" events: ", 1)[-1] if dropped_lines else "none"))
            stuck.settimeout(60)
            received = b""
            closed = False
            try:
                while True:
                    chunk = stuck.recv(65536)
                    if not chunk:
                        closed = True
                        break
                    received += chunk
            except (socket.timeout, ConnectionResetError):
                closed = not isinstance(sys.exc_info()[1], socket.timeout)
            check(closed, "the dropped subscriber's connection was closed by the daemon "
                  "(%d bytes had reached it)" % len(received))
            print("     its last bytes %s the final 'event: dropped'"
                  % ("include" if b"event: dropped" in received else "do not include (best effort)"))
            stuck.close()

            # 3. The Python client follows a job on the stream.
            client = vsm_client.Client(base)
            status, _, job = daemon.json(
                "POST", "/v1/models", {"id": "junkwait", "source": {"import": junk, "patch_size": 65}})
            seen = []
            final = client.wait(job["id"], on_progress=seen.append)
            check(final["state"] == "failed" and seen and seen[-1]["state"] == "failed",
                  "vsm_client wait() follows a job to its end (%d updates)" % len(seen))
            stream = client.events(timeout=60)
            check(next(stream)["event"] == "open", "vsm_client events() opens the stream")
            daemon.json("POST", "/v1/models",
                        {"id": "junkgen", "source": {"import": junk, "patch_size": 65}})
            names = []
            for event in stream:
                names.append(event["event"])
                if event["event"] == "job_end":
                    break
            stream.close()
            check(names[0] == "job" and names[-1] == "job_end", "vsm_client events() yields %s" % names)

            # 4. SIGTERM ends the streams at once: vsmd exits well before the grace period, which
            # it would wait out if a stream kept it (GRACE is long, so any machine is far from it).
            started = time.monotonic()
            daemon.proc.send_signal(signal.SIGTERM)
            daemon.proc.wait(2 * GRACE)
            seconds = time.monotonic() - started
            check(daemon.proc.returncode == 0 and seconds < GRACE / 2,
                  "SIGTERM with three streams open: exit %d after %.2f s (grace %d s)"
                  % (daemon.proc.returncode, seconds, GRACE))
            check(all(r.ended.wait(DEADLINE) for r in readers), "every stream ended with the daemon")
        finally:
            hold.release()
            daemon.stop()

    def test_5_the_cap(self):
        work, root = self.work, self.root
        check = functools.partial(harness.check, self)
        # 5. The cap.
        daemon = Daemon("--set", "limits.event_subscribers=2", root=root,
                        port_file=os.path.join(work, "capped.port"),
                        log_path=os.path.join(work, "capped.log"))
        try:
            base = daemon.base
            first, second = Reader(base, "a"), Reader(base, "b")
            first.start()
            second.start()
            first.opened.wait(DEADLINE)
            second.opened.wait(DEADLINE)
            third = Reader(base, "c")
            third.start()
            third.opened.wait(DEADLINE)
            check(first.status == 200 and second.status == 200 and third.status == 503 and
                  third.headers.get("retry-after") == "1",
                  "limits.event_subscribers=2: a third subscriber gets 503 with Retry-After: 1")
            first.close()

            # The daemon notices the close asynchronously: a new subscriber is asked for until one is
            # taken (each refused one is answered 503 and closed).
            def subscribe():
                reader = Reader(base, "d")
                reader.start()
                reader.opened.wait(DEADLINE)
                if reader.status == 200:
                    return reader
                reader.close()
                return None

            fourth = poll(subscribe, DEADLINE, interval=0.05)
            check(fourth is not None, "once one left, a new subscriber is taken")
        finally:
            daemon.stop()


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--lib", required=True, help="libvsm_fault_inject.so (tests/fault)")
    parser.add_argument("--data", required=True)
    parser.add_argument("--clients", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    sys.path.insert(0, os.path.join(ARGS.clients, "python"))  # vsm_client
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
