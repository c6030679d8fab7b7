"""What the cluster tests share: HTTP without redirects or proxies, etcd's JSON gateway, and
deploy/local-cluster.sh (real etcd, three vsmd nodes over one data root, real nginx in front).

    cluster = LocalCluster(repo, directory, env)   # directory/data holds the models
    cluster.up()                                   # cluster.env: front, nodes, etcd, pids
    ...
    cluster.down()

Used by cluster_test.py and the nemesis (nemesis_cluster.py and the other nemesis_*.py).
"""

import base64
import json
import os
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402


def request(url, method="GET", body=None, timeout=30, token=None, headers=None):
    """harness.request, with `token` sent only with writes (reads are public)."""
    return harness.request(url, method, body, timeout, token=token if method != "GET" else None,
                           headers=headers)


def import_models(vsm, rasters, data, token_file, token):
    """PRISM and Jacksboro (`rasters` holds the shared DEMs) imported into `data` as models
    `prism` and `jacksboro`, in patches of 65 x 65 (a few hundred patches, enough to spread over
    nodes), and `token` written to `token_file` (mode 0600) for the nodes."""
    os.makedirs(data, exist_ok=True)
    for name, raster in (("prism", "PRISMelevation.tif"), ("jacksboro", "jacksboro_fault_dem.tif")):
        subprocess.run([vsm, "import", os.path.join(rasters, raster), os.path.join(data, name),
                        "--patch-size", "65"],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    with open(token_file, "w") as f:
        f.write(token + "\n")
    os.chmod(token_file, 0o600)


def etcd_value(etcd, key):
    """The value of `key` in etcd (its v3 JSON API), or None."""
    status, _, body = request(etcd + "/v3/kv/range", "POST",
                              {"key": base64.b64encode(key.encode()).decode()}, timeout=10)
    if status != 200:
        raise AssertionError("etcd range: %d %s" % (status, body[:200]))
    kvs = json.loads(body).get("kvs", [])
    return base64.b64decode(kvs[0]["value"]).decode() if kvs else None


def read_env(path):
    env = {}
    with open(path) as f:
        for line in f:
            name, _, value = line.strip().partition("=")
            env[name] = value
    return env


def write_token(directory, token):
    """A token file (mode 0600) for --token-file; its path."""
    path = os.path.join(directory, "token")
    with open(path, "w") as f:
        f.write(token + "\n")
    os.chmod(path, 0o600)
    return path


class LocalCluster:
    """deploy/local-cluster.sh on `directory` (its models in directory/data)."""

    def __init__(self, repo, directory, env):
        self.script = os.path.join(repo, "deploy", "local-cluster.sh")
        self.dir = directory
        self.env = env

    def up(self, timeout=180):
        started = time.monotonic()
        subprocess.run([self.script, "up", self.dir], check=True, env=self.env, timeout=timeout)
        print("cluster up in %.1f s" % (time.monotonic() - started), flush=True)
        self.values = read_env(os.path.join(self.dir, "cluster.env"))
        self.front = self.values["FRONT"]
        self.etcd = self.values["ETCD"]
        self.nodes = {"n%d" % i: self.values["N%d" % i] for i in (1, 2, 3) if self.values["N%d" % i]}
        self.pids = {"n%d" % i: int(self.values["PID_N%d" % i])
                     for i in (1, 2, 3) if self.values["PID_N%d" % i]}
        return self

    def set_pid(self, node, pid):
        """Records a node restarted by the test in cluster.env, so that `down` stops it."""
        self.pids[node] = pid
        self.values["PID_" + node.upper()] = str(pid)
        path = os.path.join(self.dir, "cluster.env")
        with open(path + ".tmp", "w") as f:
            for name, value in self.values.items():
                f.write("%s=%s\n" % (name, value))
        os.replace(path + ".tmp", path)

    def down(self, timeout=120):
        subprocess.run([self.script, "down", self.dir], timeout=timeout)
