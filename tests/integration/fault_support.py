"""The writers the fault tests run (fault_sweep_test, disk_full_test): a scenario's run directory,
`vsm merge` and `vsm import` runs and a merge job through a real vsmd, each reset before a run and
telling its state and commit point. vsm and vsmd are harness.VSM and harness.VSMD
(harness.configure)."""

import json
import os
import shutil
import subprocess

import harness
from harness import Daemon
from model_states import version_of

# The patch size of the fault tests' small models (17 x 17 patches).
PATCH = 17
# A writer's run, and a merge job, end by then (seconds).
TIMEOUT = 120


class Scenario:
    """A writer run under the library, its old and new states, and the checks after each run."""

    def __init__(self, name, work):
        self.name = name
        self.work = os.path.join(work, name)
        self.run_dir = os.path.join(self.work, "run")

    def reset(self):
        if os.path.exists(self.run_dir):
            shutil.rmtree(self.run_dir)
        os.makedirs(self.run_dir)


class CliMerge(Scenario):
    """A merge into a copy of `target`; `indexed`: the copy gets a full index (`vsm index`), which
    the publish adopts as its delta base (a copy's hierarchy has another inode, so the target's
    own index would be stale)."""

    def __init__(self, name, work, target, detail, outside, indexed=False):
        super().__init__(name, work)
        self.target, self.detail, self.outside = target, detail, outside
        self.indexed = indexed
        self.copy = os.path.join(self.run_dir, "target")
        self.old = version_of(target)

    def reset(self):
        super().reset()
        shutil.copytree(self.target, self.copy)
        if self.indexed:
            subprocess.run([harness.VSM, "index", self.copy], check=True,
                           stdout=subprocess.DEVNULL, timeout=60)

    def command(self):
        return [harness.VSM, "merge", self.copy, self.detail]

    def commit_of(self, calls):
        return next(seq for seq, cls, _, path in calls
                    if cls == "rename" and path.endswith("/Patches/patchhierarchy.xml"))

    def state(self):
        return self.copy

    def run(self, env):
        proc = subprocess.run(self.command(), env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, timeout=TIMEOUT)
        return proc.returncode, proc.stderr


class CliImport(CliMerge):
    def __init__(self, name, work, raster, outside):
        Scenario.__init__(self, name, work)
        self.raster, self.outside = raster, outside
        self.copy = os.path.join(self.run_dir, "out")
        self.old = None

    def reset(self):
        Scenario.reset(self)

    def command(self):
        return [harness.VSM, "import", self.raster, self.copy, "--patch-size", str(PATCH)]

    def commit_of(self, calls):
        return next(seq for seq, cls, _, path in calls
                    if cls == "rename" and path == self.copy)


class DaemonMerge(CliMerge):
    def __init__(self, name, work, target, detail, outside, indexed=False):
        super().__init__(name, work, target, detail, outside, indexed)
        self.root = self.run_dir
        self.log = os.path.join(self.work, "vsmd.log")

    def reset(self):
        super().reset()
        shutil.copytree(self.detail, os.path.join(self.root, "detail"))

    def run(self, env, on_ready=None):
        try:
            daemon = Daemon("--token", "sweep", "--log-level", "info", root=self.root, env=env,
                            port_file=os.path.join(self.work, "port"),
                            log_path=self.log, start_deadline=30)
        except AssertionError as e:
            return 99, "vsmd did not start: " + str(e)[-500:]
        try:
            if on_ready:
                on_ready()
            status, _, answer = daemon.json("POST", "/v1/jobs", {"type": "merge", "target": "target",
                                                                "source": "detail"}, timeout=30)
            if status != 202:
                return 1, "job refused: %d %s" % (status, answer)
            try:
                state = daemon.wait_job(answer["id"], timeout=TIMEOUT, interval=0.02)
            except AssertionError as e:
                return 98, "job hangs: %s" % e
            body = json.dumps(state)
            problems = []
            status, _, answer = daemon.request("GET", "/v1/models/target", timeout=30)
            if status != 200:
                problems.append("the model is not served after the job: %d %s"
                                % (status, answer.decode(errors="replace")))
            try:
                rc = daemon.stop(timeout=60)
            except AssertionError:
                return 97, "vsmd hangs on SIGTERM"
            log = daemon.log()
            if rc != 0:
                problems.append("vsmd exited %d on SIGTERM" % rc)
            if state["state"] == "failed":
                message = (state.get("error") or {}).get("message", "")
                if not message:
                    problems.append("the failed job has no message: %s" % body)
                if ("Input/output error" in message or "No space left" in message) and \
                        "read again from disk" not in log:
                    problems.append("the model was not read again from disk after: " + message)
                out = "vsm: error: " + message
                return (1 if not problems else 96), out + "".join("\n" + p for p in problems)
            if state["state"] != "succeeded":
                return 95, body
            warn = "\n".join(line for line in log.splitlines() if " WARN " in line)
            return (0 if not problems else 96), warn + "".join("\n" + p for p in problems)
        finally:
            daemon.kill()
