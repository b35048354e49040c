"""The CPU of the per-cycle serialisation of the robotics outputs alone, on two (or more) source
trees, alternating round by round in one run (issue 24): the record's JSON as the Zenoh
publisher puts it (``records.dumpb``; a tree without it: ``records.dumps(r).encode()``, what its
publisher did) and a cycle's Foxglove messages (``mcap_out.encode``: the taxel maps and the JSON
topics, a fresh ``TopicMap`` a pass, so its caches fill as in a run).

    .venv/bin/python bench/records_encode.py --tree before=/tmp/base --tree after=. [--rounds 5]
        [--scenes matrix57 skin4096 grasp_lift] [--traces DIR]

Per scene a demo records a CAN trace once (``fusion-center demo --log``, this tree; or
``DIR/<scene>.log`` when it exists). Each round runs, for every tree in turn, a child process
with that tree first on ``sys.path`` (this interpreter) that replays the trace with the tree's
own code, then measures thread CPU (``time.thread_time``) per record: **hot**, every record
back to back (three passes, the fastest), and **cold**, every fourth record alone after a
10 ms sleep, as the centre calls it after the idle gap between cycles. Printed per round and,
at the end, the medians over rounds and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

CHILD = r'''
import json, sys, time
sys.path.insert(0, sys.argv[1])
from taxel_net.scene import load_scene
from fusion_center.service import replay_trace
from fusion_center.service import records
from fusion_center.robotics.mcap_out import encode
from fusion_center.robotics.topics import TopicMap
import fusion_center

assert fusion_center.__file__.startswith(sys.argv[1]), fusion_center.__file__
scene = load_scene(sys.argv[2])
recs = replay_trace(scene, sys.argv[3])[0]
dumpb = getattr(records, "dumpb", None) or (lambda r, _d=records.dumps: _d(r).encode())
out = {"bytes": sum(len(dumpb(r)) for r in recs) / len(recs)}

def measure(make):
    hot = []
    for _ in range(3):
        f = make()
        t0 = time.thread_time()
        for r in recs:
            f(r)
        hot.append((time.thread_time() - t0) / len(recs))
    f = make()
    cold = 0.0
    picked = recs[::4]
    for k, r in enumerate(recs):
        if k % 4:
            f(r)  # the caches fill as in a run
            continue
        time.sleep(0.01)
        t0 = time.thread_time()
        f(r)
        cold += time.thread_time() - t0
    return min(hot) * 1e6, cold / len(picked) * 1e6

out["record_hot_us"], out["record_cold_us"] = measure(lambda: dumpb)
out["messages_hot_us"], out["messages_cold_us"] = measure(lambda: (lambda r, _t=TopicMap(scene): encode(_t, r)))
print(json.dumps(out))
'''


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", required=True, help="LABEL=PATH (repeatable)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--cycles", type=int, default=200)
    ap.add_argument("--scenes", nargs="+", default=["matrix57", "skin4096", "grasp_lift"])
    ap.add_argument("--traces", type=Path, default=None, help="a directory of SCENE.log traces to use")
    args = ap.parse_args()
    trees = [(label, Path(path).resolve()) for label, path in (t.split("=", 1) for t in args.tree)]
    tmp = Path(tempfile.mkdtemp(prefix="records_encode_"))
    traces = {}
    for scene in args.scenes:
        given = args.traces / f"{scene}.log" if args.traces else None
        if given is not None and given.exists():
            traces[scene] = given
            continue
        traces[scene] = tmp / f"{scene}.log"
        subprocess.run([str(Path(sys.executable).parent / "fusion-center"), "demo", "--scene", scene, "--cycles",
                        str(args.cycles), "--log", str(traces[scene]), "--no-live"], cwd=ROOT, check=True,
                       capture_output=True)
    print(f"load average {os.getloadavg()[0]:.1f}", flush=True)
    runs: dict[tuple, list] = {}
    keys = ("record_hot_us", "record_cold_us", "messages_hot_us", "messages_cold_us")
    for k in range(args.rounds):
        for scene in args.scenes:
            for label, root in trees:
                done = subprocess.run([sys.executable, "-c", CHILD, str(root), scene, str(traces[scene])],
                                      capture_output=True, text=True, cwd=root, env={**os.environ, "PYTHONPATH": ""})
                if done.returncode:
                    raise SystemExit(f"{label} {scene}: {done.stderr[-2000:]}")
                r = json.loads(done.stdout.splitlines()[-1])
                runs.setdefault((scene, label), []).append(r)
                print(f"  round {k + 1} {scene} {label}: record {r['bytes']:.0f} B, hot {r['record_hot_us']:.1f} / "
                      f"cold {r['record_cold_us']:.1f} us; messages hot {r['messages_hot_us']:.1f} / cold "
                      f"{r['messages_cold_us']:.1f} us (load {os.getloadavg()[0]:.1f})", flush=True)
    print(f"medians of {args.rounds} rounds, us of thread CPU a record (load average now {os.getloadavg()[0]:.1f}):")
    print(f"  {'scene':10s} {'tree':8s} " + " ".join(f"{key:>17s}" for key in keys))
    for (scene, label), rs in runs.items():
        print(f"  {scene:10s} {label:8s} " + " ".join(f"{statistics.median(r[key] for r in rs):17.1f}" for key in keys))
    return 0


if __name__ == "__main__":
    sys.exit(main())
