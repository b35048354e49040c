"""Onset -> stuck again against the drive: bench/grasp.py's randomised grasps under other torque slopes and force lags.

Issue 23's goal "stuck again at most 50 ms after slip onset" is not met with the bundled drive
(``grasp_lift``'s 0x6087: 500 N/s per jaw, 5 N a 10 ms cycle; the jaws' force lag
``[grasp] force_lag_ms`` 20 ms); ``docs/grip-control.md`` ("Bounds") argues the drive and the pad
pitch bound it. This bench measures it: the same cases as ``bench/grasp.py`` (the same ``--seed``
draws the same objects, tasks, pitches and contact positions), each run through the live centre's
control code (``bench/grasp_sim.py``) once per drive ``(torque slope, force lag)`` - only the drive
changes, not the law's ``[grip]`` - and prints side by side, per pad pitch and over all: onset ->
stuck again (median / p95 ms), the share of slip episodes stuck again within 50 ms, onset ->
detection and the parts after it (``bench/grasp.py``'s "stuck in parts"), the slide, objects lost
and the holding force within 1.3x.

Usage: python bench/grasp_drive.py [--grasps 300] [--seed 23] [--slopes 500,1000,2000] [--lags 20]
       [--syncs 10] [--modes decision] [--contact random|centred] [--jobs N] [--json out.json]

The bundled scenes' drive is not changed: this is what a faster drive or a finer pitch would buy.
After each mode's table: each pad layout's bus per cycle at each SYNC period (worst-case stuffing,
the loop's frames included) and a WARNING line for a layout whose frames do not fit the cycle -
the bench skips the bus, so such a variant's figures assume a bus that is not there.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from grasp import PARTS, PITCHES, make_case, place_contacts, run_jobs  # noqa: E402
from grasp_layout import pad_rows  # noqa: E402
from grasp_sim import BitCounter  # noqa: E402
from fusion_center.core.bus_timing import bus_load, worst_case_frame_bits  # noqa: E402

GOAL_MS = 50.0


def _floats(text: str, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: comma-separated numbers") from None
    if not values or any(not np.isfinite(v) or v < 0 for v in values):
        raise argparse.ArgumentTypeError(f"{what} {text!r}: comma-separated finite numbers >= 0")
    return values


def cell_stats(grasps: list[dict], mode: str, dt_ms: float) -> dict:
    """One variant's numbers over ``grasps`` (``bench/grasp.py``'s per-grasp results)."""
    eps = [e for g in grasps for e in g[mode]["episodes"]]
    stuck = [e["stuck_ms"] for e in eps if e["stuck_ms"] is not None]
    det = [e["detect_cycles"] * dt_ms for e in eps if e["detect_cycles"] is not None]
    parts = [e["parts"] for e in eps if e.get("parts")]
    ratios = [g[mode]["ratio"] for g in grasps if g[mode]["ratio"] is not None]
    out = {"grasps": len(grasps), "episodes": len(eps),
           "stuck_med": _pct(stuck, 50), "stuck_p95": _pct(stuck, 95),
           "stuck_le_goal": (sum(1 for s in stuck if s <= GOAL_MS + 1e-9) / len(stuck)) if stuck else float("nan"),
           "detect_med": _pct(det, 50),
           "slid_med": _pct([g[mode]["slid_mm"] for g in grasps], 50),
           "slid_p95": _pct([g[mode]["slid_mm"] for g in grasps], 95),
           "dropped": sum(1 for g in grasps if g[mode]["dropped"]),
           "crushed": sum(1 for g in grasps if g[mode]["crushed"]),
           "ratio_le_1_3": (sum(1 for r in ratios if r <= 1.3) / len(ratios)) if ratios else float("nan")}
    for n, part in enumerate(PARTS):
        out[f"part_{part}"] = _pct([p[n] * dt_ms for p in parts], 50)
    return out


def _pct(values, q):
    return float(np.percentile(values, q)) if values else float("nan")


def _f(v, fmt="{:.0f}"):
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else fmt.format(v)


PDO_BYTES = {"decision": 1, "raw": 4}   # a one-taxel node's TPDO1 (u_i) / TPDO2 (X_i, REAL32)


def layout_bus_share(pitch_mm: float, mode: str, sync_ms: float, bitrate: float, drive_node: int) -> float:
    """The bus time one cycle of a pad layout needs, as a share of the SYNC period: every
    one-taxel node's PDO with worst-case stuffing (``worst_case_frame_bits``: a cycle fits for
    sure at <= 1) plus the loop's own frames (SYNC, the drive's TPDOs, the centre's RPDO1:
    ``BitCounter.loop_bits``). The bench skips the bus, so a layout over 1 runs here on a bus that
    could not carry it: its figures are flagged, not left to look valid."""
    nodes = len(pad_rows(pitch_mm))
    bits = [worst_case_frame_bits(PDO_BYTES[mode])] * nodes + [BitCounter.loop_bits(drive_node)]
    return bus_load(bits, sync_ms / 1000.0, bitrate)


def render_bus(variants, mode: str, bitrate: float, drive_node: int) -> tuple[str, list[str]]:
    """Per pad pitch and SYNC period: the layout's bus share (``layout_bus_share``); and a line per
    (pitch, SYNC) whose frames do not fit."""
    syncs = sorted({v[2] for v in variants}, reverse=True)
    lines = [f"{mode}: bus per cycle, worst-case stuffing and the loop's frames, % of {bitrate / 1e6:g} Mbit/s "
             f"(over 100 %: the frames do not fit the cycle)",
             f"{'pitch':28s}" + "".join(f"{f'SYNC {s:g} ms':>14s}" for s in syncs)]
    over = []
    for pitch in PITCHES:
        cells = []
        for sync in syncs:
            share = layout_bus_share(pitch, mode, sync, bitrate, drive_node)
            cells.append(f"{100 * share:.0f} %" + (" !" if share > 1 else "  "))
            if share > 1:
                over.append(f"{mode}: the {pitch:g} mm pads at a {sync:g} ms SYNC need {100 * share:.0f} % of the bus: "
                            "their figures assume frames a real bus could not carry in the cycle")
        lines.append(f"{f'{pitch:g} mm ({len(pad_rows(pitch))} nodes)':28s}" + "".join(f"{c:>14s}" for c in cells))
    return "\n".join(lines), over


def variant_name(variant: tuple[float, float, float]) -> str:
    """``(slope N/s, lag ms, SYNC ms)`` -> its column head."""
    slope, lag, sync = variant
    return f"{slope:g} N/s, {lag:g} ms, SYNC {sync:g}"


def render(stats: dict, variants: list[tuple[float, float, float]], mode: str) -> str:
    """``stats[(variant, pitch or "all")]`` -> the side-by-side table."""
    heads = [variant_name(v) for v in variants]
    width = max(22, max(len(h) for h in heads) + 2)
    lines = [f"{mode}: onset -> stuck again, ms median/p95 [share of episodes <= {GOAL_MS:g} ms] (episodes)",
             f"{'pitch':28s}" + "".join(f"{h:>{width}s}" for h in heads)]
    for pitch in (*PITCHES, "all"):
        label = f"{pitch:g} mm" if pitch != "all" else "all pitches"
        cells = []
        for v in variants:
            st = stats[(v, pitch)]
            cells.append(f"{_f(st['stuck_med'])}/{_f(st['stuck_p95'])} [{_f(100 * st['stuck_le_goal'])}%] "
                         f"({st['episodes']})")
        lines.append(f"{label:28s}" + "".join(f"{c:>{width}s}" for c in cells))
    lines.append("all pitches, medians:")
    rows = [("onset->detect ms", lambda st: _f(st["detect_med"])),
            ("  parts: detect ms", lambda st: _f(st["part_detect"])),
            ("  detect->raise ms", lambda st: _f(st["part_raise"])),
            ("  raise->force holds ms", lambda st: _f(st["part_force"])),
            ("  force->stuck ms", lambda st: _f(st["part_stop"])),
            ("slid mm med/p95", lambda st: f"{_f(st['slid_med'], '{:.1f}')}/{_f(st['slid_p95'], '{:.1f}')}"),
            ("dropped / crushed", lambda st: f"{st['dropped']} / {st['crushed']}"),
            ("hold force/least <= 1.3", lambda st: f"{_f(100 * st['ratio_le_1_3'])} %")]
    for label, fn in rows:
        lines.append(f"{label:28s}" + "".join(f"{fn(stats[(v, 'all')]):>{width}s}" for v in variants))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grasps", type=int, default=300, help="randomised grasps per drive (default 300)")
    ap.add_argument("--seed", type=int, default=23)
    ap.add_argument("--slopes", type=lambda t: _floats(t, "--slopes"), default=[500.0, 1000.0, 2000.0],
                    help="torque slopes, N/s per jaw (0x6087 x rated force; default 500,1000,2000)")
    ap.add_argument("--lags", type=lambda t: _floats(t, "--lags"), default=[20.0],
                    help="the jaws' force lags, ms ([grasp] force_lag_ms; default 20)")
    ap.add_argument("--syncs", type=lambda t: _floats(t, "--syncs"), default=None,
                    help="SYNC periods, ms ([bus] sync_period_ms: the world, the drive and the centre "
                         "step by it; default the base scene's, 10)")
    ap.add_argument("--modes", default="decision", help="centre modes, comma-separated: decision, raw (default decision)")
    ap.add_argument("--contact", choices=("random", "centred"), default="random")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--json", type=Path, help="write the per-variant tables here")
    args = ap.parse_args(argv)
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    if not modes or any(m not in ("decision", "raw") for m in modes):
        ap.error(f"--modes {args.modes!r}: decision and/or raw")
    if args.grasps < 1 or args.jobs < 1:
        ap.error("--grasps and --jobs must be >= 1")
    if any(s <= 0 for s in args.slopes):
        ap.error("--slopes: every slope must be > 0 N/s")
    from grasp import _base

    rated = _base().gripper.rated_force_n
    for s in args.slopes:   # 0x6087 is an integer ‰/s
        if abs(s * 1000.0 / rated - round(s * 1000.0 / rated)) > 1e-9:
            ap.error(f"--slopes {s:g}: must be a whole number of ‰/s of the rated force ({rated:g} N: "
                     f"steps of {rated / 1000.0:g} N/s)")
    syncs = args.syncs or [_base().bus.sync_period_ms]
    from taxel_net.scene import SYNC_PERIOD_MIN_MS

    for sync in syncs:   # the scene's least [bus] sync_period_ms; at most 1 s (a grasp's phases last 0.3-2 s)
        if not SYNC_PERIOD_MIN_MS <= sync <= 1000.0:
            ap.error(f"--syncs {sync:g}: every SYNC period must be 1-1000 ms")
    variants = list(itertools.product(args.slopes, args.lags, syncs))
    rng = np.random.default_rng(args.seed)
    cases = place_contacts([make_case(rng, i) for i in range(args.grasps)], args.seed, args.contact)
    jobs = [(c, False, {}, modes, v) for v in variants for c in cases]
    results, elapsed, errors = run_jobs(jobs, args.jobs, every=100, unit="runs")
    by_variant = {v: results[i * len(cases):(i + 1) * len(cases)] for i, v in enumerate(variants)}
    print(f"bench/grasp_drive.py --grasps {args.grasps} --seed {args.seed} --contact {args.contact}: "
          f"{len(variants)} variant(s) x {len(modes)} mode(s) in {elapsed:.0f} s ({args.jobs} job(s))"
          + (f"; {len(errors)} grasp(s) failed (above), left out" if errors else ""))
    out = {}
    for mode in modes:
        stats = {}
        for v, res in by_variant.items():
            ok = [r for r in res if "error" not in r]
            for pitch in (*PITCHES, "all"):
                sel = ok if pitch == "all" else [r for r in ok if r["case"]["pitch_mm"] == pitch]
                stats[(v, pitch)] = cell_stats(sel, mode, v[2])
        print(render(stats, variants, mode))
        bus_table, over = render_bus(variants, mode, _base().bus.bitrate, _base().gripper.node_id)
        print(bus_table)
        for line in over:
            print(f"WARNING {line}")
        out[mode] = {f"{variant_name(v)}|{p}": st for (v, p), st in stats.items()}
        out[f"{mode} bus"] = {f"{p:g} mm|SYNC {sync:g}": layout_bus_share(p, mode, sync, _base().bus.bitrate,
                                                                          _base().gripper.node_id)
                              for p in PITCHES for sync in sorted({v[2] for v in variants})}
    if args.json:
        args.json.write_text(json.dumps({"args": {"grasps": args.grasps, "seed": args.seed, "contact": args.contact,
                                                  "slopes": args.slopes, "lags": args.lags, "syncs": syncs,
                                                  "modes": modes,
                                                  "elapsed_s": round(elapsed, 1),
                                                  "date": time.strftime("%Y-%m-%d", time.gmtime())},
                                         "tables": out}, default=float))
    return 1 if errors else 0   # a table with grasps left out is not a complete run


if __name__ == "__main__":
    raise SystemExit(main())
