#!/usr/bin/python3
"""The production files of deploy/ agree with each other and with the real vsmd:

- deploy/k8s: every file is in kustomization.yaml (and it renders, when kubectl is there); every
  Service and PodDisruptionBudget selects the pods of a StatefulSet; each StatefulSet's
  serviceName is a headless Service; containerPort = the Services' targetPort = the port of
  `listen` in the ConfigMap = the port of --advertise; the probes are /readyz and /healthz on
  that port, and the real vsmd answers them 200; one ReadWriteMany claim at data_root; the memory
  limit leaves headroom above memory_budget; the grace period exceeds limits.shutdown_grace; the
  token is a Secret file nobody else can read; non-root, read-only root file system.
- deploy/systemd: the hardening directives, TimeoutStopSec above limits.shutdown_grace, no
  ExecReload, `systemd-analyze verify` without a complaint (when systemd-analyze is there).
- Both config files (the ConfigMap's vsmd.json, deploy/systemd/vsmd.json): vsmd starts with each
  (listen and data root overridden to 127.0.0.1:0 and a temporary directory); every key is one
  `vsmd --help` lists, and vsmd does reject an unknown key (so starting is a real check).
- Every --flag of the manifests, the unit (also its commented drop-in) and the Containerfile is
  one `vsmd --help` lists. When etcd is installed, the StatefulSet's
  args and the unit's drop-in ExecStart start a node that joins a local etcd (paths made
  temporary) and publishes its --advertise URL there.
- deploy/nginx: nginx -t accepts vsm.conf with nodes.conf; the nodes are the StatefulSet's pods
  on the container port; client_max_body_size is vsmd's limits.body_bytes.
- deploy/container/Containerfile runs deploy/install-deps.sh and deploy/build.sh, on Debian 12,
  as the same non-root uid as the manifests and the sysusers.d snippet.

Run by ctest (deploy.files):
    deploy_files_test.py --vsmd build/server/vsmd [--source .]"""

import argparse
import base64
import http.client
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import unittest

import yaml  # Debian python3-yaml (deploy/install-deps.sh)

ARGS = None
# How long a process may take to start (port file, health): a bound that only ends a hang, far
# above what a loaded machine or a sanitizer build needs.
START_DEADLINE = 120

# The memory limit must exceed memory_budget by this factor: the budget counts patch data and
# encoded responses, not connection buffers, thread stacks, imports' GDAL/PCL memory or allocator
# slack.
MEMORY_HEADROOM = 1.25


def path(*parts):
    return os.path.join(ARGS.source, *parts)


def read(*parts):
    with open(path(*parts)) as f:
        return f.read()


# --- sizes and durations ----------------------------------------------------------------------

UNITS = {"": 1, "k": 1000, "m": 1000**2, "g": 1000**3, "t": 1000**4,
         "ki": 1024, "mi": 1024**2, "gi": 1024**3, "ti": 1024**4}


def vsm_size(text):
    """vsmd's sizes: bytes or 512KiB, 4GiB, 1GB ..."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([KkMmGgTt]i?)?[Bb]?\s*", str(text))
    assert m, "not a vsmd size: %r" % text
    return float(m.group(1)) * UNITS[(m.group(2) or "").lower()]


def k8s_quantity(text):
    """Kubernetes memory quantities: 6Gi, 6G, 512Mi, 6442450944."""
    m = re.fullmatch(r"(\d+(?:\.\d+)?)([KMGT]i?)?", str(text))
    assert m, "not a Kubernetes memory quantity: %r" % text
    return float(m.group(1)) * UNITS[(m.group(2) or "").lower()]


def seconds(text):
    """vsmd's and systemd's durations as used here: 20, 20s, 250ms, 5m, 1min."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*(ms|s|sec|m|min|h)?\s*", str(text))
    assert m, "not a duration: %r" % text
    scale = {None: 1, "s": 1, "sec": 1, "ms": 0.001, "m": 60, "min": 60, "h": 3600}
    return float(m.group(1)) * scale[m.group(2)]


def flatten(obj, prefix=""):
    """The dotted keys of a vsmd config file ({"limits": {"x": 1}} -> limits.x)."""
    keys = []
    for name, value in obj.items():
        if isinstance(value, dict):
            keys += flatten(value, prefix + name + ".")
        else:
            keys.append(prefix + name)
    return keys


def listen_port(listen):
    return int(listen.rsplit(":", 1)[1])


# --- vsmd --------------------------------------------------------------------------------------

def vsmd_help():
    result = subprocess.run([ARGS.vsmd, "--help"], capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, "vsmd --help exited with %d" % result.returncode
    return result.stdout


def help_flags(text):
    return set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", text))


def help_keys(text):
    """The configuration keys of the --help section 'configuration keys'."""
    section = text.split("configuration keys", 1)[1].split("\nsizes:", 1)[0]
    section = re.sub(r"\([^)]*\)", "", section)  # "(cost-aware-clock | ...)", "(0 = one per core)"
    section = section.split(":", 1)[1]
    return {k.strip() for k in section.replace("\n", " ").split(",") if k.strip()}


class Process:
    """A child process with a log file in a temporary directory (self.proc, self.log_path,
    self.dir): close() stops it with SIGTERM (SIGKILL after 30 s), keeps its log in self.log and
    removes the directory."""

    def close(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        with open(self.log_path, errors="replace") as f:
            self.log = f.read()
        shutil.rmtree(self.dir, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class Daemon(Process):
    """vsmd on 127.0.0.1:0 with a temporary data root; the port comes from --port-file."""

    def __init__(self, *flags):
        self.dir = tempfile.mkdtemp(prefix="vsmd-deploy-test-")
        self.port_file = os.path.join(self.dir, "port")
        self.log_path = os.path.join(self.dir, "vsmd.log")
        data = os.path.join(self.dir, "data")
        os.mkdir(data)
        args = [ARGS.vsmd, *flags, "--listen", "127.0.0.1:0", "--data-root", data,
                "--port-file", self.port_file]
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=log,
                                         stderr=subprocess.STDOUT)
        deadline = time.monotonic() + START_DEADLINE
        while not os.path.exists(self.port_file):
            if self.proc.poll() is not None:
                self.close()
                raise AssertionError("vsmd %s exited with %d:\n%s"
                                     % (shlex.join(flags), self.proc.returncode, self.log))
            if time.monotonic() > deadline:
                self.close()
                raise AssertionError("vsmd wrote no port file within %d s:\n" % START_DEADLINE + self.log)
            time.sleep(0.02)
        with open(self.port_file) as f:
            self.port = int(f.read())

    def get(self, target):
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
        try:
            conn.request("GET", target)
            response = conn.getresponse()
            response.read()
            return response.status
        finally:
            conn.close()

    def get_until_200(self, target, timeout=START_DEADLINE):
        """/readyz may answer 503 for a moment while vsmd starts."""
        deadline = time.monotonic() + timeout
        while True:
            status = self.get(target)
            if status == 200 or time.monotonic() > deadline:
                return status
            time.sleep(0.1)



def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Etcd(Process):
    """A one-member etcd on free loopback ports with a temporary data directory."""

    def __init__(self, binary):
        self.dir = tempfile.mkdtemp(prefix="etcd-deploy-test-")
        self.url = "http://127.0.0.1:%d" % free_port()
        peer = "http://127.0.0.1:%d" % free_port()
        self.log_path = os.path.join(self.dir, "etcd.log")
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [binary, "--name", "deploy-test", "--data-dir", os.path.join(self.dir, "data"),
                 "--listen-client-urls", self.url, "--advertise-client-urls", self.url,
                 "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer,
                 "--initial-cluster", "deploy-test=" + peer],
                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + START_DEADLINE
        while not self.healthy():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise AssertionError("etcd did not start:\n" + self.log)
            time.sleep(0.1)

    def call(self, route, body):
        host, port = self.url[len("http://"):].split(":")
        conn = http.client.HTTPConnection(host, int(port), timeout=5)
        try:
            conn.request("POST", route, body=json.dumps(body))
            response = conn.getresponse()
            return response.status, response.read()
        finally:
            conn.close()

    def healthy(self):
        host, port = self.url[len("http://"):].split(":")
        conn = http.client.HTTPConnection(host, int(port), timeout=2)
        try:
            conn.request("GET", "/health")
            response = conn.getresponse()
            response.read()
            return response.status == 200
        except OSError:
            return False
        finally:
            conn.close()

    def everything(self):
        """All keys and values as text (the etcd v3 JSON API, range over the whole key space)."""
        zero = base64.b64encode(b"\0").decode()
        status, body = self.call("/v3/kv/range", {"key": zero, "range_end": zero})
        assert status == 200, "etcd range: %d %s" % (status, body)
        return "\n".join(base64.b64decode(kv.get(part, "")).decode(errors="replace")
                         for kv in json.loads(body).get("kvs", []) for part in ("key", "value"))



# --- the files ---------------------------------------------------------------------------------

class K8s:
    """The documents of deploy/k8s, as kustomization.yaml lists them."""

    def __init__(self):
        self.kustomization = yaml.safe_load(read("deploy", "k8s", "kustomization.yaml"))
        self.files = list(self.kustomization.get("resources", []))
        self.docs = []
        for name in self.files:
            for doc in yaml.safe_load_all(read("deploy", "k8s", name)):
                if doc:
                    doc["_file"] = name
                    self.docs.append(doc)

    def of_kind(self, kind):
        return [d for d in self.docs if d["kind"] == kind]

    def one(self, kind, name):
        found = [d for d in self.of_kind(kind) if d["metadata"]["name"] == name]
        assert len(found) == 1, "deploy/k8s has %d %s named %r, expected one" % (
            len(found), kind, name)
        return found[0]

    def vsm(self):
        return self.one("StatefulSet", "vsm")

    def vsmd_container(self):
        containers = self.vsm()["spec"]["template"]["spec"]["containers"]
        assert len(containers) == 1, "StatefulSet vsm should have one container (vsmd)"
        return containers[0]

    def config_text(self):
        return self.one("ConfigMap", "vsm-config")["data"]["vsmd.json"]

    def config(self):
        return json.loads(self.config_text())


def arg_value(args, flag):
    """The value of `flag` in an argument list (`--flag value` or `--flag=value`)."""
    for i, arg in enumerate(args):
        if arg == flag:
            assert i + 1 < len(args), "%s without a value in %s" % (flag, args)
            return args[i + 1]
        if arg.startswith(flag + "="):
            return arg.split("=", 1)[1]
    return None


def flags_of(args):
    return {a.split("=", 1)[0] for a in args if a.startswith("--")}


class Unit:
    """deploy/systemd/vsmd.service: directives (repeated ones in order) and ExecStart lines,
    also those of the drop-in example in its comments."""

    def __init__(self):
        self.text = read("deploy", "systemd", "vsmd.service")
        self.directives = {}
        joined = re.sub(r"\\\n\s*", " ", self.text)
        for line in joined.splitlines():
            line = line.strip()
            if line and not line.startswith(("#", ";", "[")):
                key, _, value = line.partition("=")
                self.directives.setdefault(key.strip(), []).append(value.strip())
        # The commented drop-in: "#   ExecStart=/usr/local/bin/vsmd ..." (continued lines joined).
        comments = "\n".join(l.lstrip("#").strip() for l in self.text.splitlines()
                             if l.startswith("#"))
        comments = re.sub(r"\\\n\s*", " ", comments)
        self.commented_exec = [l.partition("=")[2] for l in comments.splitlines()
                               if l.startswith("ExecStart=") and l.partition("=")[2]]

    def value(self, key):
        values = self.directives.get(key)
        assert values, "vsmd.service has no %s=" % key
        return values[-1]

    def exec_starts(self):
        return [v for v in self.directives.get("ExecStart", []) if v] + self.commented_exec


def selects(selector, labels):
    return bool(selector) and all(labels.get(k) == v for k, v in selector.items())


class KubernetesManifests(unittest.TestCase):
    def setUp(self):
        self.k8s = K8s()

    def test_kustomization_lists_every_file_and_renders(self):
        on_disk = {f for f in os.listdir(path("deploy", "k8s"))
                   if f.endswith((".yaml", ".yml")) and f != "kustomization.yaml"}
        listed = set(self.k8s.files)
        self.assertEqual(on_disk - listed, set(), "files in deploy/k8s missing from "
                         "kustomization.yaml resources")
        self.assertEqual(listed - on_disk, set(), "kustomization.yaml lists missing files")
        kubectl = shutil.which("kubectl")
        if kubectl is None:
            print("skipped: kubectl kustomize (no kubectl on PATH)", file=sys.stderr)
            return
        result = subprocess.run([kubectl, "kustomize", path("deploy", "k8s")],
                                capture_output=True, text=True, timeout=60)
        self.assertEqual(result.returncode, 0, "kubectl kustomize deploy/k8s failed:\n"
                         + result.stderr)

    def test_selectors_match_pod_labels(self):
        sets = self.k8s.of_kind("StatefulSet")
        self.assertTrue(sets, "no StatefulSet in deploy/k8s")
        for s in sets:
            labels = s["spec"]["template"]["metadata"]["labels"]
            self.assertTrue(selects(s["spec"]["selector"]["matchLabels"], labels),
                            "StatefulSet %s: selector %s does not match its pod labels %s"
                            % (s["metadata"]["name"], s["spec"]["selector"], labels))
        pods = {s["metadata"]["name"]: s["spec"]["template"]["metadata"]["labels"] for s in sets}
        checked = []
        for doc in self.k8s.of_kind("Service") + self.k8s.of_kind("PodDisruptionBudget"):
            name = "%s %s" % (doc["kind"], doc["metadata"]["name"])
            selector = (doc["spec"]["selector"] if doc["kind"] == "Service"
                        else doc["spec"]["selector"]["matchLabels"])
            matched = [s for s, labels in pods.items() if selects(selector, labels)]
            self.assertEqual(len(matched), 1, "%s: selector %s selects the pods of %s; expected "
                             "exactly one StatefulSet (pod labels: %s)"
                             % (name, selector, matched or "none", pods))
            checked.append((name, matched[0]))
        for expected in ("Service vsm", "Service vsm-nodes", "PodDisruptionBudget vsm"):
            self.assertIn((expected, "vsm"), checked, expected + " must select the vsm pods")
        pdb = self.k8s.one("PodDisruptionBudget", "vsm")
        self.assertEqual(pdb["spec"].get("maxUnavailable"), 1, "PDB vsm: maxUnavailable 1")

    def test_service_names_are_headless_services(self):
        for s in self.k8s.of_kind("StatefulSet"):
            name = s["spec"].get("serviceName")
            service = self.k8s.one("Service", name)
            self.assertEqual(service["spec"].get("clusterIP"), "None",
                             "Service %s (serviceName of StatefulSet %s) must be headless"
                             % (name, s["metadata"]["name"]))
        self.assertEqual(self.k8s.vsm()["spec"]["serviceName"], "vsm-nodes")
        self.assertEqual(self.k8s.vsm()["spec"]["replicas"], 3, "three vsmd nodes")

    def test_ports_agree(self):
        container = self.k8s.vsmd_container()
        ports = {p.get("name"): p["containerPort"] for p in container["ports"]}
        self.assertEqual(len(set(ports.values())), 1, "vsmd has one container port: %s" % ports)
        port = next(iter(ports.values()))

        def resolve(target):
            return ports.get(target, target) if isinstance(target, str) else target

        for name in ("vsm", "vsm-nodes"):
            for p in self.k8s.one("Service", name)["spec"]["ports"]:
                target = resolve(p.get("targetPort", p["port"]))
                self.assertEqual(target, port, "Service %s targetPort %s != containerPort %d"
                                 % (name, p.get("targetPort"), port))
        listen = self.k8s.config()["listen"]
        self.assertEqual(listen_port(listen), port,
                         "ConfigMap listen %s: not the containerPort %d" % (listen, port))
        args = container.get("args", [])
        advertise = arg_value(args, "--advertise")
        self.assertIsNotNone(advertise, "vsmd has no --advertise")
        m = re.fullmatch(r"http://\$\(POD_NAME\)\.([a-z0-9-]+)\.[^:/]+:(\d+)/?", advertise)
        self.assertIsNotNone(m, "--advertise %s is not http://$(POD_NAME).<service>...:PORT"
                             % advertise)
        self.assertEqual(m.group(1), self.k8s.vsm()["spec"]["serviceName"],
                         "--advertise names another service than the StatefulSet's serviceName")
        self.assertEqual(int(m.group(2)), port, "--advertise port != containerPort")
        self.assertEqual(arg_value(args, "--node"), "$(POD_NAME)")
        env = {e["name"]: e for e in container.get("env", [])}
        for var in re.findall(r"\$\((\w+)\)", " ".join(args)):
            self.assertIn(var, env, "args use $(%s), which the container does not define" % var)
        for kind in ("startupProbe", "readinessProbe", "livenessProbe"):
            if kind in container:
                self.assertEqual(resolve(container[kind]["httpGet"]["port"]), port,
                                 "%s is not on the containerPort" % kind)

    def test_probes_are_routes_of_vsmd(self):
        container = self.k8s.vsmd_container()
        self.assertEqual(container["readinessProbe"]["httpGet"]["path"], "/readyz")
        self.assertEqual(container["livenessProbe"]["httpGet"]["path"], "/healthz")
        paths = {container[k]["httpGet"]["path"]
                 for k in ("startupProbe", "readinessProbe", "livenessProbe") if k in container}
        with Daemon() as vsmd:
            for target in sorted(paths):
                self.assertEqual(vsmd.get_until_200(target), 200,
                                 "GET %s of the real vsmd did not answer 200" % target)

    def test_one_shared_data_root(self):
        spec = self.k8s.vsm()["spec"]
        data_root = self.k8s.config()["data_root"]
        mounts = {m["mountPath"]: m["name"] for m in self.k8s.vsmd_container()["volumeMounts"]}
        self.assertIn(data_root, mounts, "nothing is mounted at data_root %s" % data_root)
        volumes = {v["name"]: v for v in spec["template"]["spec"]["volumes"]}
        volume = volumes[mounts[data_root]]
        self.assertIn("persistentVolumeClaim", volume,
                      "data_root must be one shared claim, not a per-pod volumeClaimTemplate")
        claim = self.k8s.one("PersistentVolumeClaim",
                             volume["persistentVolumeClaim"]["claimName"])
        self.assertEqual(claim["metadata"]["name"], "vsm-data")
        self.assertEqual(claim["spec"]["accessModes"], ["ReadWriteMany"],
                         "all nodes mount the data root at once: ReadWriteMany")

    def test_memory_limit_above_budget(self):
        budget = vsm_size(self.k8s.config()["memory_budget"])
        resources = self.k8s.vsmd_container()["resources"]
        limit = k8s_quantity(resources["limits"]["memory"])
        self.assertGreaterEqual(limit, budget * MEMORY_HEADROOM,
                                "memory limit %s is not %.2fx memory_budget %s"
                                % (resources["limits"]["memory"], MEMORY_HEADROOM,
                                   self.k8s.config()["memory_budget"]))
        self.assertLessEqual(k8s_quantity(resources["requests"]["memory"]), limit)
        self.assertIn("cpu", resources["requests"], "vsmd requests cpu")

    def test_grace_period_above_shutdown_grace(self):
        grace = seconds(self.k8s.config().get("limits", {}).get("shutdown_grace", "10s"))
        period = self.k8s.vsm()["spec"]["template"]["spec"]["terminationGracePeriodSeconds"]
        self.assertGreater(period, grace, "terminationGracePeriodSeconds %s <= "
                           "limits.shutdown_grace %ss: SIGKILL before vsmd has written back"
                           % (period, grace))

    def test_token_is_a_private_secret_file(self):
        container = self.k8s.vsmd_container()
        token_file = arg_value(container["args"], "--token-file")
        self.assertIsNotNone(token_file, "vsmd has no --token-file")
        self.assertNotIn("--token", flags_of(container["args"]), "--token is visible in ps")
        volumes = {v["name"]: v for v in self.k8s.vsm()["spec"]["template"]["spec"]["volumes"]}
        mount = [m for m in container["volumeMounts"]
                 if token_file.startswith(m["mountPath"].rstrip("/") + "/")]
        self.assertEqual(len(mount), 1, "--token-file %s is in no mounted volume" % token_file)
        secret = volumes[mount[0]["name"]].get("secret")
        self.assertIsNotNone(secret, "--token-file %s is not in a Secret volume" % token_file)
        mode = secret.get("defaultMode", 0o644)
        self.assertEqual(mode & 0o007, 0, "the token file is readable by every user (mode %o)"
                         % mode)

    def test_security_context(self):
        pod = self.k8s.vsm()["spec"]["template"]["spec"]
        container = self.k8s.vsmd_container()
        self.assertTrue(pod["securityContext"].get("runAsNonRoot"), "runAsNonRoot")
        self.assertTrue(container["securityContext"].get("readOnlyRootFilesystem"),
                        "readOnlyRootFilesystem")
        uid = pod["securityContext"].get("runAsUser")
        self.assertEqual(uid, containerfile_uid(), "runAsUser is not the Containerfile's USER")


def containerfile_uid():
    m = re.search(r"^USER\s+(\S+)", read("deploy", "container", "Containerfile"), re.M)
    assert m, "Containerfile has no USER"
    user = m.group(1).split(":")[0]
    return int(user) if user.isdigit() else user


class SystemdUnit(unittest.TestCase):
    def setUp(self):
        self.unit = Unit()
        self.config = json.loads(read("deploy", "systemd", "vsmd.json"))

    def test_hardening(self):
        expected = {
            "User": "vsm", "ProtectSystem": "strict", "ReadWritePaths": "/var/lib/vsm",
            "StateDirectory": "vsm", "ProtectHome": "yes", "PrivateTmp": "yes",
            "NoNewPrivileges": "yes", "CapabilityBoundingSet": "",
            "RestrictAddressFamilies": "AF_INET AF_INET6 AF_UNIX",
            "SystemCallFilter": "@system-service", "LimitNOFILE": "65536",
            "Restart": "on-failure",
        }
        for key, value in expected.items():
            self.assertIn(key, self.unit.directives, "vsmd.service has no %s=" % key)
            self.assertEqual(self.unit.directives[key][0], value, "vsmd.service %s=" % key)
        self.assertNotIn("DynamicUser", self.unit.directives, "the data must persist: User=vsm")
        self.assertNotIn("ExecReload", self.unit.directives, "vsmd has no reload")
        self.assertEqual(self.config["data_root"], "/var/lib/vsm",
                         "vsmd.json data_root is not the unit's ReadWritePaths")
        sysusers = read("deploy", "systemd", "vsm.sysusers.conf")
        m = re.search(r"^u\s+vsm\s+(\d+)", sysusers, re.M)
        self.assertIsNotNone(m, "vsm.sysusers.conf creates no user vsm with a fixed uid")
        self.assertEqual(int(m.group(1)), containerfile_uid(),
                         "the vsm uid differs from the container's (one shared data root)")

    def test_stop_timeout_above_shutdown_grace(self):
        grace = seconds(self.config.get("limits", {}).get("shutdown_grace", "10s"))
        timeout = seconds(self.unit.value("TimeoutStopSec"))
        self.assertGreater(timeout, grace, "TimeoutStopSec %ss <= limits.shutdown_grace %ss"
                           % (timeout, grace))

    def test_config_and_token_file(self):
        exec_start = shlex.split(self.unit.value("ExecStart"))
        self.assertEqual(arg_value(exec_start, "--config"), "/etc/vsm/vsmd.json")
        token_file = arg_value(exec_start, "--token-file")
        self.assertIsNotNone(token_file, "ExecStart has no --token-file")
        if token_file.startswith("${CREDENTIALS_DIRECTORY}/"):
            name = token_file.split("/", 1)[1]
            credentials = [v.split(":", 1)[0] for v in self.unit.directives.get(
                "LoadCredential", [])]
            self.assertIn(name, credentials, "--token-file %s without LoadCredential=%s:..."
                          % (token_file, name))

    def test_systemd_analyze_verify(self):
        analyze = shutil.which("systemd-analyze")
        if analyze is None:
            print("skipped: systemd-analyze verify (no systemd-analyze on PATH)", file=sys.stderr)
            return
        binary = shlex.split(self.unit.value("ExecStart"))[0]
        with tempfile.TemporaryDirectory() as tmp:
            # verify needs ExecStart's binary to exist: the built one stands in for it.
            unit = os.path.join(tmp, "vsmd.service")
            with open(unit, "w") as f:
                f.write(self.unit.text.replace(binary, os.path.abspath(ARGS.vsmd)))
            result = subprocess.run([analyze, "verify", unit], capture_output=True, text=True,
                                    timeout=120)
        # Unknown keys and bad values are only warnings (exit 0): any line about the unit fails.
        complaints = [l for l in (result.stdout + result.stderr).splitlines()
                      if "vsmd.service" in l]
        self.assertEqual(result.returncode, 0, "systemd-analyze verify failed:\n" + result.stderr)
        self.assertEqual(complaints, [], "systemd-analyze verify complains:\n"
                         + "\n".join(complaints))


class ConfigAndFlags(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.help = vsmd_help()
        cls.flags = help_flags(cls.help)
        cls.keys = help_keys(cls.help)
        assert "--listen" in cls.flags and "data_root" in cls.keys, (
            "could not read flags and keys from vsmd --help:\n" + cls.help)

    def configs(self):
        return {"deploy/k8s ConfigMap vsm-config": K8s().config_text(),
                "deploy/systemd/vsmd.json": read("deploy", "systemd", "vsmd.json")}

    def test_config_keys_are_listed_by_help(self):
        for name, text in self.configs().items():
            unknown = set(flatten(json.loads(text))) - self.keys
            self.assertEqual(unknown, set(), "%s: keys vsmd --help does not list" % name)

    def test_vsmd_starts_with_each_config(self):
        with tempfile.TemporaryDirectory() as tmp:
            for name, text in self.configs().items():
                config = os.path.join(tmp, "vsmd.json")
                with open(config, "w") as f:
                    f.write(text)
                with Daemon("--config", config) as vsmd:
                    self.assertEqual(vsmd.get_until_200("/readyz"), 200,
                                     "vsmd with %s never became ready" % name)

    def test_vsmd_rejects_an_unknown_key(self):
        # Otherwise starting with a config file would prove nothing about its keys.
        with tempfile.TemporaryDirectory() as tmp:
            config = os.path.join(tmp, "vsmd.json")
            with open(config, "w") as f:
                json.dump({"limits": {"no_such_key": 1}}, f)
            result = subprocess.run([ARGS.vsmd, "--config", config, "--listen", "127.0.0.1:0",
                                     "--data-root", tmp], capture_output=True, text=True,
                                    timeout=30)
            self.assertNotEqual(result.returncode, 0, "vsmd accepted an unknown config key")
            self.assertIn("no_such_key", result.stderr)

    def test_flags_are_listed_by_help(self):
        used = {}
        k8s = K8s()
        used["deploy/k8s StatefulSet vsm"] = flags_of(k8s.vsmd_container().get("args", []))
        for i, line in enumerate(Unit().exec_starts()):
            used["deploy/systemd/vsmd.service ExecStart %d" % i] = flags_of(shlex.split(line))
        container = read("deploy", "container", "Containerfile")
        for directive in ("ENTRYPOINT", "CMD"):
            m = re.search(r"^%s\s+(\[.*\])\s*$" % directive, container, re.M)
            if m:
                used["Containerfile " + directive] = flags_of(json.loads(m.group(1)))
        for where, flags in used.items():
            self.assertEqual(flags - self.flags, set(), "%s: flags vsmd --help does not list"
                             % where)
        self.assertIn("--coordinator", used["deploy/k8s StatefulSet vsm"])

    def test_nodes_start_with_the_deploy_arguments(self):
        # The StatefulSet's args and the unit's drop-in ExecStart, as written, join a real etcd:
        # only the paths become temporary files ($(POD_NAME) -> vsm-0, the ConfigMap/vsmd.json,
        # the token) and --coordinator the local etcd; listen and data root are overridden.
        etcd_binary = shutil.which("etcd")
        if etcd_binary is None:
            print("skipped: nodes joining etcd (no etcd on PATH)", file=sys.stderr)
            return
        k8s = K8s()
        unit = Unit()
        cases = {"deploy/k8s StatefulSet vsm": (k8s.vsmd_container()["args"], k8s.config_text())}
        clustered = [l for l in unit.exec_starts() if "--coordinator" in l]
        self.assertTrue(clustered, "vsmd.service shows no ExecStart with --coordinator")
        cases["deploy/systemd/vsmd.service drop-in"] = (
            shlex.split(clustered[0])[1:], read("deploy", "systemd", "vsmd.json"))
        with tempfile.TemporaryDirectory() as tmp, Etcd(etcd_binary) as etcd:
            config = os.path.join(tmp, "vsmd.json")
            token = os.path.join(tmp, "token")
            with open(token, "w") as f:
                f.write("deploy-test-token\n")
            os.chmod(token, 0o600)
            for where, (args, config_text) in cases.items():
                with open(config, "w") as f:
                    f.write(config_text)
                replaced = {"--config": config, "--token-file": token, "--coordinator": etcd.url}
                flags = []
                for i, arg in enumerate(args):
                    if i > 0 and args[i - 1] in replaced:
                        arg = replaced[args[i - 1]]
                    flags.append(arg.replace("$(POD_NAME)", "vsm-0")
                                    .replace("$(POD_NAMESPACE)", "vsm"))
                advertise = arg_value(flags, "--advertise")
                self.assertIsNotNone(advertise, "%s: no --advertise" % where)
                with Daemon(*flags) as vsmd:
                    self.assertEqual(vsmd.get_until_200("/readyz"), 200,
                                     "%s: vsmd with a coordinator never became ready" % where)
                    registered = etcd.everything()
                    self.assertIn(advertise, registered, "%s: the node's --advertise URL is not "
                                  "in etcd:\n%s" % (where, registered))


class NginxFront(unittest.TestCase):
    """deploy/nginx/vsm.conf with deploy/nginx/nodes.conf: nginx -t accepts them (node host names
    made 127.0.0.1, paths made temporary, a self-signed certificate); the nodes are the
    StatefulSet's pods on the container port; the body limit is vsmd's."""

    def test_nginx_accepts_the_front(self):
        nginx = shutil.which("nginx") or "/usr/sbin/nginx"
        if not os.path.exists(nginx) or shutil.which("openssl") is None:
            print("skipped: nginx -t (no nginx or openssl)", file=sys.stderr)
            return
        with tempfile.TemporaryDirectory() as tmp:
            nodes = re.sub(r"server\s+[^\s:;]+:(\d+)", r"server 127.0.0.1:\1",
                           read("deploy", "nginx", "nodes.conf"))
            front = (read("deploy", "nginx", "vsm.conf").replace("/etc/nginx/vsm/", tmp + "/")
                     .replace("/var/cache/nginx/vsm", tmp + "/cache"))
            for name, text in (("nodes.conf", nodes), ("vsm.conf", front)):
                with open(os.path.join(tmp, name), "w") as f:
                    f.write(text)
            subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days",
                            "1", "-subj", "/CN=localhost", "-keyout", tmp + "/key.pem", "-out",
                            tmp + "/cert.pem"], check=True, capture_output=True)
            main = os.path.join(tmp, "nginx.conf")
            with open(main, "w") as f:
                f.write("pid %(t)s/nginx.pid;\nerror_log %(t)s/error.log;\nevents {}\n"
                        "http {\n  client_body_temp_path %(t)s/body;\n"
                        "  proxy_temp_path %(t)s/proxy;\n  include %(t)s/nodes.conf;\n"
                        "  include %(t)s/vsm.conf;\n}\n" % {"t": tmp})
            out = subprocess.run([nginx, "-t", "-c", main], capture_output=True, text=True,
                                 timeout=60)
            self.assertEqual(out.returncode, 0, out.stderr)

    def test_the_nodes_are_the_statefulset_pods_on_the_container_port(self):
        k8s = K8s()
        nodes = read("deploy", "nginx", "nodes.conf")
        servers = re.findall(r"^\s*server\s+([^\s:;]+):(\d+)", nodes, re.M)
        statefulset = k8s.vsm()
        expected = ["vsm-%d.%s" % (i, statefulset["spec"]["serviceName"])
                    for i in range(statefulset["spec"]["replicas"])]
        self.assertEqual([host for host, _ in servers], expected)
        port = next(iter(p["containerPort"] for p in k8s.vsmd_container()["ports"]))
        for host, server_port in servers:
            self.assertEqual(int(server_port), port, "%s: not the container port" % host)
        self.assertRegex(nodes, r"hash\s+\$vsm_shard\s+consistent;")
        self.assertRegex(read("deploy", "nginx", "vsm.conf"), r"map\s+\$uri\s+\$vsm_shard\s")

    def test_the_body_limit_is_vsmds(self):
        m = re.search(r"client_max_body_size\s+(\d+)([km]?);", read("deploy", "nginx", "vsm.conf"))
        self.assertIsNotNone(m, "vsm.conf sets no client_max_body_size")
        limit = int(m.group(1)) * {"": 1, "k": 1024, "m": 1024 * 1024}[m.group(2)]
        body_bytes = K8s().config().get("limits", {}).get("body_bytes", "1MiB")
        self.assertEqual(limit, vsm_size(str(body_bytes)))


class Containerfile(unittest.TestCase):
    def test_built_by_the_deploy_scripts(self):
        text = read("deploy", "container", "Containerfile")
        runs = " ".join(re.findall(r"^RUN\s+(.*(?:\\\n.*)*)", text, re.M))
        self.assertRegex(text, r"(?m)^FROM\s+debian:bookworm-slim\b")
        for script in ("deploy/install-deps.sh", "deploy/build.sh"):
            self.assertRegex(runs, r"(^|[\s;&|])%s\b" % re.escape(script),
                             "the Containerfile does not RUN %s (it would drift)" % script)
        uid = containerfile_uid()
        self.assertNotIn(uid, (0, "root"), "the container runs as root")
        exposed = re.search(r"^EXPOSE\s+(\d+)", text, re.M)
        self.assertIsNotNone(exposed, "no EXPOSE")
        m = re.search(r"^CMD\s+(\[.*\])\s*$", text, re.M)
        listen = arg_value(json.loads(m.group(1)), "--listen") if m else None
        if listen:
            self.assertEqual(listen_port(listen), int(exposed.group(1)), "EXPOSE != --listen")
        self.assertIn("python3-yaml", read("deploy", "install-deps.sh"),
                      "install-deps.sh does not install python3-yaml (this test needs it)")


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True, help="the built vsmd")
    parser.add_argument("--source", default=os.path.join(os.path.dirname(
        os.path.abspath(__file__)), "..", ".."), help="the checkout (default: this file's)")
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
