"""The centre's part of SYNC -> grip command in a loop: a demo trace's frames fed as the live
stream feeds them, per cycle the time from the frame that closes it to the command computed -
this tree side by side with another checkout, and whether both make the same records.

    .venv/bin/python bench/grip_path_cpu.py --trace T.log --scene grasp_lift_patch
                                           [--against OTHER_CHECKOUT] [--rounds 5]

bench/grip_latency.py measures the centre's part on the bus (``centre``: the closing frame's
stamp -> the RPDO1's), which swings with the load of the shared host. This takes the host's
wake-ups away: every frame of the trace goes through the tree's ``EventStream.receive`` (the
assembler, the cycle's close) and every closed cycle through ``CyclePipeline.evaluate_command``
(the stages the command needs, the grip law), then ``finish`` (the rest of the record, not
timed). Timed per cycle (``time.perf_counter``): the closing frame's ``receive`` +
``evaluate_command``. Each tree runs in its own interpreter, alternately, ``--rounds`` times;
printed per tree the best round's p50 and mean (µs) and the SHA-256 of its records' JSON lines
(the same digest: the same records).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

ONE = r'''
import hashlib, json, sys, time
root, trace, scene_name = sys.argv[1:4]
sys.path.insert(0, root)
import numpy as np
from fusion_center.service.cycles import CycleAssembler
from fusion_center.service.pipeline import CyclePipeline
from fusion_center.service.records import jsonable
from fusion_center.service.stream import EventStream
from fusion_center.service.traces import _open_reader, trace_channel
from pathlib import Path
from taxel_net.resources import resolve_scene
from taxel_net.scene import load_scene

scene = load_scene(resolve_scene(scene_name))
msgs = list(_open_reader(Path(trace)))
suffix = Path(trace).suffix.lower()
assembler = CycleAssembler(scene)
closed = []
stream = EventStream(assembler, on_closed=closed.append)
pipeline = CyclePipeline(scene, truth=True)
digest = hashlib.sha256()
times = []
clock = time.perf_counter
for msg in msgs:
    channel = trace_channel(msg, suffix)
    t = clock()
    stream.receive(msg, channel)
    if closed:
        while closed:
            pending = pipeline.evaluate_command(closed.pop(0))
            times.append(clock() - t)
            record = pipeline.finish(pending)
            digest.update(json.dumps(record, default=jsonable).encode() + b"\n")
            t = clock()
print(json.dumps({"p50_us": float(np.median(times)) * 1e6, "mean_us": float(np.mean(times)) * 1e6,
                  "cycles": len(times), "sha256": digest.hexdigest()}))
'''


def run(tree: Path, trace: str, scene: str) -> dict:
    out = subprocess.run([sys.executable, "-c", ONE, str(tree), trace, scene], capture_output=True, text=True,
                         cwd=tree, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trace", required=True, help="a demo / run trace (--log) of the scene")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--against", type=Path, help="another checkout, run alternately with this tree")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args(argv)
    trees = [ROOT] + ([args.against.resolve()] if args.against else [])
    results: dict[Path, list[dict]] = {t: [] for t in trees}
    for _ in range(args.rounds):
        for tree in trees:
            results[tree].append(run(tree, str(Path(args.trace).resolve()), args.scene))
    for tree, rounds in results.items():
        best = min(rounds, key=lambda r: r["p50_us"])
        digests = {r["sha256"] for r in rounds}
        print(f"{str(tree):32s} {args.scene:24s} closing frame -> command, best of {len(rounds)}: p50 "
              f"{best['p50_us']:6.1f} us, mean {best['mean_us']:6.1f} us over {best['cycles']} cycles; "
              f"records sha256 {'/'.join(d[:12] for d in sorted(digests))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
