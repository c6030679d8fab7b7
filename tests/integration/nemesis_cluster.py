"""The nemesis's cluster (nemesis_test.py): deploy/local-cluster.sh's (cluster_support), each
node then restarted by the test behind a TCP proxy of its own to etcd (EtcdProxy) and with
tests/fault's LD_PRELOAD library (Node), so that the nemesis can cut one node off etcd, arm its
disk faults and hold its reads."""

import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.parse

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cluster_support  # noqa: E402
import harness  # noqa: E402

TOKEN = "nemesis-token"
LEASE_TTL = 5  # seconds


def start(args, directory):
    """The local cluster over directory/data (its models already there), up."""
    token = cluster_support.write_token(directory, TOKEN)
    env = dict(os.environ, VSMD=args.vsmd, VSM_LEASE_TTL="%ds" % LEASE_TTL,
               VSM_MEMORY_BUDGET="128MiB", VSM_TOKEN_FILE=token,
               VSMD_ARGS="--keep-revisions 10000")
    return cluster_support.LocalCluster(args.repo, directory, env)


# -- the proxy to etcd ------------------------------------------------------------------------

class EtcdProxy:
    """A TCP proxy on 127.0.0.1 in front of etcd for one node. cut("reset") closes its
    connections and refuses new ones; cut("blackhole") keeps them but lets nothing through;
    restore() lets everything through again."""

    def __init__(self, target):
        parsed = urllib.parse.urlparse(target)
        self.target = (parsed.hostname, parsed.port)
        self.listener = socket.socket()
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(64)
        self.url = "http://127.0.0.1:%d" % self.listener.getsockname()[1]
        self.mode = "open"
        self.lock = threading.Lock()
        self.connections = set()  # sockets, both ends
        self.closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while not self.closed:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            with self.lock:
                mode = self.mode
            if mode == "reset":
                client.close()
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=2)
            except OSError:
                client.close()
                continue
            with self.lock:
                self.connections.update((client, upstream))
            threading.Thread(target=self._pump, args=(client, upstream), daemon=True).start()

    def _pump(self, a, b):
        try:
            while not self.closed:
                with self.lock:
                    if a not in self.connections:
                        return
                    mode = self.mode
                if mode == "blackhole":
                    time.sleep(0.05)
                    continue
                readable, _, _ = select.select([a, b], [], [], 0.1)
                for source in readable:
                    data = source.recv(65536)
                    if not data:
                        return
                    (b if source is a else a).sendall(data)
        except OSError:
            pass
        finally:
            with self.lock:
                self.connections.discard(a)
                self.connections.discard(b)
            for s in (a, b):
                try:
                    s.close()
                except OSError:
                    pass

    def cut(self, mode):
        with self.lock:
            self.mode = mode
            victims = list(self.connections) if mode == "reset" else []
            if mode == "reset":
                self.connections.clear()
        for s in victims:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def restore(self):
        with self.lock:
            self.mode = "open"

    def close(self):
        self.closed = True
        self.cut("reset")
        self.listener.close()


# -- the nodes --------------------------------------------------------------------------------

class Node:
    """One vsmd node, restarted by the test with its own proxy to etcd and the fault library."""

    def __init__(self, name, url, argv, proxy, directory, cluster, lib):
        self.name = name
        self.url = url
        self.proxy = proxy
        self.cluster = cluster
        self.lib = lib
        self.argv = list(argv)
        i = self.argv.index("--coordinator")
        self.argv[i + 1] = proxy.url
        self.gate = os.path.join(directory, "gates", name)
        self.reports = os.path.join(directory, "gates", name + ".report")
        self.arm = os.path.join(directory, "gates", name + ".arm")
        self.log = os.path.join(directory, "logs", name + ".log")
        self.proc = None
        self.stopped = False
        self.lock = threading.Lock()  # held while the nemesis restarts it

    def env(self, fault=None):
        cls, n, errno = fault if fault is not None else (None, None, None)
        return harness.fault_env(self.lib, os.path.join(self.cluster.dir, "data"), hold="read",
                                 gate=self.gate, report=self.reports, arm=self.arm, **{
                                     "class": cls, "n": n, "errno": errno})

    def start(self, fault=None):
        with open(self.log, "a") as log:
            log.write("=== nemesis: started%s\n" % (" with fault %s" % (fault,) if fault else ""))
            self.proc = subprocess.Popen(self.argv, env=self.env(fault), stdout=log,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         start_new_session=True)
        self.stopped = False
        self.cluster.set_pid(self.name, self.proc.pid)

    def pid(self):
        return self.proc.pid if self.proc else self.cluster.pids[self.name]

    def signal(self, sig):
        try:
            os.kill(self.pid(), sig)
        except ProcessLookupError:
            pass

    def kill9(self):
        if self.stopped:
            self.signal(signal.SIGCONT)
        self.signal(signal.SIGKILL)
        if self.proc:
            self.proc.wait()
        self.stopped = False

    def exited(self):
        """The exit status when the node ended by itself, else None."""
        return self.proc.poll() if self.proc else None

    def ready(self, timeout=60):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if cluster_support.request(self.url + "/readyz", timeout=2)[0] == 200:
                    return True
            except OSError:
                pass
            if self.exited() is not None:
                return False
            time.sleep(0.1)
        return False


def behind_proxies(cluster, directory, lib, nodes, proxies):
    """Each node of the cluster again, with its own proxy to etcd and the fault library: fills
    `nodes` (name -> Node) and `proxies` as it goes, so that a failure half-way leaves them for
    shut_down."""
    for name in sorted(cluster.nodes):
        pid = cluster.pids[name]
        with open("/proc/%d/cmdline" % pid, "rb") as f:
            argv = [a.decode() for a in f.read().split(b"\0") if a]
        proxy = EtcdProxy(cluster.etcd)
        proxies.append(proxy)
        node = Node(name, cluster.nodes[name], argv, proxy, directory, cluster, lib)
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + 30
        while os.path.exists("/proc/%d" % pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        node.start()
        if not node.ready():
            raise AssertionError(name + " did not start again behind its proxy")
        nodes[name] = node


def quiesce(nodes, timeout=180):
    """Waits until no node has a queued or running job."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        busy = 0
        for node in nodes.values():
            try:
                status, _, body = cluster_support.request(node.url + "/v1/jobs", timeout=5)
            except OSError:
                busy += 1
                continue
            if status != 200:
                busy += 1
                continue
            busy += sum(1 for j in json.loads(body)["jobs"] if j["state"] in ("queued", "running"))
        if busy == 0:
            return True
        time.sleep(0.2)
    return False


def shut_down(cluster, nodes, proxies):
    """The cluster down (the nodes continued first), the nodes waited for, the proxies closed."""
    for node in nodes.values():
        node.signal(signal.SIGCONT)
    cluster.down()
    for node in nodes.values():
        if node.proc:
            try:
                node.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                node.kill9()
    for proxy in proxies:
        proxy.close()
