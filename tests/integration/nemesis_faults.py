"""The nemesis (nemesis_test.py): lanes of seeded faults, one after another in each, on the
cluster of nemesis_cluster.py: kill -9 of writers and replicas, armed disk faults, etcd and nodes
paused, a node cut off etcd, a replica's reads held; then the heal."""

import os
import random
import signal
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cluster_support  # noqa: E402
from nemesis_cluster import LEASE_TTL  # noqa: E402
from nemesis_models import TARGETS  # noqa: E402

FAULT_CLASSES = ["create", "write", "rename", "sync", "mkdir", "unlink", "read"]


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
