#!/usr/bin/python3
"""A VSM cluster on loopback, as deploy/local-cluster.sh starts it: real etcd, three real vsmd
nodes over one data root, real nginx in front (deploy/nginx/vsm.conf).

    /usr/bin/python3 cluster_test.py --vsm <vsm> --vsmd <vsmd> --data <shared/data> --work <dir>
                                     --repo <source tree>

1. Through the front: models, hierarchy and patches answer; 50 patches' positions come from at
   least two nodes, and each is byte for byte what every node serves directly. Over TLS the front
   speaks HTTP/2.
2. A merge job submitted through the front (a replica answers 307, nginx follows it to the
   writer) succeeds, and within 2 s every node serves the new version: its number and its bytes.
   Meanwhile 8 clients read through the front: no error, and no mixed version (one patch version
   always has the same bytes, whichever node and whichever moment). One version per answer: before
   the merge, URLs naming the version it will make (?v=N+1: positions, texture, GLB, terrain tile,
   tileset) are answered by nodes that have not made or followed it: 404 no-store through the
   front, and not cached (a second request is no HIT); once every node has followed, the same
   URLs answer version N+1, the writer's bytes, not a cached older answer.
3. kill -9 of a node that is not the writer: 200 reads through the front, none failed.
4. kill -9 of the writer during a merge: another node holds the model's writer key in etcd within
   the lease TTL + 2 s; the model is the old or the new version and validates; a new merge job
   through the front succeeds.
5. A second writer, `vsm merge` from the shell into the served model, is refused.
6. etcd stopped (SIGSTOP): the writer gives its models up within the lease TTL, reads through the
   front still answer, a write answers 503; etcd resumed: the node joins again, writes the model
   again, and a merge through the front succeeds.
"""

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cluster_support  # noqa: E402
import harness  # noqa: E402
from cluster_support import etcd_value, read_env  # noqa: E402
from hold import poll  # noqa: E402

ARGS = None
LEASE_TTL = 5  # seconds; the bound checked is relative to it
TOKEN = "cluster-test-token"


def request(url, method="GET", body=None, timeout=30, token=TOKEN):
    """(status, headers, body bytes); no redirect is followed."""
    return cluster_support.request(url, method, body, timeout, token)


def get_json(url):
    status, _, body = request(url)
    if status != 200:
        raise AssertionError("GET %s: %d %s" % (url, status, body[:200]))
    return json.loads(body)


class Cluster(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.dir = os.path.abspath(ARGS.work)
        shutil.rmtree(cls.dir, ignore_errors=True)
        cls.data = os.path.join(cls.dir, "data")
        token = os.path.join(cls.dir, "token")
        cluster_support.import_models(ARGS.vsm, ARGS.data, cls.data, token, TOKEN)
        cls.script = os.path.join(ARGS.repo, "deploy", "local-cluster.sh")
        env = dict(os.environ, VSMD=ARGS.vsmd, VSM_LEASE_TTL="%ds" % LEASE_TTL,
                   VSM_MEMORY_BUDGET="128MiB", VSM_TOKEN_FILE=token)
        started = time.monotonic()
        subprocess.run([cls.script, "up", cls.dir], check=True, env=env, timeout=180)
        print("cluster up in %.1f s" % (time.monotonic() - started), flush=True)
        cls.env = read_env(os.path.join(cls.dir, "cluster.env"))
        cls.front = cls.env["FRONT"]
        cls.nodes = {"n1": cls.env["N1"], "n2": cls.env["N2"], "n3": cls.env["N3"]}
        cls.pids = {"n1": int(cls.env["PID_N1"]), "n2": int(cls.env["PID_N2"]),
                    "n3": int(cls.env["PID_N3"])}
        cls.killed = set()

    @classmethod
    def tearDownClass(cls):
        subprocess.run([cls.script, "down", cls.dir], timeout=120)

    # -- helpers ----------------------------------------------------------------------------

    def alive(self):
        return {n: u for n, u in self.nodes.items() if n not in self.killed}

    def writer(self, model):
        return etcd_value(self.env["ETCD"], "/vsm/writers/" + model)

    def submit_merge(self, target="prism", source="jacksboro"):
        status, headers, body = request(self.front + "/v1/jobs", "POST",
                                        {"type": "merge", "target": target, "source": source})
        self.assertEqual(status, 202, body[:300])
        job = json.loads(body)
        return job["id"], headers.get("X-VSM-Node")

    def submit_merge_or_none(self):
        """(job id, node) of a merge the front took, or (None, status) when it answered otherwise."""
        status, headers, body = request(self.front + "/v1/jobs", "POST",
                                        {"type": "merge", "target": "prism", "source": "jacksboro"})
        if status != 202:
            return None, status
        return json.loads(body)["id"], headers.get("X-VSM-Node")

    def wait_job(self, job_id, timeout=120):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            status, _, body = request(self.front + "/v1/jobs/" + job_id)
            self.assertEqual(status, 200, body[:300])
            job = json.loads(body)
            if job["state"] in ("succeeded", "failed", "cancelled"):
                return job
            time.sleep(0.1)
        self.fail("job %s did not finish in %d s" % (job_id, timeout))

    def kill(self, node):
        os.kill(self.pids[node], signal.SIGKILL)
        self.killed.add(node)

    # -- the checks, in order ---------------------------------------------------------------

    def test_1_reads_through_the_front_come_from_several_nodes_and_agree(self):
        models = get_json(self.front + "/v1/models")
        self.assertEqual(sorted(m["id"] for m in models["models"]), ["jacksboro", "prism"])
        keys = []
        for model in ("prism", "jacksboro"):
            self.assertEqual(get_json(self.front + "/v1/models/" + model)["id"], model)
            hierarchy = get_json(self.front + "/v1/models/%s/hierarchy" % model)
            keys += [(model, k) for k in harness.keys(hierarchy)]
        self.assertGreaterEqual(len(keys), 50)
        served_by = {}
        for model, key in keys[:50]:
            path = "/v1/models/%s/patches/%s/positions" % (model, key)
            status, headers, body = request(self.front + path)
            self.assertEqual(status, 200, path)
            served_by[headers["X-VSM-Node"]] = served_by.get(headers["X-VSM-Node"], 0) + 1
            for node, url in self.nodes.items():
                status, direct_headers, direct = request(url + path)
                self.assertEqual(status, 200, node + path)
                self.assertEqual(direct_headers["X-VSM-Node"], node)
                self.assertEqual(direct, body, "%s%s differs from the front's" % (node, path))
        print("50 patches through the front, served by", served_by, flush=True)
        self.assertGreaterEqual(len(served_by), 2, served_by)
        # HTTP/2 over TLS, as browsers use it.
        out = subprocess.run(["curl", "-sk", "--http2", "-o", "/dev/null", "-w", "%{http_version} %{http_code}",
                              self.env["FRONT_TLS"] + "/v1/models/prism"],
                             capture_output=True, text=True, timeout=30)
        self.assertEqual(out.stdout, "2 200", out.stderr)

    def versioned_urls(self, version):
        return ["/v1/models/prism/patches/0_0_0/positions?v=%d" % version,
                "/v1/models/prism/patches/0_0_0/texture?v=%d" % version,
                "/v1/models/prism/3dtiles/0_0_0.glb?v=%d" % version,
                "/v1/models/prism/terrain/0/0/0.terrain?v=%d" % version,
                "/v1/models/prism/3dtiles/tileset.json?v=%d" % version]

    def test_2_a_merge_through_the_front_reaches_every_node_and_readers_see_no_mix(self):
        before = get_json(self.nodes["n1"] + "/v1/models/prism")["version"]
        # The next version, asked before any node has it: what a node that has not followed a
        # publish yet sees. Not its older bytes under the newer URL, and nothing the front keeps.
        for path in self.versioned_urls(before + 1):
            for attempt in range(2):
                status, headers, body = request(self.front + path)
                self.assertEqual(status, 404, "%s: %d %s" % (path, status, body[:200]))
                self.assertEqual(headers["Cache-Control"], "no-store", path)
                self.assertEqual(json.loads(body)["error"]["code"], "not_found", path)
                self.assertNotEqual(headers.get("X-Cache-Status"), "HIT", path)
        keys = harness.keys(get_json(self.front + "/v1/models/prism/hierarchy"))
        stop = threading.Event()
        errors = []
        seen = {}  # (key, patch version) -> bytes
        lock = threading.Lock()
        reads = [0]

        def reader(index):
            i = index
            while not stop.is_set():
                key = keys[i % len(keys)]
                i += 7
                # Every other read passes the front's cache (a query it has not seen), so that
                # the nodes answer while the merge publishes and they follow.
                bust = "?read=%d-%d" % (index, i) if i % 2 else ""
                try:
                    status, headers, body = request(
                        self.front + "/v1/models/prism/patches/%s/positions%s" % (key, bust),
                        timeout=10)
                except OSError as e:
                    errors.append("%s: %s" % (key, e))
                    continue
                if status != 200:
                    errors.append("%s: %d %s" % (key, status, body[:100]))
                    continue
                version = (key, headers["X-VSM-Patch-Version"])
                with lock:
                    reads[0] += 1
                    if seen.setdefault(version, body) != body:
                        errors.append("patch %s version %s has two contents" % version)

        threads = [threading.Thread(target=reader, args=(i,)) for i in range(8)]
        for t in threads:
            t.start()
        try:
            # The readers are under way (counted, not timed: on any machine).
            self.assertTrue(poll(lambda: reads[0] >= 50), "the readers read nothing")
            job_id, node = self.submit_merge()
            writer = self.writer("prism")
            self.assertTrue(job_id.startswith(writer + "-"), (job_id, writer))
            job = self.wait_job(job_id)
            self.assertEqual(job["state"], "succeeded", job)
            done = time.monotonic()
            after = get_json(self.nodes[writer] + "/v1/models/prism")["version"]
            self.assertGreater(after, before)
            # While the replicas follow, a client holding the new version's links (from the
            # writer) reads them through the front: a replica that has not followed answers 404
            # and the front asks the next node, so the client sees the new version or nothing.
            lagging = {}
            i = 0
            while time.monotonic() - done < 1.0:
                key = keys[i % len(keys)]
                i += 1
                path = "/v1/models/prism/patches/%s/positions?v=%d&read=lag-%d" % (key, after, i)
                status, headers, body = request(self.front + path, timeout=10)
                lagging[status] = lagging.get(status, 0) + 1
                if status == 200:
                    self.assertEqual(headers["X-VSM-Model-Version"], str(after), path)
            print("?v=%d through the front while the replicas follow: %s" % (after, lagging),
                  flush=True)
            self.assertEqual(set(lagging), {200}, lagging)
            # Every node follows within 2 s: the version, and the changed patches' bytes.
            changed = harness.keys(get_json(self.nodes[writer] + "/v1/models/prism/hierarchy"))
            for name, url in self.nodes.items():
                while get_json(url + "/v1/models/prism")["version"] != after:
                    self.assertLess(time.monotonic() - done, 2.0, name + " did not follow in 2 s")
                    time.sleep(0.05)
                print("%s serves version %d %.2f s after the job ended" % (name, after, time.monotonic() - done),
                      flush=True)
            for key in changed[-20:]:
                path = "/v1/models/prism/patches/%s/positions" % key
                bodies = {name: request(url + path)[2] for name, url in self.nodes.items()}
                self.assertEqual(len(set(bodies.values())), 1, path)
            # The URLs asked before the merge now answer the merged version, through the front.
            self.assertEqual(after, before + 1)
            for path in self.versioned_urls(after):
                status, headers, body = request(self.front + path)
                self.assertEqual(status, 200, "%s: %d %s" % (path, status, body[:200]))
                self.assertEqual(headers["X-VSM-Model-Version"], str(after), path)
                self.assertEqual(body, request(self.nodes[writer] + path)[2], path)
            print("?v=%d before the merge: 404 no-store, not cached; after it: version %d"
                  % (after, after), flush=True)
            # And go on until they have read the merged version too (or the deadline).
            with lock:
                reads_after = reads[0]

            def read_merged():
                with lock:
                    return reads[0] >= reads_after + 50 and str(after) in {v for _, v in seen}

            poll(read_merged)
        finally:
            stop.set()
            for t in threads:
                t.join()
        versions = {v for _, v in seen}
        print("8 readers: %d reads during the merge, patch versions %s, %d errors"
              % (reads[0], sorted(versions), len(errors)), flush=True)
        self.assertEqual(errors, [])
        self.assertIn(str(after), versions, "the readers saw the merged version too")
        self.assertGreater(reads[0], 100)

    def test_3_killing_a_replica_fails_no_read_through_the_front(self):
        writer = self.writer("prism")
        replica = next(n for n in sorted(self.alive()) if n != writer)
        self.kill(replica)
        keys = harness.keys(get_json(self.front + "/v1/models/prism/hierarchy"))
        failed = []
        for i in range(200):
            # Model metadata is not cached by the front (no-cache): every read reaches a node.
            path = "/v1/models/prism" if i % 2 == 0 else "/v1/models/prism/patches/%s" % keys[i % len(keys)]
            status, headers, body = request(self.front + path, timeout=10)
            if status != 200:
                failed.append((path, status, body[:100]))
            else:
                self.assertNotEqual(headers["X-VSM-Node"], replica)
        print("killed %s: 200 reads through the front, %d failed" % (replica, len(failed)), flush=True)
        self.assertEqual(failed, [])

    def test_4_killing_the_writer_during_a_merge_hands_the_model_over(self):
        writer = self.writer("prism")
        before = get_json(self.front + "/v1/models/prism")["version"]
        job_id, _ = self.submit_merge()
        deadline = time.monotonic() + 30
        while get_json(self.front + "/v1/jobs/" + job_id)["state"] == "queued":
            self.assertLess(time.monotonic(), deadline)
            time.sleep(0.02)
        self.kill(writer)
        killed_at = time.monotonic()
        while True:
            holder = self.writer("prism")
            if holder is not None and holder != writer:
                break
            self.assertLess(time.monotonic() - killed_at, LEASE_TTL + 2,
                            "no node took prism over within the TTL + 2 s")
            time.sleep(0.1)
        took = time.monotonic() - killed_at
        print("killed the writer %s during a merge: %s writes prism %.1f s later (TTL %d s)"
              % (writer, holder, took, LEASE_TTL), flush=True)
        # Old or new version, and valid.
        version = get_json(self.nodes[holder] + "/v1/models/prism")["version"]
        self.assertIn(version, (before, before + 1))
        validate = subprocess.run([ARGS.vsm, "validate", os.path.join(self.data, "prism")],
                                  capture_output=True, text=True, timeout=300)
        self.assertEqual(validate.returncode, 0, validate.stdout + validate.stderr)
        job_id, _ = self.submit_merge()
        self.assertTrue(job_id.startswith(holder + "-"), job_id)
        job = self.wait_job(job_id)
        self.assertEqual(job["state"], "succeeded", job)

    def test_5_a_second_writer_from_the_shell_is_refused(self):
        out = subprocess.run([ARGS.vsm, "merge", os.path.join(self.data, "prism"),
                              os.path.join(self.data, "jacksboro")],
                             capture_output=True, text=True, timeout=120)
        self.assertEqual(out.returncode, 1, out.stdout + out.stderr)
        self.assertIn("is being written by vsmd", out.stderr)

    def test_6_a_node_cut_off_from_etcd_stops_writing_and_comes_back(self):
        (node,) = self.alive()
        log_path = os.path.join(self.dir, "logs", node + ".log")
        with open(log_path, errors="replace") as f:
            lost_before = f.read().count("lost its lease")
        etcd = int(self.env["PID_ETCD"])
        os.kill(etcd, signal.SIGSTOP)
        try:
            stopped = time.monotonic()
            while True:
                with open(log_path, errors="replace") as f:
                    if f.read().count("lost its lease") > lost_before:
                        break
                self.assertLess(time.monotonic() - stopped, LEASE_TTL + 5,
                                node + " did not give its models up without etcd")
                time.sleep(0.1)
            print("etcd stopped: %s gave its models up %.1f s later (TTL %d s)"
                  % (node, time.monotonic() - stopped, LEASE_TTL), flush=True)
            status, _, body = request(self.front + "/v1/models/prism")
            self.assertEqual(status, 200, body[:200])
            status, _, body = request(self.front + "/v1/jobs", "POST",
                                      {"type": "merge", "target": "prism", "source": "jacksboro"})
            self.assertEqual(status, 503, body[:300])
        finally:
            os.kill(etcd, signal.SIGCONT)
        resumed = time.monotonic()
        # The node joins again with a new lease; its old writer key goes when the old lease
        # expires, then it claims the model again and opens it for writing. Until then a write
        # answers 503.
        while True:
            job_id, _ = self.submit_merge_or_none()
            if job_id is not None or time.monotonic() - resumed > LEASE_TTL + 10:
                break
            time.sleep(0.2)
        print("etcd resumed: %s took a merge again %.1f s later"
              % (node, time.monotonic() - resumed), flush=True)
        self.assertIsNotNone(job_id, "no merge was taken after etcd came back")
        self.assertEqual(self.wait_job(job_id)["state"], "succeeded")


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    for name in ("--vsm", "--vsmd", "--data", "--work", "--repo"):
        parser.add_argument(name, required=True)
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
