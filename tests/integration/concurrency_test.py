#!/usr/bin/python3
"""No lost write under concurrency (issue 32): the real vsmd on 127.0.0.1:0 over real data (PRISM
and Jacksboro imported by the real `vsm` at --patch-size 65), with the project's fault library
(tests/fault/fault_inject.c) preloaded where a test injects a fault.

    /usr/bin/python3 concurrency_test.py --vsm <vsm> --vsmd <vsmd> --lib <libvsm_fault_inject.so>
        --data <shared/data> --work <dir>

1. A failed merge reopens the model; merges queued behind it still land (finding 1). With one job
   thread, J1 merges a detail into PRISM and fails on ENOSPC at its first draft; J2, queued behind
   it, merges Jacksboro; J3, submitted after J2 ended, merges another detail. Every acknowledged
   merge is in the revision chain: J3's base is J2's version, the revisions list J2's, and every
   folder on disk is one a kept revision names (no orphans); `vsm validate` passes.
2. Jobs on one model run in submission order (not "being changed by another job"): with two job
   threads, two merges into PRISM submitted together both succeed, the second on the first's
   version.
3. A commit rename that reports ENOENT after it was applied (a retransmitted rename over NFS) is
   resolved by looking (finding 5): the job succeeds, and every folder the hierarchy names is on
   disk (today the edit deleted the drafts the committed hierarchy names).
"""

import argparse
import os
import shutil
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from model_states import reachable_folders  # noqa: E402

ARGS = None
TOKEN = "concurrency-test-token"


def import_models(root, details=("jacksboro",)):
    """PRISM as `prism`, Jacksboro under each name of `details` (copies: each merge has its own
    source model)."""
    harness.import_dem(os.path.join(ARGS.data, "PRISMelevation.tif"), os.path.join(root, "prism"),
                       65)
    first = os.path.join(root, details[0])
    harness.import_dem(os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), first, 65)
    for name in details[1:]:
        shutil.copytree(first, os.path.join(root, name))


def fault_env(prefix, work, **fault):
    """The fault library acting under `prefix`, reporting to <work>/faults."""
    return harness.fault_env(ARGS.lib, prefix, report=os.path.join(work, "faults"), **fault)


def folders_of_kept_revisions(opc):
    """Every folder the current hierarchy or a kept revision file names."""
    patches = os.path.join(opc, "Patches")
    named = set()
    for name in os.listdir(patches):
        if name == "patchhierarchy.xml" or (name.startswith("vsm-revision-")
                                            and name.endswith(".xml")):
            named |= reachable_folders(opc, name)
    return named


class Concurrency(unittest.TestCase):
    def setUp(self):
        self.work = os.path.join(ARGS.work, self.id().rsplit(".", 1)[-1])
        shutil.rmtree(self.work, ignore_errors=True)
        self.root = os.path.join(self.work, "root")
        os.makedirs(self.root)
        self.daemon = None

    def tearDown(self):
        if self.daemon is not None:
            log = self.daemon.log()
            code = self.daemon.stop()
            self.assertEqual(code, 0, log[-3000:])

    def start(self, *flags, env=None):
        self.daemon = harness.Daemon("--token", TOKEN, *flags, root=self.root, env=env)

    def post_merge(self, source, target="prism"):
        return self.daemon.submit({"type": "merge", "target": target, "source": source})

    def wait(self, job):
        return self.daemon.wait_job(job["id"], interval=0.05)

    def revisions(self):
        code, _, body = self.daemon.get_json("/v1/models/prism/revisions")
        self.assertEqual(code, 200, body)
        return body["revisions"]

    def assert_model_whole(self):
        opc = os.path.join(self.root, "prism")
        patches = os.path.join(opc, "Patches")
        on_disk = {n for n in os.listdir(patches) if os.path.isdir(os.path.join(patches, n))}
        named = folders_of_kept_revisions(opc)
        self.assertEqual(on_disk - named, set(), "folders no kept revision names (orphans)")
        self.assertEqual(named - on_disk, set(), "folders kept revisions name but that are gone")
        result = harness.vsm("validate", opc)
        self.assertEqual(result.returncode, 0, result.stdout + result.stderr)

    def test_merges_behind_a_failed_one_all_land(self):
        import_models(self.root, ("j1", "jacksboro", "j3"))
        self.start("--set", "threads.jobs=1",
                   env=fault_env(os.path.join(self.root, "prism"), self.work, CLASS="create", N=2,
                                 ERRNO="ENOSPC"))
        j1 = self.post_merge("j1")
        j2 = self.post_merge("jacksboro")
        j1 = self.wait(j1)
        self.assertEqual(j1["state"], "failed", j1)
        with open(os.path.join(self.work, "faults")) as f:
            self.assertIn("ENOSPC", f.read())
        j2 = self.wait(j2)
        self.assertEqual(j2["state"], "succeeded", j2)
        self.assertEqual(j2["result"]["base_version"], 1, j2)
        self.assertEqual(j2["result"]["version"], 2, j2)
        j3 = self.wait(self.post_merge("j3"))
        self.assertEqual(j3["state"], "succeeded", j3)
        self.assertEqual(j3["result"]["base_version"], j2["result"]["version"],
                         "J3 was not made on J2's version: J2's merge is lost")
        listed = self.revisions()
        self.assertEqual([r["revision"] for r in listed], [1, 2, 3])
        self.assertEqual(listed[1]["job"], j2["id"])
        self.assertEqual(listed[2]["job"], j3["id"])
        self.assertEqual(listed[2]["parent"], 2)
        _, _, model = self.daemon.get_json("/v1/models/prism")
        self.assertEqual(model["version"], 3, model)
        self.assert_model_whole()

    def test_merges_into_one_model_run_in_submission_order(self):
        import_models(self.root, ("jacksboro", "j2"))
        self.start("--set", "threads.jobs=2")
        first = self.post_merge("jacksboro")
        second = self.post_merge("j2")
        first, second = self.wait(first), self.wait(second)
        self.assertEqual(first["state"], "succeeded", first)
        self.assertEqual(second["state"], "succeeded", second)
        self.assertEqual(second["result"]["base_version"], first["result"]["version"])
        # In order: the second started no earlier than the first ended.
        self.assertGreaterEqual(second["started_at"], first["finished_at"])
        self.assertEqual([r["job"] for r in self.revisions()[1:]], [first["id"], second["id"]])
        self.assert_model_whole()

    def test_a_commit_rename_reported_failed_but_applied_commits(self):
        import_models(self.root)
        prism = os.path.join(self.root, "prism")
        # Which rename under the model commits the hierarchy: counted in a traced dry run on a
        # copy (the same merge makes the same calls).
        dry = os.path.join(self.work, "dry")
        shutil.copytree(self.root, dry)
        trace = os.path.join(self.work, "trace")
        traced = harness.vsm("merge", os.path.join(dry, "prism"), os.path.join(dry, "jacksboro"),
                             env=fault_env(os.path.join(dry, "prism"), self.work, trace=trace))
        self.assertEqual(traced.returncode, 0, traced.stderr)
        with open(trace) as f:
            commits = [int(line.split()[2]) for line in f
                       if line.split()[1] == "rename" and line.rstrip().endswith(
                           "/Patches/patchhierarchy.xml")]
        self.assertEqual(len(commits), 1, commits)
        self.start(env=fault_env(prism, self.work, CLASS="rename", N=commits[0], ERRNO="ENOENT",
                                 APPLIED=1))
        job = self.wait(self.post_merge("jacksboro"))
        with open(os.path.join(self.work, "faults")) as f:
            self.assertIn("patchhierarchy.xml", f.read(), "the fault did not hit the commit")
        self.assertEqual(job["state"], "succeeded", job)
        self.assertEqual(job["result"]["version"], 2, job)
        self.assertIn("but was applied", self.daemon.log())
        named = reachable_folders(prism)
        missing = [n for n in named if not os.path.isdir(os.path.join(prism, "Patches", n))]
        self.assertEqual(missing, [], "folders the committed hierarchy names were deleted")
        code, _, _ = self.daemon.request("GET", "/v1/models/prism/patches/0_0_0/positions")
        self.assertEqual(code, 200)
        self.assert_model_whole()


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--lib", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], "-v", *rest])
