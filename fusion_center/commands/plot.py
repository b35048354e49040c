"""``fusion-center plot RUN.jsonl [-o OUT.png | --out DIR]``: one figure of a run's decision log.

Four panels over the SYNC cycle, read from the per-cycle records (``--json-lines`` of ``run``,
``demo`` or ``replay``; docs/service.md, *The decision log*) - a grasp run's log (records with
``grip``) gets the figure of :mod:`.plot_grasp` instead (forces, slide, slip, drive states):

1. the decision statistic U_G of the deciding rule (``decide_with``) against its threshold,
   each cycle's decision (H1, H0, undecided) and the cycles where the ground truth is H1;
   a decision that disagrees with the truth is marked;
2. the nodes that did not take part, by state (missing, silent, pre-operational, stopped,
   resetting, unknown: ``nodes_by_state``);
3. late and malformed frames per cycle (``late_frames``, ``bad_frames``);
4. the decision latency on the bus: SYNC to the event that closed each cycle
   (``closed_after_ms``) by how it closed (``closed_by``), its histogram (inset, p50/p99), and
   the time from one SYNC to the next (from ``t``). The evaluation time after the close is the
   run summary's ``latency_ms``.

The figure is written to ``OUT.partial.png`` and renamed when complete: a failed plot leaves
no complete-looking file. An ``OUT`` that is not a regular file (a FIFO, a device) is written
in place, never renamed over nor removed. An ``OUT`` that is the log itself (or its
``OUT.partial.png``) exits 2 in one line (``taxel_net.outputs.check_distinct_paths``). A log that cannot be read (missing, not JSON lines, not decision
records) exits 2 with one line naming the file and the line.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from pathlib import Path

HELP = "plot a run's decision log (RUN.jsonl): U_G vs threshold, decisions vs truth, nodes, late frames, SYNC timing"

STATES = ("missing", "silent", "pre-operational", "stopped", "resetting", "unknown")
STATE_COLOURS = {"missing": "tab:red", "silent": "gold", "pre-operational": "tab:purple", "stopped": "black",
                 "resetting": "tab:pink", "unknown": "tab:gray"}
CLOSED_BY = {"complete": "tab:green", "window": "tab:orange", "sync": "tab:red", "nmt": "tab:gray"}
FORMATS = (".png", ".pdf", ".svg")
MARKERS_MAX = 20_000  # decision markers drawn per kind (a longer log is thinned evenly for them)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="RUN.jsonl", help="decision log written by --json-lines")
    parser.add_argument("-o", "--out", metavar="OUT.png|DIR", default=None,
                        help="figure to write (.png, .pdf or .svg), or a directory for DIR/RUN.png "
                             "(default: RUN.png next to the log)")


def read_log(path: Path) -> dict:
    """The per-cycle series of a decision log, as lists (one entry per record)."""
    from taxel_net.errors import UsageError
    from taxel_net.json_lines import iter_log

    name = str(path)
    if not path.is_file():
        raise UsageError(f"decision log {name!r} not found")
    keys = ("cycle", "t", "U_G", "threshold", "decision", "truth", "closed_by", "closed_after_ms", "late_frames",
            "bad_frames")
    series: dict = {key: [] for key in keys}
    series["states"] = {state: [] for state in STATES}
    series["errors"] = 0
    meta: dict = {}
    for _, record in iter_log(path, check=_not_a_record,
                              not_json="not a JSON record ({why}); expected one JSON object per line "
                                       "(--json-lines of run, demo or replay)"):
        if "error" in record and "decision" not in record:
            series["errors"] += 1  # the service logged a failed evaluation for this cycle
        meta.setdefault("decide_with", record.get("decide_with"))
        meta.setdefault("mode", record.get("mode"))
        meta["n_expected"] = record.get("n_expected", meta.get("n_expected"))
        for key in keys:
            series[key].append(record.get(key))
        if "grip" in record:  # a grasp run (issue 23): its own figure (.plot_grasp)
            from .plot_grasp import collect

            collect(record, series)
        by_state = record.get("nodes_by_state") or {}
        for state in STATES:
            nodes = by_state.get(state)
            if nodes is None and state in ("missing", "silent"):
                nodes = record.get(f"{state}_nodes")
            series["states"][state].append(len(nodes or ()))
    if not series["cycle"]:
        raise UsageError(f"decision log {name!r}: no records (a run writes one JSON line per SYNC cycle)")
    series["meta"] = meta
    return series


def _not_a_record(record) -> str | None:
    """What keeps ``record`` from being plotted (the fields the figures read, by type), None if nothing."""
    if not isinstance(record, dict) or not isinstance(record.get("cycle"), int):
        return "not a decision record (no integer 'cycle'); expected the --json-lines of run, demo or replay"
    t = record.get("t")
    if t is not None and (isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t)):
        return f"t {t!r}: the record's SYNC time must be a finite number (seconds)"
    by_state = record.get("nodes_by_state")
    if by_state is not None and (not isinstance(by_state, dict)
                                 or any(not isinstance(v, list) for v in by_state.values())):
        return f"nodes_by_state {_short(by_state)}: must be an object of lists (state -> nodes)"
    for key in ("missing_nodes", "silent_nodes"):
        if record.get(key) is not None and not isinstance(record[key], list):
            return f"{key} {_short(record[key])}: must be a list of nodes"
    for key in ("grip", "grasp_truth"):
        if record.get(key) is not None and not isinstance(record[key], dict):
            return f"{key} {_short(record[key])}: must be an object"
    truth = record.get("grasp_truth") or {}
    if truth.get("phase") is not None and not isinstance(truth["phase"], str):
        return f"grasp_truth.phase {_short(truth['phase'])}: must be a phase name"
    state = (record.get("grip") or {}).get("drive_state")
    if state is not None and not isinstance(state, str):
        return f"grip.drive_state {_short(state)}: must be a CiA 402 state name"
    return None


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _legend(ax, ncol: int) -> None:
    """The panel's legend above it, outside the data."""
    ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=ncol, fontsize=7, frameon=False,
              borderaxespad=0.2, handlelength=1.5, columnspacing=1.2)


def _symlog(ax, top: float) -> None:
    """Counts on a symlog axis (linear 0..2) with plain integer ticks 0, 1, 2, 5, 10, 20, 50..."""
    from matplotlib.ticker import FixedLocator, NullLocator, StrMethodFormatter

    ax.set_yscale("symlog", linthresh=2, linscale=0.6)
    ax.set_ylim(bottom=0, top=top * 1.3)
    ticks = [0, 1, 2] + [m * 10 ** e for e in range(0, 12) for m in (5, 10, 20) if 2 < m * 10 ** e <= top * 1.3]
    ax.yaxis.set_major_locator(FixedLocator(sorted(set(ticks))))
    ax.yaxis.set_major_formatter(StrMethodFormatter("{x:,.0f}"))
    ax.yaxis.set_minor_locator(NullLocator())


def _number(value) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def draw(series: dict, title: str, out: Path) -> None:
    if "grasp" in series:  # forces, slide, slip against time, drive states (.plot_grasp)
        from .plot_grasp import draw as draw_grasp

        return draw_grasp(series, title, out)
    import numpy as np

    from ..report.plots import _COLOURS, _save, plt  # the report's colours and figure writer

    cycle = np.asarray(series["cycle"], dtype=float)
    n = len(cycle)
    u_g = np.array([_number(v) for v in series["U_G"]])
    threshold = np.array([_number(v) for v in series["threshold"]])
    decision = np.array([d if isinstance(d, str) else "undecided" for d in series["decision"]])
    truth = np.array([t if isinstance(t, str) else "" for t in series["truth"]])
    rule = series["meta"].get("decide_with") or "fusion"

    fig, axes = plt.subplots(4, 1, figsize=(10, 9.5), sharex=True,
                             gridspec_kw={"height_ratios": [3, 1.4, 1.2, 1.4]})
    ax = axes[0]
    present = truth == "H1"
    if present.any():  # ground truth H1: shaded cycles
        ax.fill_between(cycle, 0, 1, where=present, step="mid", color="tab:green", alpha=0.12,
                        transform=ax.get_xaxis_transform(), label="truth H1 (object present)")
    colour = _COLOURS.get(rule, "tab:blue")
    ax.plot(cycle, u_g, "-", color=colour, lw=1.0, label=f"U_G ({rule})")
    ax.plot(cycle, threshold, "--", color="black", lw=1.0, label="threshold")
    step = max(1, n // MARKERS_MAX)
    for kind, style in (("H1", dict(marker="^", color="tab:green")), ("H0", dict(marker="v", color="tab:blue"))):
        pick = np.flatnonzero(decision == kind)[::step]
        ax.plot(cycle[pick], u_g[pick], ls="none", ms=4, label=f"decision {kind} ({int((decision == kind).sum())})",
                **style)
    undecided = decision == "undecided"
    if undecided.any():
        ax.plot(cycle[undecided][::step], np.zeros(int(undecided.sum()))[::step], ls="none", marker="|", ms=14,
                color="tab:gray", transform=ax.get_xaxis_transform(),
                label=f"undecided ({int(undecided.sum())}, at the bottom)")
    decided = (decision != "undecided") & (truth != "")
    wrong = decided & (decision != truth)
    if wrong.any():
        ax.plot(cycle[wrong][::step], np.ones(int(wrong.sum()))[::step] * 0.97, ls="none", marker="x", ms=7,
                color="tab:red", transform=ax.get_xaxis_transform(),
                label=f"decision != truth ({int(wrong.sum())}, at the top)")
    if not np.isfinite(u_g).any():
        ax.text(0.5, 0.5, "no U_G in any record (every cycle undecided)", transform=ax.transAxes, ha="center",
                va="center", color="tab:gray")
        ax.set_yticks([])
    agree = f"; agree with truth {int((decided & ~wrong).sum())}/{int(decided.sum())}" if decided.any() else ""
    fig.suptitle(f"{title}: {n} cycles{agree}", fontsize=11)
    ax.set_ylabel(f"U_G of {rule}")
    _legend(ax, ncol=4)

    ax = axes[1]
    counts = [np.asarray(series["states"][state]) for state in STATES]
    shown = [(state, c) for state, c in zip(STATES, counts) if c.any()]
    if shown:
        ax.stackplot(cycle, *[c for _, c in shown], step="mid",
                     labels=[f"{s} (in {int((c > 0).sum())} cycles, at most {c.max()})" for s, c in shown],
                     colors=[STATE_COLOURS[s] for s, _ in shown], alpha=0.8)
        _legend(ax, ncol=3)
    else:
        ax.text(0.5, 0.5, "every node took part in every cycle", transform=ax.transAxes, ha="center", va="center",
                color="tab:gray")
    n_expected = series["meta"].get("n_expected")
    # symlog: one missing node of 57 stays visible next to a first cycle that nobody answered
    _symlog(ax, max(2, n_expected or 0, max((int(c.max()) for c in counts), default=0)))
    ax.set_ylabel("nodes not taking\npart" + (f" (of {n_expected})" if n_expected else "") + "\nsymlog scale")

    ax = axes[2]
    late = np.array([_number(v) for v in series["late_frames"]])
    bad = np.array([_number(v) for v in series["bad_frames"]])
    ax.bar(cycle, np.nan_to_num(late), width=1.0, color="tab:orange", label=f"late frames (total {int(np.nansum(late))})")
    ax.bar(cycle, np.nan_to_num(bad), width=1.0, bottom=np.nan_to_num(late), color="tab:red",
           label=f"malformed frames (total {int(np.nansum(bad))})")
    ax.set_ylabel("frames per cycle\nsymlog scale")
    _symlog(ax, max(2.0, float(np.nanmax(np.nan_to_num(late) + np.nan_to_num(bad)))))
    _legend(ax, ncol=2)

    ax = axes[3]
    t = np.array([_number(v) for v in series["t"]])
    gap = np.diff(t) * 1e3
    if gap.size:
        ax.plot(cycle[1:], gap, "-", color="0.6", lw=0.8, label="SYNC to next SYNC")
    after = np.array([_number(v) for v in series["closed_after_ms"]])
    closed = np.array([c if isinstance(c, str) else "?" for c in series["closed_by"]])
    if np.isfinite(after).any():  # the decision latency on the bus (logs before it: SYNC gaps only)
        for kind, col in CLOSED_BY.items():
            pick = np.flatnonzero((closed == kind) & np.isfinite(after))[::step]
            if pick.size:
                ax.plot(cycle[pick], after[pick], ls="none", marker=".", ms=4, color=col,
                        label=f"SYNC to close, {kind} ({int((closed == kind).sum())})")
        finite = after[np.isfinite(after)]
        inset = ax.inset_axes([1.03, 0.0, 0.15, 0.78])  # right of the panel, clear of the data
        inset.hist(finite, bins=40, color="tab:blue", log=True)
        inset.set_title(f"SYNC to close (ms)\np50 {np.percentile(finite, 50):.2f}, p99 {np.percentile(finite, 99):.2f}",
                        fontsize=7)
        inset.tick_params(labelsize=6)
        inset.set_ylabel("cycles", fontsize=6)
    elif gap.size:
        for kind, col in CLOSED_BY.items():
            pick = np.flatnonzero(closed[1:] == kind)[::step]
            if pick.size:
                ax.plot(cycle[1:][pick], gap[pick], ls="none", marker=".", ms=4, color=col,
                        label=f"cycle closed by {kind} ({int((closed[1:] == kind).sum())})")
    if gap.size or np.isfinite(after).any():
        _legend(ax, ncol=3)
    ax.set_ylabel("SYNC to close /\nnext SYNC (ms)")
    ax.set_xlabel("SYNC cycle")
    _save(fig, out)


def run(args) -> int:
    from taxel_net.errors import UsageError
    from taxel_net.outputs import OutputPath

    log = Path(args.log)
    out = Path(args.out) if args.out else log.with_suffix(".png")
    if args.out and (out.is_dir() or args.out.endswith(("/", os.sep))):
        if not out.is_dir():
            raise UsageError(f"--out {args.out!r}: directory does not exist")
        out = out / (log.stem + ".png")  # --out DIR: DIR/RUN.png
    if out.suffix.lower() not in FORMATS:
        raise UsageError(f"--out {str(out)!r}: unknown figure format {out.suffix!r} (use {', '.join(FORMATS)})")
    if not out.parent.is_dir():
        raise UsageError(f"--out {str(out)!r}: directory {str(out.parent)!r} does not exist")
    from taxel_net.outputs import check_distinct_paths

    check_distinct_paths([("RUN.jsonl", args.log)], [("--out", str(out))])  # the log itself: one line
    series = read_log(log)
    meta = series["meta"]
    title = f"{log.name} ({meta.get('mode') or '?'} mode)"
    # the partial file keeps the suffix (matplotlib takes the format from it); a FIFO or a
    # device is written in place, never renamed over nor removed (taxel_net.outputs)
    target = OutputPath(out, lambda t: t.stem + ".partial" + t.suffix, option="--out")
    try:
        if target.in_place:  # a FIFO cannot seek (PNG writers do): draw first, then write it out
            with tempfile.TemporaryDirectory() as scratch:
                drawn = Path(scratch) / ("figure" + out.suffix)
                draw(series, title, drawn)
                with open(target.write_path, "wb") as sink:
                    sink.write(drawn.read_bytes())
        else:
            draw(series, title, target.write_path)
        target.commit()
    except OSError as exc:
        raise UsageError(f"--out {str(out)!r} cannot be written: {exc.strerror or exc}") from None
    finally:
        target.discard_partial()
    errors = f", {series['errors']} cycles whose evaluation failed" if series["errors"] else ""
    print(f"wrote {out} ({len(series['cycle'])} cycles{errors})")
    return 0
