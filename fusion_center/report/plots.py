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
_LOG_FLOOR = 1e-300  # exact values are drawn down to here (log axes); below: a "< 1e-300" marker


def _exact_y(value):
    """(y to draw, below the floor?) of an exact value on a log axis."""
    return (_LOG_FLOOR, True) if value is None or value < _LOG_FLOOR else (value, False)


def _log_axis_floor(ax, values, mc_floor=None) -> None:
    """Bottom of a log y axis at a third of the smallest positive value drawn (exact values
    included, down to 1e-300), so nothing sits on an unlabelled clip."""
    low = min([v for v in values if v is not None and v > 0] + ([mc_floor] if mc_floor else []) + [1.0])
    ax.set_ylim(bottom=max(low / 3.0, _LOG_FLOOR / 3.0))


def error_vs_runtime(points: list[dict], floor: float, path, bitrates=None) -> None:
    """Total error (Monte Carlo with 95 % CI; the exact value of every rule as a hollow diamond,
    drawn where it is, down to 1e-300, and as a down triangle at 1e-300 when below) against bus
    time per cycle (one marker shape per bit rate, the same rule joined by a dotted line) and
    against CPU time per decision, one colour per rule / test. A Monte Carlo estimate of 0 (no
    error event in its trials) is drawn on the labelled floor line 1/(2 trials)."""
    from matplotlib.lines import Line2D

    bitrates = [str(b) for b in (bitrates or [])]
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), sharey=True)
    drawn = []

    def draw(ax, p, xs, markers):
        err = p["total_error"]
        est, lo, hi = (max(v, floor) for v in (err["estimate"], *err["ci95"]))
        c = _COLOURS.get(p["rule"], "tab:cyan")
        if len(xs) > 1:
            ax.plot(xs, [est] * len(xs), ":", color=c, lw=0.8)
        exact = err.get("exact")
        for x, marker in zip(xs, markers):
            ax.errorbar([x], [est], yerr=[[est - lo], [hi - est]], fmt=marker, color=c, capsize=3, ms=6)
            if exact is not None:
                y, below = _exact_y(exact)
                ax.plot([x], [y], marker="v" if below else "D", mfc="none", color=c, ms=10, mew=1.5)
                drawn.append(y)
            if err["estimate"] == 0.0:
                ax.annotate("MC: no event", (x, est), fontsize=7, xytext=(5, -11), textcoords="offset points",
                            color=c)
        drawn.extend([est, lo])

    ax = axes[0]
    for p in points:
        by = p.get("bus_time_per_cycle_ms_by_bitrate") or {}
        xs = [by[b] for b in bitrates if b in by] or [p["bus_time_per_cycle_ms"]]
        draw(ax, p, xs, [_BITRATE_MARKERS[j % len(_BITRATE_MARKERS)] for j in range(len(xs))])
    handles = [Line2D([], [], marker=_BITRATE_MARKERS[j % len(_BITRATE_MARKERS)], ls="none", color="k",
                      label=f"{int(b) // 1000} kbit/s") for j, b in enumerate(bitrates)] if len(bitrates) > 1 else []
    handles += [Line2D([], [], marker="D", mfc="none", ls="none", color="k", ms=9, label="exact"),
                Line2D([], [], ls=":", color="k", lw=0.8, label=f"MC floor 1/(2 trials) = {floor:.1g}")]
    if any(p["total_error"].get("exact") is not None and p["total_error"]["exact"] < _LOG_FLOOR for p in points):
        handles.append(Line2D([], [], marker="v", mfc="none", ls="none", color="k", ms=9, label="exact < 1e-300"))
    ax.legend(handles=handles, fontsize=8, loc="best")
    ax.set_xlabel("bus time per SYNC cycle [ms]" + (" (decision_sync / raw)" if bitrates else ""))
    ax = axes[1]
    for p in points:
        draw(ax, p, [p["cpu_time_per_decision_us"]], ["o"])
    rule_handles = [Line2D([], [], marker="o", ls="none", color=_COLOURS.get(p["rule"], "tab:cyan"),
                           label=f"{p['rule']} ({p['mode']})") for p in points]
    ax.legend(handles=rule_handles, fontsize=7, loc="best")
    ax.set_xlabel("CPU time per decision [µs]")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, which="major", alpha=0.3)
        ax.axhline(floor, ls=":", color="k", lw=0.8)
    _log_axis_floor(axes[0], drawn, floor)
    axes[0].set_ylabel("total error vs ground truth (o MC with 95 % CI, ◇ exact)")
    fig.suptitle("detection error vs run time (decision mode vs centralised raw-data test)")
    _save(fig, path)


def _dense_exact_roc(r, per_segment: int = 24):
    """An exact ROC (atoms: thresholds from the top) densified for log axes: between two
    attainable thresholds the randomised test moves on the straight line in (P_F, P_D), which
    is sampled at P_F spaced evenly in log. Returns log10 P_F, P_D and log10 P_M arrays (exact
    in the log domain; None entries of the atoms = probability 0 are dropped)."""
    ln10 = math.log(10.0)
    lpf = [None if v is None else v * ln10 for v in r["log10_pf"]]
    lpm = r.get("log10_pm") or [None] * len(lpf)
    lpm = [None if v is None else v * ln10 for v in lpm]
    pd = list(r["pd"])
    out_f, out_d, out_m = [], [], []
    for j in range(len(lpf)):
        if lpf[j] is None:
            continue
        if out_f and j > 0 and lpf[j - 1] is not None and lpf[j] > lpf[j - 1]:
            a_f, b_f = lpf[j - 1], lpf[j]
            a_m = lpm[j - 1] if lpm[j - 1] is not None else -math.inf
            b_m = lpm[j] if lpm[j] is not None else -math.inf
            for k in range(1, per_segment):
                f = a_f + (b_f - a_f) * k / per_segment  # ln P_F, evenly spaced
                # t = (P_F - P_F(a)) / (P_F(b) - P_F(a)), formed without overflow or cancellation
                t = math.exp(a_f - b_f) * math.expm1(f - a_f) / -math.expm1(a_f - b_f)
                t = min(max(t, 1e-300), 1.0 - 1e-16)
                out_f.append(f)
                out_d.append(pd[j - 1] + t * (pd[j] - pd[j - 1]))
                out_m.append(np.logaddexp(math.log1p(-t) + a_m, math.log(t) + b_m))
        out_f.append(lpf[j])
        out_d.append(pd[j])
        out_m.append(lpm[j] if lpm[j] is not None else (math.log1p(-pd[j]) if pd[j] < 1.0 else -math.inf))
    return np.array(out_f) / ln10, np.array(out_d), np.array(out_m) / ln10


def _auc(auc: float) -> str:
    return f"1 - {1.0 - auc:.2g}" if 0.9999 < auc < 1.0 else f"{auc:.6f}"


def _dense_linear(pf: np.ndarray, pd: np.ndarray, per_segment: int = 24):
    """Points (P_F ascending, > 0) joined by straight lines in (P_F, P_D), sampled at P_F evenly
    spaced in log: (log10 P_F, P_D)."""
    out_f, out_d = [], []
    for j in range(pf.size):
        if j and pf[j] > pf[j - 1]:
            a, b = math.log10(pf[j - 1]), math.log10(pf[j])
            f = np.linspace(a, b, per_segment + 1)[1:-1]
            t = (10.0**f - pf[j - 1]) / (pf[j] - pf[j - 1])
            out_f.extend(f)
            out_d.extend(pd[j - 1] + t * (pd[j] - pd[j - 1]))
        out_f.append(math.log10(pf[j]))
        out_d.append(pd[j])
    return np.array(out_f), np.array(out_d)


def roc_curves(roc: dict, operating: dict, path, trials: int | None = None) -> None:
    """ROC, two panels. Left, the range the Monte Carlo can see (P_F down to a hundredth of its
    floor 1/(2 trials)): the exact curves (solid) of the count rules, the preferential U_G and
    the eq 31/32 statistic beside the Monte Carlo curves (dashed, the cross-check), each with its
    AUC; a Monte Carlo P_F of 0 sits on the labelled floor line. Right, the exact curves over
    their whole range as P_M = 1 - P_D against P_F, both on log axes down to the smallest exact
    value (1e-300 at most). Between two attainable thresholds an exact curve is the randomised
    test's straight line in (P_F, P_D). Operating points of the configured rules: o Monte
    Carlo, ◇ exact (▽ at 1e-300: an exact P_F below it)."""
    from matplotlib.lines import Line2D

    fig, axes = plt.subplots(1, 2, figsize=(14, 6.4))
    mc_floor = 0.5 / trials if trials else 1e-7
    low_f = low_m = 1e-3
    handles = []
    beyond: dict = {}
    for name, r in roc.items():
        exact = name.endswith("_exact") or name == "count_exact"
        rule = "count rules, K >= m" if name == "count_exact" else (name[:-6] if name.endswith("_exact") else name)
        colour = "tab:blue" if name == "count_exact" else _COLOURS.get(rule, "tab:cyan")
        if exact and r.get("log10_pf"):
            lf, pd, lm = _dense_exact_roc(r)
            lf_draw = np.maximum(lf, -300.0)
            style = dict(ls="-", lw=1.8, color=colour)
            axes[0].plot(10.0**lf_draw, pd, **style)
            ok = np.isfinite(lm)
            axes[1].plot(10.0 ** lf_draw[ok], 10.0 ** np.maximum(lm[ok], -300.0), **style)
            if lf.size:
                low_f = min(low_f, 10.0 ** float(lf_draw.min()))
            if ok.any():
                low_m = min(low_m, 10.0 ** max(float(lm[ok].min()), -300.0))
            label = f"{rule}: exact, AUC {_auc(r['auc'])}"
        else:
            pf = np.asarray(r["pf"], float)
            pd = np.asarray(r["pd"], float)
            style = dict(ls="--", lw=1.2, color=colour)
            # the same straight lines between thresholds as the exact curves; a P_F of 0 on the floor
            order = np.lexsort((pd, pf))
            lf, dense_pd = _dense_linear(np.maximum(pf[order], mc_floor), pd[order])
            axes[0].plot(10.0**lf, dense_pd, **style)
            axes[0].plot(np.maximum(pf, mc_floor), pd, ".", color=colour, ms=4)
            label = f"{rule}: Monte Carlo, AUC {_auc(r['auc'])}"
        handles.append(Line2D([], [], label=label, **style))
    for name, point in operating.items():
        pf, pd = point[0], point[1]
        exact = point[2] if len(point) > 2 else None
        if pd is None:
            continue
        colour = _COLOURS.get(name, "tab:cyan")
        axes[0].plot([pf if pf > 0 else mc_floor], [pd], "o", color=colour, ms=8, mec="k")
        if 0.0 < pf and pd < 1.0:
            axes[1].plot([pf], [1.0 - pd], "o", color=colour, ms=8, mec="k")
        if exact is not None and exact[0] is not None and exact[1] is not None:
            epf, below = _exact_y(exact[0])
            low_f = min(low_f, epf)
            marker = "v" if below else "D"
            axes[0].plot([epf], [exact[1]], marker, mfc="none", color=colour, ms=11, mew=1.5)
            pm = 1.0 - exact[1]
            if pm > 0.0:
                low_m = min(low_m, pm)
                axes[1].plot([epf], [pm], marker, mfc="none", color=colour, ms=11, mew=1.5)
                if epf < mc_floor:  # beyond the Monte Carlo's reach: say which rule and where
                    key = (f"{epf:.2g}", f"{pm:.2g}")
                    beyond.setdefault(key, [epf, pm, below, []])[3].append(name)
    for j, (epf, pm, below, rules_here) in enumerate(sorted(beyond.values(), key=lambda v: v[0])):
        right = math.log10(epf) > 0.2 * math.log10(max(low_f / 10.0, _LOG_FLOOR / 10.0))  # near the right edge
        axes[1].annotate(f"{', '.join(rules_here)}\nP_F {'< 1e-300' if below else f'{epf:.2g}'}", (epf, pm),
                         fontsize=7, xytext=(-8 if right else 7, -22 - 22 * (j % 2)), textcoords="offset points",
                         ha="right" if right else "left")
    handles += [Line2D([], [], marker="o", ls="none", color="gray", mec="k", ms=8, label="operating point, Monte Carlo"),
                Line2D([], [], marker="D", ls="none", mfc="none", color="gray", ms=9, label="operating point, exact"),
                Line2D([], [], ls=":", color="k", lw=0.8,
                       label=f"MC floor 1/(2 trials) = {mc_floor:.1g}: no false alarm seen" if trials else "P_F = 0")]
    axes[0].axvline(mc_floor, ls=":", color="k", lw=0.8)
    axes[0].set_xlim(mc_floor / 100.0, 1.5)
    axes[0].set_ylim(-0.02, 1.02)
    axes[0].set_ylabel("P_D (system detection)")
    axes[0].set_title("where the Monte Carlo can see: exact and Monte Carlo", fontsize=10)
    axes[1].set_xlim(max(low_f / 10.0, _LOG_FLOOR / 10.0), 1.5)
    axes[1].set_ylim(max(low_m / 10.0, _LOG_FLOOR / 10.0), 1.5)
    axes[1].set_yscale("log")
    axes[1].set_ylabel("P_M = 1 - P_D (system miss)")
    axes[1].set_title("exact curves over their whole range (log-log)", fontsize=10)
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("P_F (system false alarm)")
        ax.grid(True, which="major", alpha=0.3)
    fig.legend(handles=handles, fontsize=7, loc="lower center", ncol=3, frameon=False)
    fig.suptitle("ROC: exact (solid) and Monte Carlo (dashed) curves; operating points of the configured rules")
    fig.tight_layout(rect=(0, 0.06 + 0.025 * math.ceil(len(handles) / 3), 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def achieved_vs_requested(data: dict, path) -> None:
    """Achieved P_F vs requested alpha (additive, preferential, N-P, centralised) and achieved
    P_M vs requested beta (multiplicative). Exact values are drawn where they are (log axis down
    to the smallest, 1e-300 at most, a down triangle below it); a Monte Carlo 0 on a labelled
    floor."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    ax = axes[0]
    grid = np.logspace(-4, 0, 50)
    ax.plot(grid, grid, "k:", label="achieved = requested")
    values = []
    mc_zero = False
    for name, d in data.items():
        if name == "multiplicative":
            continue
        ach = np.asarray(d["achieved"], float)
        log10 = d.get("log10_achieved")
        if log10:
            ach = np.array([10.0 ** max(v, -300.0) if v is not None else _LOG_FLOOR for v in log10])
        mc = d["source"].startswith("MC")
        if mc and np.any(ach == 0.0):
            mc_zero = True
        shown = np.where(ach > 0, np.maximum(ach, _LOG_FLOOR), np.nan)
        values.extend(shown[np.isfinite(shown)].tolist())
        ax.plot(d["requested"], shown, "o-", color=_COLOURS.get(name, "tab:cyan"), label=f"{name} ({d['source']})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    _log_axis_floor(ax, values)
    if mc_zero:
        ax.annotate("Monte Carlo saw no false alarm: not drawn", (0.02, 0.02), xycoords="axes fraction", fontsize=7)
    ax.set_xlabel("requested alpha (HEBTEM eqs 17-18) / false-alarm rate (N-P, centralised)")
    ax.set_ylabel("achieved system P_F")
    ax.grid(True, which="major", alpha=0.3)
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
        seen: dict = {}
        for r in pts:  # labels of points at one place stacked, not overprinted
            y = max(r["relative_error"], 1e-18)
            key = (round(math.log10(r["time_us"]), 1), round(math.log10(y), 1))
            k = seen[key] = seen.get(key, -1) + 1
            ax.annotate(f"n={r['n']}", (r["time_us"], y), fontsize=7, xytext=(4, 2 + 9 * k), textcoords="offset points")
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


def taxel_map(xy: np.ndarray, active: np.ndarray, hull: np.ndarray | None, title: str, path,
              node_ids=None, unit: str = "scene units") -> None:
    """Taxel layout with each taxel's node-ID, the active taxels (u_i = +1) and their convex hull
    (eq 35). Taxels sharing one location (two per R-cell strut on the matrix sensor) are drawn
    side by side, so every taxel is visible."""
    n = xy.shape[0]
    ids = list(node_ids) if node_ids is not None else list(range(1, n + 1))
    span = float(np.nanmax(xy) - np.nanmin(xy)) if n else 1.0
    offset = 0.018 * (span or 1.0)
    draw = xy.astype(float).copy()
    sites: dict = {}
    for i, (x, y) in enumerate(xy):
        sites.setdefault((float(x), float(y)), []).append(i)
    shared = 0
    for members in sites.values():
        if len(members) > 1:
            shared += 1
            for j, i in enumerate(members):
                draw[i, 0] += (j - (len(members) - 1) / 2) * 2 * offset
    fig, ax = plt.subplots(figsize=(7.5, 8.2))
    ax.scatter(draw[~active, 0], draw[~active, 1], s=36, facecolors="none", edgecolors="gray", label="absent (u_i = -1)")
    ax.scatter(draw[active, 0], draw[active, 1], s=56, color="tab:red", label="present (u_i = +1)", zorder=3)
    if hull is not None and len(hull) >= 2:
        closed = np.vstack([hull, hull[:1]])
        ax.plot(closed[:, 0], closed[:, 1], "-", color="tab:red", lw=1.5, label="convex hull (eq 35)")
    for i in range(n):
        ax.annotate(str(ids[i]), (draw[i, 0], draw[i, 1]), fontsize=7, xytext=(0, 5), textcoords="offset points",
                    ha="center", color="tab:red" if active[i] else "dimgray")
    if shared:
        ax.plot([], [], " ", label=f"{shared} sites with two taxels: drawn side by side")
    ax.set_aspect("equal")
    ax.margins(0.06)
    ax.set_xlabel(f"x [{unit}]")
    ax.set_ylabel(f"y [{unit}]")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=2, frameon=False)
    ax.set_title(title + "; labels: node-IDs", fontsize=10)
    _save(fig, path)


_LAYOUT_STYLE = {"per-taxel decision": ("tab:blue", "o"), "per-taxel raw": ("tab:cyan", "s"),
                 "patch decision": ("tab:red", "^"), "patch raw": ("tab:orange", "D")}


def bits_vs_taxels(data: dict, path, bitrates=None) -> None:
    """Bits per SYNC cycle against the number of taxels (log-log) of every layout, mean (line)
    and worst case (band), summed over the channels each layout needs; CAN FD in nominal bit
    times (``scaling.layout_bits_vs_taxels``). Horizontal lines: the bits one bus carries in one
    SYNC period at each bit rate, and 8 buses at the first."""
    fig, ax = plt.subplots(figsize=(11, 7))
    period_ms = data["sync_period_ms"]
    f0 = data["nominal_bitrate"]
    for key, curve in data["curves"].items():
        kind = ("per-taxel" if curve["taxels_per_node"] == 1 else "patch") + (
            " decision" if curve["payload"] == "decision" else " raw")
        colour, marker = _LAYOUT_STYLE[kind]
        pts = curve["points"]
        x = [p["taxels"] for p in pts]
        y = [p["nominal_bit_times"] for p in pts]
        yw = [p["nominal_bit_times_worst"] for p in pts]
        ls = "--" if curve["fd"] else "-"
        ax.plot(x, y, ls, marker=marker, color=colour, ms=4, mfc="none" if curve["fd"] else colour,
                label=f"{key}" + (f" ({pts[-1]['channels']} ch at {x[-1]})" if pts[-1]["channels"] > 1 else ""))
        ax.fill_between(x, y, yw, color=colour, alpha=0.12, lw=0)
    rates = sorted({int(b) for b in (bitrates or [f0])} | {int(f0)})
    for j, b in enumerate(rates):
        cap = b * period_ms / 1000.0
        ax.axhline(cap, color="k", ls=":", lw=1.0)
        ax.annotate(f"1 bus @ {b // 1000} kbit/s: {cap:,.0f} bits / {period_ms:g} ms", (16, cap),
                    xytext=(2, 2), textcoords="offset points", fontsize=7)
    cap8 = 8 * f0 * period_ms / 1000.0
    ax.axhline(cap8, color="k", ls="-.", lw=1.0)
    ax.annotate(f"8 buses @ {int(f0) // 1000} kbit/s: {cap8:,.0f} bits", (16, cap8), xytext=(2, 2),
                textcoords="offset points", fontsize=7)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("taxels")
    ax.set_ylabel(f"bits per SYNC cycle, all channels (FD: nominal bit times at {int(f0) // 1000} kbit/s)")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", ncol=2)
    fd_rate = data["data_bitrate"]
    fig.suptitle("bus cost per SYNC cycle against skin size, exact (line: mean over uniform payloads; band: up to "
                 "the worst case)")
    fig.text(0.01, 0.005, _wrap(f"Solid: classic CAN; dashed: CAN FD {int(f0) // 1000}k/{fd_rate / 1e6:g}M, drawn as bus time "
             f"x {int(f0) // 1000} kbit/s (nominal bits + data-phase bits x {f0 / 1e6:g}/{fd_rate / 1e6:g}) so the "
             "same limit lines hold. Bits summed over the channels a layout needs (<= 127 nodes each): "
             "a curve above '1 bus' fits k buses if it is below k x that line (one channel must carry its share). "
             "SYNC per channel included, heartbeats not. Patch = packed in patch nodes; raw = 8-bit readings "
             "unless the legend says otherwise.", 150), fontsize=7, va="bottom")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)


_RULE_LABEL = {"additive": "additive (HEBTEM eq 17)", "multiplicative": "multiplicative (HEBTEM eq 16)",
               "preferential": "preferential (HEBTEM eq 18)", "k-of-n": "k-of-n", "llr": "Chair-Varshney LLR (eq 31)",
               "np": "N-P (eq 32)"}
_ERROR_FLOOR = 1e-30
_RULE_MARKS = {"additive": ("o", "-", 10), "multiplicative": ("s", "--", 8), "preferential": ("^", "-.", 7),
               "k-of-n": ("D", "-", 5), "llr": ("P", ":", 6), "np": ("X", "-", 5)}


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.fill(part, width) for part in text.split("\n"))


def error_vs_taxels(panels: list[dict], path, scene_n: int | None = None, caption: str = "") -> None:
    """Bayes error at prior 0.5, (P_F + P_M) / 2, of every rule against the number of taxels,
    one panel per H1 model (``scaling.rule_error_vs_taxels``). Exact values; below 1e-30 a down
    triangle on the floor; 0.5 = the rule answers the same whatever the truth. The legend gives
    the first n where a rule's error reaches 0.1."""
    fig, axes = plt.subplots(1, len(panels), figsize=(7.5 * len(panels), 6.2), sharey=True, squeeze=False)
    for ax, panel in zip(axes[0], panels):
        for rule, rec in panel["rules"].items():
            colour = _COLOURS.get(rule, "tab:cyan")
            xs = [n for n, e in zip(rec["taxels"], rec["error"]) if e is not None]
            es = [e for e in rec["error"] if e is not None]
            if not xs:
                continue
            ys = [max(e, _ERROR_FLOOR) for e in es]
            fails = next((n for n, e in zip(xs, es) if e >= 0.1), None)
            label = _RULE_LABEL.get(rule, rule) + (f": error >= 0.1 from n = {fails}" if fails is not None
                                                   else ": error < 0.1 at every n")
            if rec.get("stopped_at") is not None:
                label += f" (computed up to n = {rec['stopped_at']})"
            marker, ls, ms = _RULE_MARKS.get(rule, ("o", "-", 5))
            ax.plot(xs, ys, ls, color=colour, lw=1.3, marker=marker, ms=ms, mfc="none", mew=1.2, label=label)
            below = [(x, y) for x, e, y in zip(xs, es, ys) if e < _ERROR_FLOOR]
            if below:
                ax.plot(*zip(*below), "v", color=colour, ms=7)
        ax.axhline(0.5, color="k", ls=":", lw=1.0)
        ax.annotate("0.5: the same answer whatever the truth (hollow markers of several rules overlap there)",
                    (min(panel["sizes"]), 0.5), xytext=(2, -10), textcoords="offset points", fontsize=7)
        if scene_n is not None:
            ax.axvline(scene_n, color="gray", ls="--", lw=0.8)
            ax.annotate(f"scene: n = {scene_n}", (scene_n, _ERROR_FLOOR * 10), xytext=(3, 0),
                        textcoords="offset points", fontsize=7, color="gray")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_ylim(_ERROR_FLOOR / 3, 2.0)
        ax.set_xlabel("taxels n (identical)")
        ax.set_title(panel["title"], fontsize=9)
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    axes[0][0].set_ylabel("Bayes error at prior 0.5 = (P_F + P_M) / 2, exact (▽: below 1e-30)")
    fig.suptitle("where each fusion rule stops working as the skin grows")
    if caption:
        fig.text(0.01, 0.005, _wrap(caption, 215), fontsize=7, va="bottom")
    fig.tight_layout(rect=(0, 0.08 if caption else 0, 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)
