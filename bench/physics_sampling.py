"""Throughput of node_sim.physics sampling (taxel samples per second), measured side by side.

Run: .venv/bin/python bench/physics_sampling.py
Target for the fusion centre's Monte Carlo report: >= 2e7 taxel samples/s on the rng path.
"""

import time
from pathlib import Path

import numpy as np

from taxel_net.scene import load_scene
from node_sim import physics

ROOT = Path(__file__).resolve().parent.parent


def rate(fn, samples, repeat=3):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return samples / best


def main():
    for name in ("matrix57.toml", "gripper18.toml"):
        s = load_scene(ROOT / "scenes" / name)
        m = 200_000
        cycles = np.arange(m) % s.cycles
        rng = np.random.default_rng(0)
        mc = rate(lambda: physics.sample_readings_batch(s, cycles, rng), m * s.n)
        mc_x = rate(lambda: rng.standard_normal((m, s.n)), m * s.n)
        k = 2_000
        canon = rate(lambda: physics.sample_readings_batch(s, cycles[:k]), k * s.n)
        print(f"{name:16s} Monte Carlo (rng)  {mc:10.3g} samples/s")
        print(f"{name:16s} bare standard_normal {mc_x:10.3g} samples/s  (ratio MC/bare {mc / mc_x:.2f})")
        print(f"{name:16s} canonical per-cycle {canon:10.3g} samples/s  (ratio MC/canonical {mc / canon:.0f})")


if __name__ == "__main__":
    main()
