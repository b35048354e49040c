"""CPU cost of the 24 patch-node twins' SYNC handling (scenes/skin4096.toml), per cycle, side by
side for two trees.

What one SYNC costs the twins of all 8 channels of the skin4096 scene (4,096 taxels in 24
``node_sim.patch.PatchNode`` of 128-192 taxels, 3 per channel): a ``node_sim.rig.Rig`` on
python-can ``virtual`` buses, every node started (NMT), then each channel's ``_dispatch(0x080,
counter)`` called directly, SYNCs 2 ms apart, 300 cycles, timed in thread CPU time (the
protocol of issue 14's measurement; nothing else listens on the buses). Two figures per tree:

* ``ready``: the readings of the timed cycles computed before (as at the scene's 100 Hz, where
  the rig's read-ahead always has them): the twins' SYNC handling alone;
* ``rig``: the readings as the rig provides them (read-ahead half a SYNC period after a SYNC:
  at one SYNC per ~2.5 ms some cycles compute the physics on the SYNC path).

Each tree runs in its own interpreter, alternately, ``--rounds`` times; the median and the best
of each are printed, and the ratio of the medians.

    .venv/bin/python bench/patch_sync_cost.py [--against OTHER_CHECKOUT] [--rounds 5]

``--against`` takes another checkout of this repository (e.g. ``git worktree add /tmp/before
<commit>``): the 'before'.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PROBE = r'''
import json, sys, time, uuid
root = sys.argv[1]
sys.path.insert(0, root)
import node_sim
from node_sim.rig import Rig
from taxel_net.scene import load_scene
assert node_sim.__file__.startswith(root), node_sim.__file__
scene = load_scene(root + "/scenes/skin4096.toml")
tag = uuid.uuid4().hex[:6]
rig = Rig(scene, "virtual", channel=[f"{name}-{tag}" for name in scene.bus.channels]).start()
time.sleep(0.3)
for ch in rig._channels:
    with ch.lock:
        ch._dispatch(0x000, b"\x01\x00")        # NMT start, every node
def cycle(c):
    for ch in rig._channels:
        with ch.lock:
            ch._dispatch(0x080, bytes([c % 64 + 1]))
def timed(first, n):
    t0 = time.thread_time()
    for c in range(first, first + n):
        cycle(c)
        time.sleep(0.002)
    return (time.thread_time() - t0) / n * 1e3
for c in range(50):
    cycle(c)
    time.sleep(0.01)
out = {"rig": timed(50, 300)}
rig._schedule_prefetch = lambda channel, cycle: None   # no read-ahead: the cache keeps what is computed now
for c in range(350, 650):
    rig._readings(c)
out["ready"] = timed(350, 300)
rig.stop()
print(json.dumps({"tree": node_sim.__file__, "ms": out}))
'''


def measure(tree: Path) -> dict[str, float]:
    res = subprocess.run([sys.executable, "-c", PROBE, str(tree)], capture_output=True, text=True, cwd=tree,
                         timeout=600)
    if res.returncode != 0:
        raise SystemExit(f"{tree}: {res.stderr.strip().splitlines()[-1] if res.stderr else res.returncode}")
    return json.loads(res.stdout)["ms"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", type=Path, help="another checkout to compare with (the 'before')")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args(argv)
    trees = {"this": ROOT} if args.against is None else {"before": args.against.resolve(), "this": ROOT}
    runs: dict[str, dict[str, list[float]]] = {name: {"ready": [], "rig": []} for name in trees}
    for _ in range(args.rounds):
        for name, tree in trees.items():
            for mode, ms in measure(tree).items():
                runs[name][mode].append(ms)
    print(f"ms of thread CPU per cycle, 24 patch nodes on 8 channels (skin4096), 300 SYNCs 2 ms apart, "
          f"{args.rounds} rounds: median (best)")
    for mode in ("ready", "rig"):
        row = "  ".join(f"{name} {statistics.median(runs[name][mode]):.3f} ({min(runs[name][mode]):.3f})"
                        for name in trees)
        ratio = (f"  ratio this/before {statistics.median(runs['this'][mode]) / statistics.median(runs['before'][mode]):.2f}"
                 if "before" in runs else "")
        print(f"readings {mode:>5}: {row}{ratio}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
