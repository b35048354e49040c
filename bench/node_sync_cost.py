"""CPU cost of one node twin's SYNC handling, per node and SYNC, side by side for two trees.

What the rig calls for each node on each SYNC (sample X_i, decide u_i by eqs 1-4, write the
OD, queue the TPDO), for 57 operational nodes, TPDO1 transmission type 1 (synchronous) and 254
(event-driven), timed in thread CPU time (insensitive to other processes on a loaded machine,
unlike ``bench/rig_cycles.py``'s wall-clock cycles/s). Each tree runs in its own interpreter,
alternately, ``--rounds`` times; the best of each is compared.

    .venv/bin/python bench/node_sync_cost.py [--against OTHER_CHECKOUT] [--rounds 4]

``--against`` takes another checkout of this repository (e.g. ``git worktree add /tmp/before
<commit>``) and prints before/after per transmission type and the ratio.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PROBE = r'''
import json, statistics, sys, threading, time
root = sys.argv[1]
sys.path.insert(0, root)
import numpy as np
import node_sim
from node_sim.node import NodeLink, Scheduler, TaxelNode
assert node_sim.__file__.startswith(root), node_sim.__file__
lock = threading.RLock()
sched = Scheduler(lock)
sent = []
link = NodeLink(lambda i, d: sent.append((i, d)), sched, lambda frames: sent.extend(frames))
X = np.random.default_rng(0).normal(5.0, 3.0, size=(2000, 57)).tolist()
out = {}
for tt in (1, 254):
    nodes = []
    for nid in range(1, 58):
        node = TaxelNode(nid, link)
        node.configure({(0x2001, 1): 5.0, (0x2001, 2): 1.0, (0x1017, 0): 0, (0x1800, 2): tt, (0x1800, 3): 0})
        node.power_on()
        node.on_nmt(1)
        nodes.append(node)
    calls = [n.sync.on_sync if hasattr(n, "sync") and hasattr(n.sync, "on_sync") else n.on_sync for n in nodes]
    best = []
    for _ in range(5):
        t0 = time.thread_time()
        with lock:
            for c, row in enumerate(X):
                link.hold()
                for f, x in zip(calls, row):
                    f(c, x, None)
                link.release()
                sent.clear()
        best.append((time.thread_time() - t0) / (len(X) * 57) * 1e6)
    for node in nodes:
        node.shutdown()
    out[tt] = min(best)
sched.stop()
print(json.dumps({"tree": node_sim.__file__, "us": out}))
'''


def measure(tree: Path) -> dict[str, float]:
    res = subprocess.run([sys.executable, "-c", PROBE, str(tree)], capture_output=True, text=True, cwd=tree,
                         timeout=600)
    if res.returncode != 0:
        raise SystemExit(f"{tree}: {res.stderr.strip().splitlines()[-1] if res.stderr else res.returncode}")
    return json.loads(res.stdout)["us"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", type=Path, help="another checkout to compare with (the 'before')")
    ap.add_argument("--rounds", type=int, default=4)
    args = ap.parse_args(argv)
    trees = {"this": ROOT} if args.against is None else {"before": args.against.resolve(), "this": ROOT}
    best: dict[str, dict[str, float]] = {name: {} for name in trees}
    for _ in range(args.rounds):
        for name, tree in trees.items():
            for tt, us in measure(tree).items():
                best[name][tt] = min(best[name].get(tt, float("inf")), us)
    print("us of thread CPU per node and SYNC (57 nodes, best of "
          f"{args.rounds} x 5 x 2000 SYNCs)")
    for tt in ("1", "254"):
        row = "  ".join(f"{name} {best[name][tt]:.3f}" for name in trees)
        ratio = f"  ratio this/before {best['this'][tt] / best['before'][tt]:.3f}" if "before" in best else ""
        print(f"TPDO1 transmission type {tt:>3}: {row}{ratio}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
