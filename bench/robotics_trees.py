"""bench/robotics_outputs.py on two (or more) source trees, alternating round by round, in one
run: a before / after comparison of the robotics outputs' cost on a shared host.

    .venv/bin/python bench/robotics_trees.py --tree before=/tmp/base --tree after=. [--rounds 3]
        [--scenes matrix57 skin4096] [--variants "live, 1 viewer" mcap] [--bus]

Each round runs, for every tree in turn, ``TREE/bench/robotics_outputs.py --rounds 1`` (its own
code: the script puts its tree first on ``sys.path``; this interpreter) with ``bare`` and the
variants. Printed per round and at the end (medians over rounds): the process CPU per cycle,
its ratio to ``bare`` of the same pass, and the outputs' threads' CPU (publisher + SDK) per
cycle over ``bare``'s - the figure docs/robotics.md quotes; the load average before and after.
A tree is e.g. ``git archive COMMIT | tar -x -C /tmp/base``.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

LINE = re.compile(r"\s+(.+?)\s+process\s+([\d.]+) us(?: x([\d.]+) of bare.*(?:other threads \+|publisher \+ SDK "
                  r"threads)\s*([-\d.]+) us = \+?([-\d.]+) %)?")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", required=True, help="LABEL=PATH (repeatable)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--cycles", type=int, default=300)
    ap.add_argument("--scenes", nargs="+", default=["matrix57", "skin4096"])
    ap.add_argument("--variants", nargs="+", default=["live, 1 viewer", "mcap"])
    ap.add_argument("--bus", action="store_true", help="matrix57 live on udp_multicast (robotics_outputs.py --bus)")
    args = ap.parse_args()
    trees = [(label, Path(path).resolve()) for label, path in (t.split("=", 1) for t in args.tree)]
    runs: dict[tuple, list] = {}
    print(f"load average {os.getloadavg()[0]:.1f}", flush=True)
    for k in range(args.rounds):
        for label, root in trees:
            out = subprocess.run([sys.executable, str(root / "bench" / "robotics_outputs.py"), "--cycles",
                                  str(args.cycles), "--rounds", "1", "--scenes", *args.scenes, "--variants", "bare",
                                  *args.variants, *(["--bus"] if args.bus else [])], capture_output=True, text=True,
                                 cwd=root).stdout
            scene = None
            for line in out.splitlines():
                if not line.startswith(" "):
                    scene = "matrix57-bus" if args.bus else line.split(":")[0]
                    continue
                m = LINE.match(line)
                if m and m.group(3):
                    runs.setdefault((scene, m.group(1), label), []).append(
                        (float(m.group(2)), float(m.group(3)), float(m.group(4)), float(m.group(5))))
            print(f"  round {k + 1} {label}: " + "; ".join(
                f"{s} {v}: +{r[-1][2]:.0f} us = +{r[-1][3]:.1f} %" for (s, v, lab), r in runs.items() if lab == label)
                + f" (load {os.getloadavg()[0]:.1f})", flush=True)
    print(f"medians of {args.rounds} rounds (load average now {os.getloadavg()[0]:.1f}):")
    for (scene, variant, label), r in sorted(runs.items()):
        med = [statistics.median(x[i] for x in r) for i in range(4)]
        print(f"  {scene:9s} {variant:16s} {label:8s} process {med[0]:7.1f} us x{med[1]:.3f} of bare; outputs' threads "
              f"+{med[2]:6.1f} us = +{med[3]:.1f} % of bare (rounds: {', '.join(f'{x[3]:.1f}' for x in r)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
