"""The nemesis's checker (nemesis_test.py) over the recorded history and the files: 1 acknowledged
merges kept, 2 one content per version, 3 replicas converge, 4 no read mixes versions, 5 vsm
validate. Revisions are read from the OPC files by check_import.py's reader, none of vsm's code."""

import collections
import json
import os
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cluster_support  # noqa: E402
from check_import import Patch, ecef_to_geodetic, read_hierarchy  # noqa: E402
from nemesis_clients import digest  # noqa: E402
from nemesis_models import BASE_HEIGHT, DETAILS, TARGETS, detail_centre, detail_height  # noqa: E402


LEAF_HEIGHTS = {}  # (opc, folder) -> {detail: (distance in degrees, height)}: folders are shared


def leaf_heights(opc, patches_dir, folder):
    """{detail: (distance, height)} of the vertex of a leaf patch nearest each detail's centre
    (for the centres inside the patch's lon/lat range)."""
    if (opc, folder) not in LEAF_HEIGHTS:
        patch = Patch(patches_dir, folder, None)
        patch.expand(patch.vsm_size or 65)
        g = patch.grid.reshape(-1, 3)
        g = g[~np.isnan(g[:, 0])]
        found = {}
        if len(g):
            lon, lat, h = ecef_to_geodetic(g[:, 0], g[:, 1], g[:, 2])
            for i in range(DETAILS):
                x, y = detail_centre(i)
                if lon.min() <= x <= lon.max() and lat.min() <= y <= lat.max():
                    d = np.hypot(lon - x, lat - y)
                    j = int(np.argmin(d))
                    found[i] = (float(d[j]), float(h[j]))
        LEAF_HEIGHTS[(opc, folder)] = found
    return LEAF_HEIGHTS[(opc, folder)]


def details_in(opc, hierarchy_file):
    """{detail index: True (in), False (not in), or the height found} of one revision of a
    target, from its hierarchy file and leaf patches alone (check_import.py's reader): the height
    of the leaf vertex nearest each detail's centre."""
    patches_dir, root, children = read_hierarchy(opc, hierarchy_file)
    best = {}
    stack = [root]
    seen = set()
    while stack:
        folder = stack.pop()
        if folder in seen:
            raise AssertionError("%s %s: %s twice in the tree" % (opc, hierarchy_file, folder))
        seen.add(folder)
        if children.get(folder):
            stack.extend(children[folder].values())
            continue
        for i, (d, h) in leaf_heights(opc, patches_dir, folder).items():
            if i not in best or d < best[i][0]:
                best[i] = (d, h)
    result = {}
    for i in range(DETAILS):
        h = best.get(i, (None, None))[1]
        if h is not None and abs(h - detail_height(i)) < 1.0:
            result[i] = True
        elif h is not None and abs(h - BASE_HEIGHT) < 1.0:
            result[i] = False
        else:
            result[i] = h
    return result


class Checks:
    def __init__(self):
        self.results = collections.OrderedDict()

    def add(self, name, failures, counted):
        self.results[name] = (failures, counted)
        print("check %-34s %s: %s" % (name, "FAILED" if failures else "ok", counted), flush=True)
        for f in failures[:20]:
            print("    " + f, flush=True)
        if len(failures) > 20:
            print("    ... %d more" % (len(failures) - 20), flush=True)

    def failed(self):
        return [name for name, (failures, _) in self.results.items() if failures]


def converge(cluster, nodes, models, checks, timeout=120):
    """Check 3, and the final versions by model."""
    deadline = time.monotonic() + timeout
    failures = []
    while True:
        failures = []
        finals = {}
        for model in models:
            writer = cluster_support.etcd_value(cluster.etcd, "/vsm/writers/" + model)
            if writer not in nodes:
                failures.append("%s: no writer in etcd (%s)" % (model, writer))
                continue
            answers = {}
            for name, node in nodes.items():
                try:
                    status, _, body = cluster_support.request(
                        node.url + "/v1/models/%s/hierarchy" % model, timeout=10)
                except OSError as e:
                    status, body = None, str(e).encode()
                answers[name] = (status, body)
            status, body = answers[writer]
            if status != 200:
                failures.append("%s: the writer %s answers %s" % (model, writer, status))
                continue
            version = json.loads(body)["version"]
            finals[model] = (writer, version, body)
            for name, (s, b) in answers.items():
                if s != 200 or b != body:
                    failures.append("%s: %s answers %s (version %s), the writer %s version %d%s" % (
                        model, name, s, json.loads(b)["version"] if s == 200 else "-", writer,
                        version, ", other bytes" if s == 200 else ""))
        if not failures or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    checks.add("3 replicas converge", failures,
               "%d models on 3 nodes, versions %s" % (
                   len(models), {m: v for m, (_, v, _) in sorted(finals.items())}))
    return finals


def check_history(history, cluster, nodes, finals, data, checks):
    ops = history.ops
    by_kind = collections.Counter((op["kind"], op.get("result") or op["status"]) for op in ops)
    print("operations: %d" % len(ops), flush=True)
    for (kind, result), n in sorted(by_kind.items(), key=str):
        print("    %-12s %-10s %d" % (kind, result, n), flush=True)

    # 1. Acknowledged merges, and the chain of revisions.
    failures = []
    jobs = {op["job"]: op for op in ops if op.get("job")}
    acked = [op for op in ops if op["kind"] == "merge" and op.get("result") == "succeeded"]
    restored = [op for op in ops if op["kind"] == "restore" and op.get("result") == "succeeded"]
    revisions_seen = 0
    indeterminate = 0
    published_unsure = 0
    for target in TARGETS:
        status, _, body = cluster_support.request(
            nodes[finals[target][0]].url + "/v1/models/%s/revisions" % target
            if target in finals else cluster.front + "/v1/models/%s/revisions" % target)
        if status != 200:
            failures.append("%s: revisions answer %s" % (target, status))
            continue
        revisions = json.loads(body)["revisions"]
        revisions_seen += len(revisions)
        by_number = {r["revision"]: r for r in revisions}
        made_by = collections.Counter(r["job"] for r in revisions if r["job"])
        # A write the front answered with an error or not at all (the node killed or paused
        # meanwhile) may have been taken: its job id is unknown, and so may be one revision.
        unsure = [op for op in ops if op["kind"] in ("merge", "restore") and op["model"] == target
                  and op.get("result") == "refused" and (op["status"] is None or op["status"] >= 500)]
        unknown = 0
        for job, n in made_by.items():
            if n > 1:
                failures.append("%s: job %s made %d revisions" % (target, job, n))
            if job not in jobs:
                unknown += 1
                if unknown > len(unsure):
                    failures.append("%s: revision by job %s, which no client submitted" % (
                        target, job))
            elif jobs[job].get("result") in ("failed", "cancelled"):
                message = (jobs[job].get("error") or {}).get("message", "")
                if jobs[job]["result"] == "failed" and " is published, but " in message:
                    # vsmd's own answer for a commit that took whose directory sync then failed
                    # (ENOSPC/EIO after the rename): published, its durability unknown, and
                    # said so. Not acknowledged, so not a lost write either way.
                    published_unsure += 1
                else:
                    failures.append("%s: job %s %s (%s), but its revision is published" % (
                        target, job, jobs[job]["result"], message[:100]))
        indeterminate += unknown
        opc = os.path.join(data, target)
        latest = max(by_number)
        expected = {}
        for number in sorted(by_number):
            r = by_number[number]
            if r["parent"] is None:
                want = set()
            elif r["restored_from"] is not None:
                want = expected.get(r["restored_from"])
            else:
                job = jobs.get(r["job"])
                parent = expected.get(r["parent"])
                want = None if job is None or parent is None or job["kind"] != "merge" else \
                    parent | {int(job["source"][1:])}
            if r["parent"] is not None and r["job"] is None:
                failures.append("%s: revision %d was made by no job" % (target, number))
            if r["parent"] is not None and r["parent"] != number - 1:
                failures.append("%s: revision %d has parent %s" % (target, number, r["parent"]))
            name = "patchhierarchy.xml" if number == latest else "vsm-revision-%d.xml" % number
            found = details_in(opc, name)
            have = {i for i, v in found.items() if v is True}
            odd = {i: v for i, v in found.items() if v not in (True, False)}
            if odd:
                failures.append("%s revision %d: heights at details' centres that are neither "
                                "the detail's nor the target's: %s" % (target, number, odd))
            if want is not None and have != want:
                failures.append("%s revision %d (%s): details %s, the chain says %s" % (
                    target, number, r["job"], sorted(have), sorted(want)))
            expected[number] = have if want is None else want
        for op in acked + restored:
            if op["model"] != target:
                continue
            r = by_number.get(op["version"])
            if r is None or r["job"] != op["job"]:
                failures.append("%s: job %s (%s %s) succeeded with version %s, but that revision "
                                "is %s" % (target, op["job"], op["kind"],
                                           op.get("source", op.get("revision")), op["version"], r))
            elif op["kind"] == "merge" and int(op["source"][1:]) not in expected[op["version"]]:
                failures.append("%s: job %s merged %s into version %s, which lacks it" % (
                    target, op["job"], op["source"], op["version"]))
        if finals.get(target) and finals[target][1] != latest:
            failures.append("%s: the writer serves version %d, the latest revision is %d" % (
                target, finals[target][1], latest))
    versions = collections.Counter((op["model"], op["version"]) for op in acked + restored)
    for (model, version), n in versions.items():
        if n > 1:
            failures.append("%s: %d acknowledged jobs name version %d" % (model, n, version))
    ended = collections.Counter("%s %s: %s" % (op["kind"], op["result"], (op.get("error") or {}).get(
        "message", "")[:90]) for op in ops if op.get("result") in ("failed", "cancelled"))
    for line, n in sorted(ended.items()):
        print("    %3d x %s" % (n, line), flush=True)
    checks.add("1 acknowledged merges kept", failures,
               "%d merges acknowledged, %d restores, %d revisions checked (%d by a job whose "
               "submission the front answered with an error or not at all, %d by a job that "
               "failed saying its version is published but not known durable)" % (
                   len(acked), len(restored), revisions_seen, indeterminate, published_unsure))

    # 2. One content per version.
    failures = []
    contents = collections.defaultdict(set)  # (what, model, version[, key]) -> digests
    for op in ops:
        if op["status"] != 200 or "digest" not in op:
            continue
        if op["kind"] == "hierarchy":
            contents[("hierarchy", op["model"], op["version"])].add(op["digest"])
        elif op["kind"] == "hierarchy_v":
            contents[("hierarchy", op["model"], op["want"])].add(op["digest"])
        elif op["kind"] == "tileset":
            contents[("tileset", op["model"], op["version"])].add(op["digest"])
        elif op["kind"] == "glb" and op["patch_version"] == str(op["want"]):
            contents[("glb", op["model"], op["want"], op["key"])].add(op["digest"])
        elif op["kind"] == "positions" and op["patch_version"] is not None:
            contents[("positions", op["model"], int(op["patch_version"]), op["key"])].add(
                op["digest"])
    finals_read = 0
    for target in TARGETS:
        status, _, body = cluster_support.request(cluster.front + "/v1/models/%s/revisions"
                                                  % target)
        for r in json.loads(body)["revisions"] if status == 200 else []:
            for name, node in nodes.items():
                s, _, b = cluster_support.request(node.url + "/v1/models/%s/hierarchy?rev=%d"
                                                  % (target, r["revision"]))
                if s == 200:
                    contents[("hierarchy", target, r["revision"])].add(digest(b))
                    finals_read += 1
                else:
                    failures.append("%s: %s answers %d to hierarchy?rev=%d" % (
                        target, name, s, r["revision"]))
    for what, digests in sorted(contents.items(), key=str):
        if len(digests) > 1:
            failures.append("%s: %d different bodies %s" % (what, len(digests), sorted(digests)))
    checks.add("2 one content per version", failures,
               "%d (document, model, version) seen, %d of them at the end from each node" % (
                   len(contents), finals_read))

    # 4. No read returned a mix of versions.
    failures = []
    counted = collections.Counter()
    for op in ops:
        if op["kind"] == "glb":
            counted["glb %s" % op["status"]] += 1
            if op["status"] == 200 and op["patch_version"] != str(op["want"]):
                failures.append("%s: patch version %s for ?v=%s (tileset of version %s)" % (
                    op["path"], op["patch_version"], op["want"], op["tileset_version"]))
        elif op["kind"] == "positions":
            counted["positions %s" % op["status"]] += 1
            # From any snapshot holding the patch as version N holds it: the patch's version
            # as the hierarchy of N says, a snapshot of N or later (proto/openapi.yaml, `v`).
            if op["status"] == 200 and (op["patch_version"] != str(op["want_patch"]) or
                                        int(op["model_version"]) < op["want"]):
                failures.append("%s: model version %s patch version %s, the hierarchy of "
                                "version %s said patch version %s" % (
                                    op["path"], op["model_version"], op["patch_version"],
                                    op["want"], op["want_patch"]))
        elif op["kind"] == "hierarchy_v":
            counted["hierarchy?v= %s" % op["status"]] += 1
            if op["status"] == 200 and op["version"] != op["want"]:
                failures.append("%s: the hierarchy of version %s" % (op["path"], op["version"]))
        elif op["kind"] == "tileset" and op["status"] == 200:
            counted["tileset 200"] += 1
            if op["model_version"] != str(op["version"]):
                failures.append("%s: X-VSM-Model-Version %s, the document says %s" % (
                    op["path"], op["model_version"], op["version"]))
    checks.add("4 no read mixes versions", failures, dict(sorted(counted.items())))


def validate(vsm, data, models, checks):
    """Check 5: every model validates (the cluster stopped: the files as they stay)."""
    failures = []
    for model in models:
        out = subprocess.run([vsm, "validate", os.path.join(data, model)],
                             capture_output=True, text=True, timeout=300)
        if out.returncode != 0:
            failures.append("%s: %s" % (model, (out.stdout + out.stderr).strip()[-300:]))
    checks.add("5 vsm validate", failures, "%d models" % len(models))
