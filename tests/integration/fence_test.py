#!/usr/bin/python3
"""Fenced writers in a cluster (issue 32, finding 2): real etcd and two real vsmd nodes over one
data root, on loopback.

    /usr/bin/python3 fence_test.py --vsm <vsm> --vsmd <vsmd> --lib <libvsm_fault_inject.so>
                                   --data <shared/data> --work <dir>

1. A node whose opening of a model for writing outlasts its lease does not become its writer.
   n2 writes both models; n1 follows them, its reads of `prism` counted by the fault library.
   n2 is killed (-9); once etcd ends its lease, n1 claims the models and starts opening `prism`
   for writing, and its first read of it is held at the gate (the coordinator's thread waits
   there, the writer lock taken). n1's lease then ends in etcd (polled), n2 starts again and
   claims `prism` (its opening waits for n1's lock). The
   gate is opened: n1 finishes the opening, finds its lease past the fence, renews it, hears
   from etcd that it ended and gives the model up (its log says so); n2 becomes the writer and a
   merge through n2 succeeds.
2. The revision that merge published carries n2's fencing token: <Fence><Takeover> is the etcd
   revision that created /vsm/writers/prism, <Lease> the lease it is attached to; n1 follows it.
3. A revision a replica serves is kept (issue 32, finding 3): n1 says in etcd which version it
   serves (/vsm/reading/prism/n1); while its following is held at the gate, n2 publishes twice
   with keep_revisions=2 and no time floor, and the revision n1 serves stays; once n1 follows, a
   later publish drops it.
4. A follower refuses an older token: a hierarchy naming the same patches but an older takeover
   is put in place (as a writer that lost the model would commit it; n2, the writer, does not
   read its own model's hierarchy again, so only the follower is tested); n1 does not follow it, says
   so in its log and counts it in vsm_follows_refused_total; the real hierarchy put back is
   followed again. `vsm validate` accepts the model with its token.
Waits poll for states with generous bounds; no verdict depends on the machine's speed.
"""

import argparse
import base64
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cluster_support  # noqa: E402
from hold import Hold, poll  # noqa: E402

ARGS = None
LEASE_TTL = 3  # seconds
TOKEN = "fence-test-token"


def request(url, method="GET", body=None, timeout=30, token=TOKEN):
    """(status, body bytes); status 0 with the error when the node cannot be reached."""
    try:
        status, _, answer = cluster_support.request(url, method, body, timeout, token)
        return status, answer
    except OSError as e:
        return 0, str(e).encode()


def etcd_key(etcd, key):
    """The key's kv as etcd's JSON API gives it (value decoded), or None."""
    status, body = request(etcd + "/v3/kv/range", "POST",
                           {"key": base64.b64encode(key.encode()).decode()}, token=None)
    if status != 200:
        return None
    kvs = json.loads(body).get("kvs", [])
    if not kvs:
        return None
    kv = kvs[0]
    kv["value"] = base64.b64decode(kv["value"]).decode()
    return kv


def free_ports(n):
    sockets = [socket.socket() for _ in range(n)]
    for s in sockets:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in sockets]
    for s in sockets:
        s.close()
    return ports


def log_of(dir, node):
    with open(os.path.join(dir, node + ".log"), errors="replace") as f:
        return f.read()


def version_of(url, model):
    status, body = request(url + "/v1/models/" + model)
    return json.loads(body)["version"] if status == 200 else None


def fence_of(hierarchy):
    with open(hierarchy) as f:
        text = f.read()
    takeover = re.search(r"<Takeover>(\d+)</Takeover>", text)
    lease = re.search(r"<Lease>(\d+)</Lease>", text)
    return (int(takeover.group(1)) if takeover else None, int(lease.group(1)) if lease else None)


class Fence(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.procs = {}
        cls.logs = {}
        cls.hold = None
        try:
            cls.start_cluster()
        except BaseException:
            cls.tearDownClass()
            raise

    @classmethod
    def start_cluster(cls):
        cls.dir = os.path.abspath(ARGS.work)
        shutil.rmtree(cls.dir, ignore_errors=True)
        cls.data = os.path.join(cls.dir, "data")
        token = os.path.join(cls.dir, "token")
        cluster_support.import_models(ARGS.vsm, ARGS.data, cls.data, token, TOKEN)
        etcd_port, peer_port, p1, p2 = free_ports(4)
        cls.etcd = "http://127.0.0.1:%d" % etcd_port
        cls.logs["etcd"] = open(os.path.join(cls.dir, "etcd.log"), "w")
        cls.procs["etcd"] = subprocess.Popen(
            ["etcd", "--name", "fence", "--data-dir", os.path.join(cls.dir, "etcd"),
             "--listen-client-urls", cls.etcd, "--advertise-client-urls", cls.etcd,
             "--listen-peer-urls", "http://127.0.0.1:%d" % peer_port,
             "--initial-advertise-peer-urls", "http://127.0.0.1:%d" % peer_port,
             "--initial-cluster", "fence=http://127.0.0.1:%d" % peer_port],
            stdout=cls.logs["etcd"], stderr=subprocess.STDOUT)
        if not poll(lambda: request(cls.etcd + "/health")[0] == 200, timeout=60):
            raise AssertionError("etcd did not start")
        cls.urls = {"n1": "http://127.0.0.1:%d" % p1, "n2": "http://127.0.0.1:%d" % p2}
        cls.hold = Hold(ARGS.lib, prefix=os.path.join(cls.data, "prism"), cls="read",
                        gate=os.path.join(cls.dir, "gate"))
        # n2 first, so that it claims every model; n1 then follows them.
        cls.start("n2", dict(os.environ))
        cls.wait_ready("n2")
        if not poll(lambda: all((etcd_key(cls.etcd, "/vsm/writers/" + m) or {}).get("value")
                                == "n2" for m in ("prism", "jacksboro")), timeout=120):
            raise AssertionError("n2 did not claim the models")
        cls.start("n1", cls.hold.env())
        cls.wait_ready("n1")

    @classmethod
    def start(cls, node, env):
        port = cls.urls[node].rsplit(":", 1)[1]
        cls.logs[node] = open(os.path.join(cls.dir, node + ".log"), "a")
        cls.procs[node] = subprocess.Popen(
            [ARGS.vsmd, "--listen", "127.0.0.1:" + port, "--data-root", cls.data,
             "--coordinator", cls.etcd, "--node", node, "--advertise", cls.urls[node],
             "--memory-budget", "128MiB", "--set", "cluster.lease_ttl=%ds" % LEASE_TTL,
             "--set", "keep_revisions=2", "--set", "keep_revisions_seconds=0s",
             "--token-file", os.path.join(cls.dir, "token")],
            env=env, stdout=cls.logs[node], stderr=subprocess.STDOUT)

    @classmethod
    def wait_ready(cls, node):
        if not poll(lambda: request(cls.urls[node] + "/readyz")[0] == 200, timeout=120):
            raise AssertionError(node + " did not become ready")

    @classmethod
    def tearDownClass(cls):
        if cls.hold is not None:
            cls.hold.release()
        for node in ("n1", "n2", "etcd"):
            proc = cls.procs.get(node)
            if proc is None:
                continue
            try:
                proc.send_signal(signal.SIGCONT)
                proc.terminate()
                proc.wait(timeout=30)
            except (subprocess.TimeoutExpired, ProcessLookupError):
                proc.kill()
                proc.wait()
        for f in cls.logs.values():
            f.close()

    def writer(self, model):
        kv = etcd_key(self.etcd, "/vsm/writers/" + model)
        return kv["value"] if kv else None

    def test_1_an_opening_that_outlasts_the_lease_does_not_make_a_writer(self):
        n1_lease = poll(lambda: (etcd_key(self.etcd, "/vsm/nodes/n1") or {}).get("lease"))
        self.assertTrue(n1_lease, "n1 holds no lease")
        # From now on n1's next read under prism waits at the gate.
        allowed = self.hold.let_through(self.hold.calls())
        # n2 dies (its writer locks go with it); its lease ends, n1 claims prism and starts
        # opening it for writing: held there, with the lock taken.
        self.procs["n2"].kill()
        self.procs["n2"].wait()
        path = self.hold.wait_held(allowed + 1, ended=lambda: self.procs["n1"].poll() is not None)
        self.assertIsNotNone(path, "n1 exited")
        print("n1 held opening prism for writing at %s" % path, flush=True)
        self.assertEqual(self.writer("prism"), "n1")
        # n1's coordinator waits at the gate: its lease ends in etcd, and its keys with it.
        self.assertTrue(poll(lambda: etcd_key(self.etcd, "/vsm/nodes/n1") is None,
                             timeout=LEASE_TTL + 60), "n1's lease did not end")
        # n2 starts again and claims prism; its opening for writing waits for n1's lock.
        self.start("n2", dict(os.environ))
        self.wait_ready("n2")
        self.assertTrue(poll(lambda: self.writer("prism") == "n2", timeout=LEASE_TTL + 60),
                        "n2 did not claim prism again")
        self.hold.release()
        self.assertTrue(poll(lambda: "model=prism given up: the lease ended while it was being "
                                     "opened" in log_of(self.dir, "n1"), timeout=120),
                        "n1 did not give prism up after its opening outlasted its lease:\n"
                        + log_of(self.dir, "n1")[-3000:])
        self.assertEqual(self.writer("prism"), "n2")
        # n2 writes prism: a merge through it succeeds.
        Fence.merged = self.run_job("/v1/jobs", {"type": "merge", "target": "prism",
                                                 "source": "jacksboro"})

    def test_2_a_published_revision_carries_its_writers_token_and_is_followed(self):
        kv = etcd_key(self.etcd, "/vsm/writers/prism")
        self.assertEqual(kv["value"], "n2")
        hierarchy = os.path.join(self.data, "prism", "Patches", "patchhierarchy.xml")
        self.assertEqual(fence_of(hierarchy), (int(kv["create_revision"]), int(kv["lease"])))
        self.assertTrue(poll(lambda: version_of(self.urls["n1"], "prism") == Fence.merged,
                             timeout=60), "n1 did not follow n2's merge")
        out = subprocess.run([ARGS.vsm, "validate", os.path.join(self.data, "prism")],
                             capture_output=True, text=True, timeout=300)
        self.assertEqual(out.returncode, 0, out.stdout + out.stderr)

    def run_job(self, path, body=None):
        """Submits a job to n2 (retried while it answers otherwise than 202) and waits for it."""
        def submit():
            status, reply = request(self.urls["n2"] + path, "POST", body or {})
            return json.loads(reply) if status == 202 else None
        job = poll(submit, timeout=120, interval=0.2)
        self.assertIsNotNone(job, "n2 took no job at " + path)

        def final():
            status, reply = request(self.urls["n2"] + "/v1/jobs/" + job["id"])
            state = json.loads(reply) if status == 200 else None
            return state if state and state["state"] in ("succeeded", "failed",
                                                         "cancelled") else None
        done = poll(final, timeout=600, interval=0.2)
        self.assertIsNotNone(done)
        self.assertEqual(done["state"], "succeeded", done)
        return done["result"]["version"]

    def test_3_a_revision_a_replica_serves_is_kept(self):
        patches = os.path.join(self.data, "prism", "Patches")
        served = Fence.merged
        reading = lambda: (etcd_key(self.etcd, "/vsm/reading/prism/n1") or {}).get("value")
        self.assertTrue(poll(lambda: reading() == str(served), timeout=60), reading())
        # n1 follows no more: its next read of prism waits at the gate.
        allowed = self.hold.let_through(self.hold.calls())
        try:
            self.run_job("/v1/models/prism/revisions/%d/restore" % (served - 1))
            self.assertIsNotNone(self.hold.wait_held(allowed + 1), "n1 did not start following")
            self.run_job("/v1/models/prism/revisions/%d/restore" % served)
            # keep_revisions=2 and no time floor: only n1's reading keeps it.
            self.assertTrue(os.path.exists(os.path.join(patches, "vsm-revision-%d.xml" % served)),
                            "the revision n1 serves was dropped: " + str(os.listdir(patches)))
            self.assertEqual(version_of(self.urls["n1"], "prism"), served)
        finally:
            self.hold.release()
        latest = served + 2
        self.assertTrue(poll(lambda: reading() == str(latest), timeout=60), reading())
        # Once n2 has read that (its next round), a publish drops the revision.
        for _ in range(5):
            # (the one before the latest: restoring the latest would change nothing)
            Fence.merged = self.run_job("/v1/models/prism/revisions/%d/restore" % (latest - 1))
            latest = Fence.merged
            if not os.path.exists(os.path.join(patches, "vsm-revision-%d.xml" % served)):
                break
        self.assertFalse(os.path.exists(os.path.join(patches, "vsm-revision-%d.xml" % served)))
        self.assertTrue(poll(lambda: version_of(self.urls["n1"], "prism") == Fence.merged,
                             timeout=60))

    def test_4_a_follower_refuses_an_older_token(self):
        patches = os.path.join(self.data, "prism", "Patches")
        hierarchy = os.path.join(patches, "patchhierarchy.xml")
        takeover, _ = fence_of(hierarchy)
        with open(hierarchy) as f:
            good = f.read()
        # A writer that claimed prism before n2 did (an older takeover) commits: here by hand,
        # with the same patches, so that only the token differs.
        stale = good.replace("<Takeover>%d</Takeover>" % takeover,
                             "<Takeover>%d</Takeover>" % (takeover - 1))
        self.assertNotEqual(stale, good)
        followed = "model=prism read again from disk after another writer published"
        before = log_of(self.dir, "n1").count(followed)
        for name, text in (("stale.xml", stale), ("good.xml", good)):
            with open(os.path.join(patches, name), "w") as f:
                f.write(text)
        os.replace(os.path.join(patches, "stale.xml"), hierarchy)
        self.assertTrue(poll(lambda: "is not followed: its writer's fencing token" in
                             log_of(self.dir, "n1"), timeout=60),
                        "n1 followed a stale token:\n" + log_of(self.dir, "n1")[-3000:])
        status, body = request(self.urls["n1"] + "/metrics")
        self.assertEqual(status, 200)
        self.assertIn("vsm_follows_refused_total 1", body.decode())
        self.assertEqual(version_of(self.urls["n1"], "prism"), Fence.merged)
        self.assertEqual(log_of(self.dir, "n1").count(followed), before)
        os.replace(os.path.join(patches, "good.xml"), hierarchy)
        self.assertTrue(poll(lambda: log_of(self.dir, "n1").count(followed) > before,
                             timeout=60), "n1 did not follow the real hierarchy again")
        status, body = request(self.urls["n1"] + "/metrics")
        self.assertIn("vsm_follows_refused_total 1", body.decode())


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    for name in ("--vsm", "--vsmd", "--lib", "--data", "--work"):
        parser.add_argument(name, required=True)
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2, failfast=True)


if __name__ == "__main__":
    main()
