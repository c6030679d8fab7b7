#!/usr/bin/python3
"""No lost write under concurrency (issue 32): a randomized fault run of a three-node cluster.

    /usr/bin/python3 nemesis_test.py --vsm <vsm> --vsmd <vsmd> --lib <libvsm_fault_inject.so>
                                     --work <dir> --repo <source tree>
                                     [--seconds S] [--seed N] [--lanes L]

S (default 60, or VSM_NEMESIS_SECONDS; 600 is the long mode) is how long the nemesis acts; the
seed (VSM_NEMESIS_SEED, else random) is printed, and given again it replays the same choices:
the same faults in the same order with the same parameters per lane, the same operations per
client thread (what happens between threads still depends on timing). L (default 2,
VSM_NEMESIS_LANES) lanes of faults act side by side.

The cluster is deploy/local-cluster.sh's (cluster_support.LocalCluster): real etcd, three vsmd
nodes over one data root (lease TTL 5 s, --keep-revisions 10000 so that every revision stays
readable to the checker), real nginx in front. Each node is then restarted by the test behind a
TCP proxy of its own to etcd (nemesis_cluster.EtcdProxy) and with tests/fault's LD_PRELOAD library, so that
the nemesis can cut one node off etcd and hold its reads.

Models (synthetic, GDAL): three targets t0, t1, t2 (the same flat surface at 100 m, 257 x 257
samples of 2^-12 degrees, patches of 65) and twelve details d0..d11 (33 x 33 samples at a quarter
of that spacing, each in its own place inside the targets and flat at 1000 + 100 i m). A merge of
di into a target is seen in any revision by reading the height at di's centre: 1000 + 100 i when
di is in, 100 when not (read from the OPC files by check_import.py's reader, none of vsm's code).

Clients through the front (nginx), every operation recorded with its start and end, result,
version seen and body digest:
- two writers: merge jobs (a random detail into a random target) and restores of a random kept
  revision (1 in 6), each job followed until it ends or is lost with its node;
- three readers: a tileset.json and three of its GLBs (each by its `?v=`), the hierarchy, the
  hierarchy again by `?v=` its version, and the positions of three of its patches by `?v=`.

The nemesis, in each lane one fault after another at random (a pause of 0.2 to 1.5 s between),
until the time is up:
- kill_writer, kill_replica: kill -9 of the node writing a random model (or of one that does
  not), restarted after 0 to 2 s;
- disk_fault: the fault library of a writer armed (VSM_FAULT_ARM, a file the test writes): its
  next call of a random class (create, write, rename, sync, mkdir, unlink) fails with ENOSPC or
  EIO, or the next open for reading (`read`) of any node with EIO; disarmed after 5 s if no such
  call came;
- pause_etcd, pause_node: SIGSTOP for 1 to 10 s (twice the TTL), then SIGCONT;
- cut_etcd: one node's proxy to etcd cut for 1 to 10 s, either reset (connections closed and
  refused) or a black hole (connections kept, nothing goes through), while the others reach it;
- slow_reads: a replica's reads held for 0.5 to 3 s: the fault library's gate on its `read`
  class (every open for reading under the data root waits while the gate file says 0), released
  by the nemesis's timer.
A node that exits by itself is restarted and counted (not a check).

Then everything is healed (proxies open, processes continued, gates removed), the clients stop,
the test waits until no job is queued or running, and checks:
1. acknowledged merges: every merge job that ended succeeded is the revision its result names
   (the revision list records the job) and that revision has the detail; every revision's
   details are what the chain of revisions says (a merge adds its detail to its parent's, a
   restore has the restored revision's), the final model's included; no revision was made by a
   job no client submitted (beyond the submissions the front answered with an error or not at
   all), or by a job that ended failed or cancelled; no job made two, and no two acknowledged
   jobs name one version;
2. one content per version: every hierarchy read as version N (unversioned through the front,
   by ?v=N through the front, and by ?rev=N from each node at the end) has the same bytes; every
   tileset of model version N the same bytes; every GLB and positions of one patch version the
   same bytes;
3. convergence: every node serves, for every model, the version etcd's writer serves, with the
   same hierarchy bytes;
4. no mix: a GLB read by a tileset's `?v=K` answers patch version K, positions read by `?v=N`
   (N the version of the hierarchy that listed the patch) the patch version that hierarchy says,
   from a snapshot of N or later (X-VSM-Patch-Version, X-VSM-Model-Version), or not at all; a
   hierarchy by ?v=N says N; a tileset's X-VSM-Model-Version is its document's model_version;
5. `vsm validate` passes for every model.
The counts are printed: operations by kind and result, faults by kind (and injected disk faults
that fired), each check. Exit 1 when a check fails.

One concern a module: nemesis_models.py the synthetic models, nemesis_cluster.py the cluster (the
proxies to etcd, the nodes, the wait for idle jobs), nemesis_clients.py the clients and the
history, nemesis_faults.py the nemesis, nemesis_check.py the checks; this file runs them in order.
"""

import argparse
import collections
import json
import os
import shutil
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
import nemesis_check  # noqa: E402
import nemesis_cluster  # noqa: E402
from nemesis_clients import Clients, History  # noqa: E402
from nemesis_faults import Nemesis  # noqa: E402
from nemesis_models import DETAILS, TARGETS, make_models  # noqa: E402


def main():
    parser = argparse.ArgumentParser()
    for name in ("--vsm", "--vsmd", "--lib", "--work", "--repo"):
        parser.add_argument(name, required=True)
    parser.add_argument("--seconds", type=float,
                        default=float(os.environ.get("VSM_NEMESIS_SECONDS", "60")))
    parser.add_argument("--lanes", type=int, default=int(os.environ.get("VSM_NEMESIS_LANES", "2")),
                        help="faults acting at once at most (each lane one after the other)")
    parser.add_argument("--seed", type=int, default=int(os.environ.get(
        "VSM_NEMESIS_SEED", str(int.from_bytes(os.urandom(4), "little")))))
    args = parser.parse_args()
    harness.configure(args)
    print("nemesis: seed %d, %g s, %d lanes (replay: --seed %d or VSM_NEMESIS_SEED=%d)" % (
        args.seed, args.seconds, args.lanes, args.seed, args.seed), flush=True)
    directory = os.path.abspath(args.work)
    shutil.rmtree(directory, ignore_errors=True)
    data = os.path.join(directory, "data")
    os.makedirs(data)
    os.makedirs(os.path.join(directory, "gates"))
    make_models(data, directory)
    cluster = nemesis_cluster.start(args, directory)
    proxies = []
    nodes = {}
    history = History()
    stop = threading.Event()
    clients = None
    try:
        cluster.up()
        etcd_pid = int(cluster.values["PID_ETCD"])
        nemesis_cluster.behind_proxies(cluster, directory, args.lib, nodes, proxies)
        print("nodes behind their proxies to etcd: %s" % {n: p.proxy.url for n, p in nodes.items()},
              flush=True)

        nemesis = Nemesis(history, args.seed, nodes, etcd_pid, cluster.etcd, directory)
        history.lane = nemesis.lane
        clients = Clients(history, args.seed, stop, cluster.front)
        history.restart_clock()
        clients.start()
        started = time.monotonic()
        try:
            nemesis.run(args.seconds, args.lanes)
        finally:
            nemesis.heal()
        print("nemesis over after %.1f s; healed" % (time.monotonic() - started), flush=True)
        stop.set()
        clients.join()
        for node in nodes.values():
            if not node.ready():
                raise AssertionError(node.name + " is not ready after the heal")
        if not nemesis_cluster.quiesce(nodes):
            raise AssertionError("jobs still queued or running 180 s after the clients stopped")

        faults = collections.Counter(f["kind"] for f in history.faults)
        fired = []
        for node in nodes.values():
            if os.path.exists(node.reports):
                with open(node.reports) as f:
                    fired += [line.strip() for line in f if line.strip()]
        print("faults: %d %s; injected disk faults that fired: %d %s; nodes that exited by "
              "themselves: %s" % (sum(faults.values()), dict(sorted(faults.items())), len(fired),
                                  fired, nemesis.exits), flush=True)

        checks = nemesis_check.Checks()
        models = TARGETS + ["d%d" % i for i in range(DETAILS)]
        finals = nemesis_check.converge(cluster, nodes, models, checks)
        nemesis_check.check_history(history, cluster, nodes, finals, data, checks)
    finally:
        stop.set()
        with open(os.path.join(directory, "history.json"), "w") as f:
            json.dump({"seed": args.seed, "ops": history.ops, "faults": history.faults}, f)
        nemesis_cluster.shut_down(cluster, nodes, proxies)

    # 5. Every model validates (the cluster stopped: the files as they stay).
    nemesis_check.validate(args.vsm, data, models, checks)

    failed = checks.failed()
    print("nemesis: seed %d, %d operations, %d faults, checks %s" % (
        args.seed, len(history.ops), len(history.faults),
        "all passed" if not failed else "FAILED: " + ", ".join(failed)), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
