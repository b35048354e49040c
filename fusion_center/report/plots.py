"""PNG plots of ``fusion-center report`` (matplotlib, Agg backend: no display needed).

Each function takes the JSON-ready data the report computed and a path, draws one figure and
writes it. Plotting only: every number comes from the report's data.
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

_COLOURS = {
    "additive": "tab:blue", "multiplicative": "tab:orange", "preferential": "tab:green",
    "k-of-n": "tab:red", "llr": "tab:purple", "np": "tab:brown",
    "centralised_known": "black", "centralised_glrt": "tab:gray", "centralised_bayes": "tab:olive",
}


def _save(fig, path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


_BITRATE_MARKERS = "os^Dv<>p"
_LOG_FLOOR = 1e-300  # exact values are drawn down to here (log axes)


def error_vs_runtime(points: list[dict], floor: float, path, bitrates=None) -> None:
    """Total error (with 95 % CI, exact value as a hollow diamond) vs bus time per cycle (one
    marker shape per bit rate, the same rule joined by a dotted line) and vs CPU time per
    decision, one colour per rule / test."""
    from matplotlib.lines import Line2D

    bitrates = [str(b) for b in (bitrates or [])]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5), sharey=True)
    ax = axes[0]
    for p in points:
        err = p["total_error"]
        est, lo, hi = (max(v, floor) for v in (err["estimate"], *err["ci95"]))
        c = _COLOURS.get(p["rule"], "tab:cyan")
        by = p.get("bus_time_per_cycle_ms_by_bitrate") or {}
        xs = [by[b] for b in bitrates if b in by] or [p["bus_time_per_cycle_ms"]]
        if len(xs) > 1:
            ax.plot(xs, [est] * len(xs), ":", color=c, lw=0.8)
        for j, x in enumerate(xs):
            ax.errorbar([x], [est], yerr=[[est - lo], [hi - est]], fmt=_BITRATE_MARKERS[j % len(_BITRATE_MARKERS)],
                        color=c, capsize=3)
            if err.get("exact") is not None:
                ax.plot([x], [max(err["exact"], _LOG_FLOOR)], marker="D", mfc="none", color=c, ms=10)
            if err["estimate"] == 0.0:  # Monte Carlo saw no error event: its value is only a bound
                ax.annotate("MC: no event", (x, est), fontsize=6, xytext=(4, 4), textcoords="offset points", color=c)
    if len(bitrates) > 1:
        handles = [Line2D([], [], marker=_BITRATE_MARKERS[j % len(_BITRATE_MARKERS)], ls="none", color="k",
                          label=f"{int(b) // 1000} kbit/s") for j, b in enumerate(bitrates)]
        ax.legend(handles=handles, fontsize=8, loc="best", title="bit rate")
    ax.set_xlabel("bus time per SYNC cycle [ms]" + (" (decision_sync / raw)" if bitrates else ""))
    ax = axes[1]
    for p in points:
        err = p["total_error"]
        est, lo, hi = (max(v, floor) for v in (err["estimate"], *err["ci95"]))
        c = _COLOURS.get(p["rule"], "tab:cyan")
        ax.errorbar([p["cpu_time_per_decision_us"]], [est], yerr=[[est - lo], [hi - est]], fmt="o", color=c,
                    capsize=3, label=f"{p['rule']} ({p['mode']})")
        if err.get("exact") is not None:
            ax.plot([p["cpu_time_per_decision_us"]], [max(err["exact"], _LOG_FLOOR)], marker="D", mfc="none",
                    color=c, ms=10)
    ax.set_xlabel("CPU time per decision [µs]")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("total error vs ground truth (MC, 95 % CI; ◇ exact, every rule)")
    axes[0].axhline(floor, ls=":", color="k", lw=0.8)
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle("detection error vs run time (decision mode vs centralised raw-data test)")
    _save(fig, path)


def roc_curves(roc: dict, operating: dict, path) -> None:
    """ROC curves: exact for the count rules, empirical for the others; rule operating points."""
    fig, ax = plt.subplots(figsize=(7, 6))
    if "count_exact" in roc:
        r = roc["count_exact"]
        ax.plot(np.maximum(r["pf"], 1e-12), r["pd"], "-", color="tab:blue", label="count rules (exact, K >= m)")
    for name, r in roc.items():
        if name == "count_exact":
            continue
        ax.plot(np.maximum(r["pf"], 1e-12), r["pd"], "-", color=_COLOURS.get(name, "tab:cyan"), label=f"{name} (MC)")
    low = 1e-12
    for name, point in operating.items():
        pf, pd = point[0], point[1]
        exact = point[2] if len(point) > 2 else None
        if pd is None:
            continue
        colour = _COLOURS.get(name, "tab:cyan")
        ax.plot([max(pf, 1e-12)], [pd], "o", color=colour, ms=8, mec="k")
        label = name + (" (MC: no false alarm)" if pf == 0.0 else "")
        ax.annotate(label, (max(pf, 1e-12), pd), fontsize=7, xytext=(4, -10), textcoords="offset points")
        if exact is not None and exact[0] is not None and exact[1] is not None:
            epf = max(exact[0], _LOG_FLOOR)
            low = min(low, epf)
            ax.plot([epf], [exact[1]], "D", mfc="none", color=colour, ms=10)  # exact operating point
    ax.set_xscale("log")
    ax.set_xlim(low, 1.0)
    ax.set_xlabel("P_F (system false alarm)")
    ax.set_ylabel("P_D (system detection)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("ROC: operating points of the configured rules (o MC, ◇ exact)")
    _save(fig, path)


def achieved_vs_requested(data: dict, path) -> None:
    """Achieved P_F vs requested alpha (additive, preferential, N-P, centralised) and achieved
    P_M vs requested beta (multiplicative)."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    ax = axes[0]
    grid = np.logspace(-4, 0, 50)
    ax.plot(grid, grid, "k:", label="achieved = requested")
    for name, d in data.items():
        if name == "multiplicative":
            continue
        ach = np.maximum(np.asarray(d["achieved"], float), 1e-16)
        ax.plot(d["requested"], ach, "o-", color=_COLOURS.get(name, "tab:cyan"), label=f"{name} ({d['source']})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("requested alpha (HEBTEM eqs 17-18) / false-alarm rate (N-P, centralised)")
    ax.set_ylabel("achieved system P_F")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    ax = axes[1]
    if "multiplicative" in data:
        d = data["multiplicative"]
        ax.plot(d["requested"], d["achieved"], "o-", color=_COLOURS["multiplicative"], label=f"multiplicative ({d['source']})")
        ax.plot([0, 1], [0, 1], "k:")
        ax.legend(fontsize=7)
    ax.set_xlabel("requested beta (HEBTEM eq 16)")
    ax.set_ylabel("achieved system P_M (miss)")
    ax.grid(True, alpha=0.3)
    fig.suptitle("is the requested error level honoured? (alpha, beta of HEBTEM are curve-fit levels)")
    _save(fig, path)


def work_precision(rows: list[dict], path) -> None:
    """Relative error vs an mpmath reference against time per solve, per solver and n."""
    fig, ax = plt.subplots(figsize=(7, 5))
    solvers = sorted({r["solver"] for r in rows})
    markers = "osD^v"
    for j, s in enumerate(solvers):
        pts = [r for r in rows if r["solver"] == s]
        ax.plot([r["time_us"] for r in pts], [max(r["relative_error"], 1e-18) for r in pts],
                markers[j % len(markers)], label=s, ms=8)
        for r in pts:
            ax.annotate(f"n={r['n']}", (r["time_us"], max(r["relative_error"], 1e-18)), fontsize=7,
                        xytext=(4, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per solve [µs]")
    ax.set_ylabel("relative error vs mpmath (80 digits); 1e-18 = exact")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("threshold solvers: work-precision")
    _save(fig, path)


def probability_curves(curves: dict, path) -> None:
    """The chapter's figs 2-7: P(H1) curves with their HEBTEM thresholds."""
    panels = list(curves.items())
    cols = 3
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 4 * rows))
    axes = np.atleast_1d(axes).ravel()
    for ax, (title, c) in zip(axes, panels):
        for line in c["lines"]:
            ax.plot(line["x"], line["y"], label=line.get("label"))
        for t in c.get("thresholds", []):
            ax.axvline(t["x"], ls="--", color=t.get("color", "r"), lw=1)
            ax.annotate(t["label"], (t["x"], 0.5), rotation=90, fontsize=7, color=t.get("color", "r"))
        for band in c.get("bands", []):
            ax.axvspan(band[0], band[1], color="orange", alpha=0.2)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(c["xlabel"])
        ax.set_ylabel("P(H1)")
        ax.grid(True, alpha=0.3)
        if any(line.get("label") for line in c["lines"]):
            ax.legend(fontsize=6)
    for ax in axes[len(panels):]:
        ax.axis("off")
    _save(fig, path)


def taxel_map(xy: np.ndarray, active: np.ndarray, hull: np.ndarray | None, title: str, path) -> None:
    """Taxel layout, active taxels (u_i = +1) and their convex hull (eq 35)."""
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.scatter(xy[~active, 0], xy[~active, 1], s=30, facecolors="none", edgecolors="gray", label="absent")
    ax.scatter(xy[active, 0], xy[active, 1], s=50, color="tab:red", label="present (u_i = +1)")
    if hull is not None and len(hull) >= 2:
        closed = np.vstack([hull, hull[:1]])
        ax.plot(closed[:, 0], closed[:, 1], "-", color="tab:red", lw=1.5, label="convex hull")
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    _save(fig, path)
