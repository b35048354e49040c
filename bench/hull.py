"""Convex hull cost: exact monotone chain vs scipy Qhull, and the crossover (SMALL_SET_MAX).

    .venv/bin/python bench/hull.py [--samples 300] [--cold-samples 40]

Measured side by side in one run, per call of ``geometry.convex_hull``:
  1. contact patterns of the 57-taxel matrix (random subsets of 3..57 of the taxel locations
     of scenes/matrix57.toml): ``method="qhull"`` (the former implementation: Qhull on the
     points relative to the first one; the rotation to the lexicographically smallest vertex
     added since costs ~2 us), ``method="exact"`` and ``"auto"``;
  2. the crossover on random float sets and on integer grids (with duplicates), 64..1024 points.

Each figure twice: back to back ("hot") and after a 10 ms idle gap before each call, as the
fusion centre sees between SYNCs ("cold": caches evicted, Python runs several times slower).
On 2 cores shared with other jobs compare the figures of one run, not across runs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from fusion_center.core.geometry import SMALL_SET_MAX, convex_hull  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402

METHODS = ("qhull", "exact", "auto")


def time_calls(sets, method: str, pause_s: float) -> np.ndarray:
    """Microseconds per call (one call per set), with ``pause_s`` idle before each call."""
    out = np.empty(len(sets))
    for i, pts in enumerate(sets):
        if pause_s:
            time.sleep(pause_s)
        t0 = time.perf_counter()
        convex_hull(pts, method)
        out[i] = time.perf_counter() - t0
    return out * 1e6


def row(label: str, sets, cold_sets) -> str:
    cells = []
    for method in METHODS:
        hot = time_calls(sets, method, 0.0)
        cells.append((np.median(hot), np.median(time_calls(cold_sets, method, 0.010))))
    (qh, qc), (eh, ec), (ah, ac) = cells
    return (f"{label:>10s} " + " ".join(f"{h:8.1f} {c:8.1f}" for h, c in cells)
            + f" {qh / eh:8.1f}x {qc / ec:7.1f}x")


def header(first: str) -> str:
    return (f"{first:>10s} " + " ".join(f"{m + ' hot':>8s} {'cold':>8s}" for m in METHODS)
            + f" {'qhull/exact hot':>9s} {'cold':>7s}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=300, help="sets per size (hot)")
    parser.add_argument("--cold-samples", type=int, default=40, help="sets per size after a 10 ms gap")
    args = parser.parse_args()
    rng = np.random.default_rng(2024)

    scene = load_scene(ROOT / "scenes" / "matrix57.toml")
    xy = np.array([[t.x, t.y] for t in scene.taxels], dtype=float)
    # sanity: every path gives the same hull on these sets (exact coordinates of a layout)
    for n in range(3, len(xy) + 1):
        pts = xy[rng.choice(len(xy), n, replace=False)]
        ref = convex_hull(pts, "exact")
        assert np.array_equal(ref, convex_hull(pts, "qhull")) and np.array_equal(ref, convex_hull(pts))

    print(f"convex_hull, median us per call; SMALL_SET_MAX = {SMALL_SET_MAX} (auto = exact up to it)")
    print(f"\n1. contact patterns of matrix57 ({len(xy)} taxel locations, "
          f"{len(np.unique(xy, axis=0))} distinct): n present taxels")
    print(header("n"))
    for n in (3, 4, 6, 8, 12, 16, 24, 32, 45, 57):
        sets = [xy[rng.choice(len(xy), n, replace=False)] for _ in range(args.samples)]
        print(row(str(n), sets, sets[:args.cold_samples]))

    print("\n2. crossover: random floats in [0, 100)^2 (r), 40 x 40 integer grid with repeats (g)")
    print(header("n"))
    for n in (64, 128, 192, 256, 384, 512, 1024):
        samples = max(20, args.samples * 16 // n)
        for kind in ("r", "g"):
            if kind == "r":
                sets = [rng.random((n, 2)) * 100 for _ in range(samples)]
            else:
                sets = [rng.integers(0, 40, (n, 2)).astype(float) for _ in range(samples)]
            print(row(f"{n} {kind}", sets, sets[:min(args.cold_samples, 20)]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
