"""``fusion-center plot`` of a grasp run (issue 23): a decision log whose records carry ``grip``.

Three panels against time since the first SYNC (the records' ``t``):

1. forces per jaw: the centre's command (``grip.command_n``; < 0 opens), the drive's actual force
   (``grip.actual_n``, 0x2101), and where the world's truth is known (``grasp_truth``: demo, replay
   with ``--truth-log``) the least holding force ``min_hold_n`` and the normal force on the object;
   the task's phases shaded, every change of the drive's CiA 402 state marked (a vertical line
   and its name);
2. the slid distance (``grasp_truth.slid_mm``) and where the object was dropped;
3. slip: the centre's own detection (``grip.slip``) against the world's true slip
   (``grasp_truth.slipping``) and the presence decision, one row each, a mark per cycle.

Without ``grasp_truth`` the truth's curves and rows are left out (and the figure says so).
"""

from __future__ import annotations

import math

PHASE_COLOURS = {"approach": "0.92", "close": "#e8f0ff", "lift": "#fff1dd", "hold": "#eaf7ea",
                 "place": "#fff1dd", "release": "#f7e8f7", "done": "0.96"}


def collect(record: dict, series: dict) -> None:
    """Add one record's grasp quantities to ``series["grasp"]`` (created on the first)."""
    grip = record.get("grip")
    if not isinstance(grip, dict):
        return
    g = series.setdefault("grasp", {k: [] for k in ("t", "command", "actual", "state", "slip", "present",
                                                   "phase", "min_hold", "normal", "slid", "true_slip",
                                                   "dropped")})
    truth = record.get("grasp_truth") if isinstance(record.get("grasp_truth"), dict) else {}
    g["t"].append(_num(record.get("t")))
    g["command"].append(_num(grip.get("command_n")))
    g["actual"].append(_num(grip.get("actual_n")))
    g["state"].append(grip.get("drive_state"))
    g["slip"].append(bool(grip.get("slip")))
    g["present"].append(record.get("decision"))
    g["phase"].append(truth.get("phase"))
    g["min_hold"].append(_num(truth.get("min_hold_n")))
    g["normal"].append(_num(truth.get("normal_n")))
    g["slid"].append(_num(truth.get("slid_mm")))
    g["true_slip"].append(truth.get("slipping"))
    g["dropped"].append(truth.get("dropped"))


def _num(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan


def _spans(values, t):
    """(start, end, value) runs of equal consecutive values (a None carries the value before it)."""
    filled, last = [], None
    for v in values:
        last = v if v is not None else last
        filled.append(last)
    values = filled
    out, start = [], None
    for k, v in enumerate(values):
        if k == 0 or v != values[k - 1]:
            if start is not None and values[start] is not None:
                out.append((t[start], t[k], values[start]))
            start = k
    if start is not None and values[start] is not None:
        out.append((t[start], t[-1], values[start]))
    return out


def draw(series: dict, title: str, out) -> None:
    import numpy as np

    from ..report.plots import _save, plt

    g = series["grasp"]
    t = np.asarray(g["t"], dtype=float)
    t = t - np.nanmin(t)
    has_truth = any(p is not None for p in g["phase"])
    fig, axes = plt.subplots(3, 1, figsize=(10, 8.5), sharex=True, gridspec_kw={"height_ratios": [3, 1.4, 1.3]})
    for ax in axes:
        for start, end, phase in _spans(g["phase"], t):
            ax.axvspan(start, end, color=PHASE_COLOURS.get(phase, "0.95"), lw=0, zorder=0)
    ax = axes[0]
    ax.step(t, g["command"], where="post", color="tab:blue", lw=1.3, label="commanded (centre)")
    ax.plot(t, g["actual"], color="tab:orange", lw=1.0, label="actual (drive 0x2101)")
    if has_truth:
        ax.plot(t, g["min_hold"], "--", color="tab:red", lw=1.0, label="least holding force (world, eq 26b)")
        ax.plot(t, g["normal"], ":", color="tab:green", lw=1.0, label="normal force on the object (world)")
    ax.axhline(0, color="0.5", lw=0.5)
    states = g["state"]
    changes = [k for k in range(len(states)) if states[k] is not None and (k == 0 or states[k] != states[k - 1])]
    labels: list[list] = []  # [time, text]: changes closer than 3 % of the run share one label
    gap = 0.03 * (t[-1] - t[0] if len(t) > 1 else 1.0)
    for k in changes:
        ax.axvline(t[k], color="tab:purple", lw=0.8, alpha=0.7)
        if labels and t[k] - labels[-1][0] < gap:
            labels[-1][1] += f" > {states[k]}"
        else:
            labels.append([t[k], f"{states[k]}"])
    for x, text in labels:
        ax.text(x, 0.98, " " + text.replace(" > ", "\n> "), va="top", ha="left", fontsize=6, color="tab:purple",
                transform=ax.get_xaxis_transform())
    ax.set_ylabel("force per jaw (N)")
    for start, end, phase in _spans(g["phase"], t):
        ax.text((start + end) / 2, 0.02, phase, ha="center", va="bottom", fontsize=7, color="0.35",
                transform=ax.get_xaxis_transform())
    ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=2, fontsize=7, frameon=False)

    ax = axes[1]
    if has_truth:
        ax.plot(t, g["slid"], color="tab:brown", lw=1.2, label="slid distance (world), down positive")
        dropped = [k for k, d in enumerate(g["dropped"]) if d]
        if dropped:
            ax.axvline(t[dropped[0]], color="tab:red", lw=1.5, label="dropped")
        ax.legend(loc="upper left", fontsize=7, frameon=False)
    else:
        ax.text(0.5, 0.5, "no grasp_truth in the log (demo, or replay --truth-log, carries it)",
                transform=ax.transAxes, ha="center", va="center", color="tab:gray")
    ax.set_ylabel("slid (mm)")

    ax = axes[2]
    rows = [("centre: slip", np.asarray(g["slip"], dtype=bool), "tab:orange")]
    if has_truth:
        rows.append(("world: slipping", np.asarray([bool(s) for s in g["true_slip"]]), "tab:red"))
    rows.append(("decision H1", np.asarray([p == "H1" for p in g["present"]]), "tab:green"))
    for y, (label, on, colour) in enumerate(rows):
        ax.plot(t[on], np.full(int(on.sum()), y), ls="none", marker="|", ms=9, color=colour)
    ax.set_yticks(range(len(rows)), [f"{label} ({int(on.sum())})" for label, on, _ in rows], fontsize=7)
    ax.set_ylim(-0.6, len(rows) - 0.4)
    ax.set_xlabel("time since the first SYNC (s)")
    fig.suptitle(title + ("" if has_truth else " - no world truth"), fontsize=11)
    _save(fig, out)
