"""bench/grasp.py's figure: its table per mode (holding force / least, slid distance, onset ->
detection and onset -> stuck again, drops and crushes) - docs/img/grasp_bench.png."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot(results: list[dict], table: dict, path: Path, title: str, modes: tuple[str, ...], base) -> None:
    """The table as a figure: holding force / least, slid distance, onset -> detection and
    onset -> stuck again, drops and crushes per mode (``modes``: bench/grasp.py's MODES, in order;
    ``base``: its base scene - the pads' length and the SYNC period)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"decision": "tab:blue", "raw": "tab:orange", "fixed 2x": "tab:green", "fixed 26b": "tab:red"}
    fig, ax = plt.subplots(2, 2, figsize=(11, 7.5))
    # (a) steady holding force over the least holding force
    a = ax[0, 0]
    data = [[m["ratio"] for m in (r[mode] for r in results) if m["ratio"] is not None] for mode in modes]
    keep = [i for i, d in enumerate(data) if d]
    a.boxplot([data[i] for i in keep], whis=(5, 95), showfliers=False)
    a.set_xticks(range(1, len(keep) + 1), [modes[i] for i in keep])
    a.axhline(1.0, color="k", lw=0.8)
    a.axhline(1.3, color="tab:purple", ls="--", lw=1, label="goal 1.3x")
    a.axhline(2.0, color="tab:green", ls=":", lw=1, label="vendors' 2x")
    a.set_ylabel("holding force / least holding force")
    a.set_title("steady hold (end of the hold; box 25-75 %, whiskers 5-95 %)", fontsize=9)
    a.legend(fontsize=8)
    # (b) slid distance per grasp
    b = ax[0, 1]
    slid = [[r[mode]["slid_mm"] for r in results] for mode in modes]
    b.boxplot(slid, whis=(5, 95), showfliers=True, flierprops={"markersize": 2})
    b.set_xticks(range(1, len(modes) + 1), modes)
    b.set_ylabel("largest slide before the place, mm")
    grasp = base.grasp
    b.axhline(grasp.slide_down_mm, color="k", ls=":", lw=1, label=f"the contact leaves the pads ({grasp.slide_down_mm:g} mm)")
    b.set_title("slid distance per grasp", fontsize=9)
    b.legend(fontsize=8)
    # (c) onset -> detection and onset -> stuck, ms, centre modes
    c = ax[1, 0]
    dt = base.bus.sync_period_ms
    for mode in ("decision", "raw"):
        eps = [e for r in results for e in r[mode]["episodes"]]
        det = [e["detect_cycles"] * dt for e in eps if e["detect_cycles"] is not None]
        stk = [e["stuck_ms"] for e in eps if e["stuck_ms"] is not None]
        bins = np.arange(0, 260, 10)
        c.hist(det, bins=bins, histtype="step", color=colours[mode], lw=1.5, label=f"{mode}: onset -> detected")
        c.hist(stk, bins=bins, histtype="step", color=colours[mode], ls="--", lw=1.5,
               label=f"{mode}: onset -> stuck again")
    c.axvline(20.4, color="k", lw=0.8)
    c.axvspan(20.4 - 6, 20.4 + 6, color="k", alpha=0.08, label="Ayral et al. 20.4 +- 6 ms")
    c.axvline(50, color="tab:purple", ls="--", lw=1, label="goal: stuck <= 50 ms")
    c.set_xlabel("ms after the world's slip onset")
    c.set_ylabel("slip episodes")
    c.legend(fontsize=7)
    # (d) drops and crushes
    d = ax[1, 1]
    x = np.arange(len(modes))
    drops = [table[m]["dropped"] for m in modes]
    crush = [table[m]["crushed_fragile"] for m in modes]
    d.bar(x - 0.2, drops, 0.4, label="objects lost", color=[colours[m] for m in modes])
    d.bar(x + 0.2, crush, 0.4, label="fragile objects crushed", color=[colours[m] for m in modes], hatch="//",
          alpha=0.6)
    for i, (u, v) in enumerate(zip(drops, crush)):
        d.text(i - 0.2, u, str(u), ha="center", va="bottom", fontsize=8)
        d.text(i + 0.2, v, str(v), ha="center", va="bottom", fontsize=8)
    d.set_xticks(x, modes)
    n = len(results)
    n_frag = table[modes[0]]["fragile"]
    d.set_title(f"of {n} grasps ({n_frag} fragile)", fontsize=9)
    d.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
