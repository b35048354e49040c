"""``fusion-center bandwidth``: exact bus cost of raw-data vs decision streaming for a scene,
and for the layouts a skin could be built with.

The scene's figures come from :func:`fusion_center.report.bandwidth.bandwidth_figures` (its
module docstring defines the three modes and every figure); ``--layouts`` (or ``--taxels N``
without a scene) adds :func:`fusion_center.report.bandwidth.layout_figures`: one-taxel and
patch nodes x decisions and raw readings x classic CAN and CAN FD x SYNC and event-driven,
exact bits, bus load, highest SYNC rate and latency per channel. This module is the command line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from taxel_net.buscli import DATA_BITRATE_MAX, parse_bitrate
from taxel_net.errors import ParameterError, UsageError

from ..report.bandwidth import (
    DEFAULT_DATA_BITRATE,
    DEFAULT_P_CHANGE,
    DEFAULT_PATCH,
    LAYOUT_RAW_PAYLOADS,
    bandwidth_figures,
    layout_figures,
)
from .report import parse_bitrates

MAX_TAXELS = 1_000_000
SYNC_COUNTER_HELP = "0 (none) or 2..240"


def parse_bitrates_one(text: str) -> int:
    """argparse type of ``--bitrate``: one classic CAN bit rate (``500k``, ``1M``, ``125000``)."""
    values = parse_bitrates(text)
    if len(values) != 1:
        raise argparse.ArgumentTypeError(f"{text!r}: one bit rate")
    return values[0]


def _data_bitrate(text: str) -> int:
    value = parse_bitrate(text)
    if not 1 <= value <= DATA_BITRATE_MAX:
        raise argparse.ArgumentTypeError(f"{text!r}: CAN FD data bit rate must be a whole number in "
                                         f"1..{DATA_BITRATE_MAX} bit/s (e.g. 2M, 5M)")
    return value


def _integer(low: int, high: int, what: str):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{text!r}: {what} must be a whole number in {low}..{high}")
        return value
    return parse


def _probability(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a probability in [0, 1]")
    return value


def _positive_ms(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not 0.0 < value < 1e7:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a number of milliseconds > 0")
    return value


def _sync_counter(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or not (value == 0 or 2 <= value <= 240):
        raise argparse.ArgumentTypeError(f"{text!r}: SYNC counter overflow value must be {SYNC_COUNTER_HELP}")
    return value


HELP = "bus cost per cycle of raw-data vs decision streaming (exact CAN bits, load, max rate, latency)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", help="scene file (TOML, docs/scene-format.md); needed unless --taxels")
    parser.add_argument("--bitrate", type=parse_bitrates_one, help="bit/s, e.g. 500000, 500k or 1M "
                        "(default: the scene's bus.bitrate; without a scene 1M); the CAN FD nominal rate")
    parser.add_argument("--cycles", type=int, help="cycles simulated (default: the scene's cycles)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    lay = parser.add_argument_group("layouts compared (--layouts, or --taxels without a scene)")
    lay.add_argument("--layouts", action="store_true",
                     help="also price one-taxel vs patch nodes x decision vs raw x classic vs FD x SYNC vs "
                          "event-driven for the scene's taxels, channels and bit rate")
    lay.add_argument("--taxels", type=_integer(1, MAX_TAXELS, "number of taxels"),
                     help="price the layouts for this many taxels (no scene needed; with one, instead of its count)")
    lay.add_argument("--patch", type=_integer(2, 100_000, "taxels per patch node"), default=DEFAULT_PATCH,
                     help=f"taxels per patch node (default {DEFAULT_PATCH})")
    lay.add_argument("--raw", choices=LAYOUT_RAW_PAYLOADS, default="raw8",
                     help="raw reading per taxel: INTEGER8, INTEGER16 or REAL32 (default raw8)")
    lay.add_argument("--data-bitrate", type=_data_bitrate, default=DEFAULT_DATA_BITRATE,
                     help="CAN FD data-phase bit rate (default 5M; >= the nominal --bitrate)")
    lay.add_argument("--p-change", type=_probability, default=DEFAULT_P_CHANGE,
                     help=f"event-driven: P(a taxel's decision changes) per cycle (default {DEFAULT_P_CHANGE})")
    lay.add_argument("--p-one", type=_probability, default=0.5,
                     help="P(taxel bit = 1) for the mean payload (default 0.5)")
    lay.add_argument("--channels", type=_integer(1, 10_000, "number of channels"),
                     help="CAN channels (default: the scene's; at least the fewest that hold the layout)")
    lay.add_argument("--sync-ms", type=_positive_ms, help="SYNC period (default: the scene's, else 10)")
    lay.add_argument("--heartbeat-ms", type=_positive_ms, help="heartbeat period (default: the scene's, else 100)")
    lay.add_argument("--sync-counter", type=_sync_counter,
                     help=f"SYNC counter overflow value, {SYNC_COUNTER_HELP}: SYNC carries it, patch PDOs lead "
                          "with it as cycle tag (default: the scene's, else 0)")


def render_table(fig: dict):
    from rich.table import Table

    table = Table(title=f"{fig['scene']}: {fig['taxels']} taxels, {fig['bitrate']} bit/s, "
                        f"SYNC {fig['sync_period_ms']} ms, {len(fig['channels'])} channel(s), "
                        f"{fig['cycles_simulated']} cycles simulated")
    for col in ("mode", "bits/cycle", "worst", "bus load", "max SYNC", "latency", "mean latency"):
        table.add_column(col, justify="right" if col != "mode" else "left")
    for mode, m in fig["modes"].items():
        table.add_row(mode, f"{m['bits_per_cycle']:.1f}", f"{m['bits_per_cycle_worst']:.1f}",
                      f"{100 * m['bus_load']:.1f} %", f"{m['max_cycle_rate_hz']:.0f} Hz",
                      f"{m['latency_ms']:.3f} ms", f"{m['latency_mean_ms']:.3f} ms")
    return table


def _rate(bps: int) -> str:
    return f"{bps / 1e6:g}M" if bps >= 1_000_000 else f"{bps / 1e3:g}k"


def render_layouts(lay: dict):
    from rich.table import Table

    tag = f", SYNC counter {lay['sync_counter']} (patch PDOs tagged)" if lay["sync_counter"] else ""
    table = Table(title=f"layouts for {lay['taxels']} taxels: classic {_rate(lay['nominal_bitrate'])}, FD "
                        f"{_rate(lay['nominal_bitrate'])}/{_rate(lay['data_bitrate'])}, SYNC "
                        f"{lay['sync_period_ms']:g} ms{tag}; event: P(change) {lay['p_change']:g}")
    for col in ("layout", "payload", "bus", "mode", "ch", "frames", "bits/cycle", "worst", "load", "max SYNC",
                "latency"):
        table.add_column(col, justify="left" if col in ("layout", "payload", "bus", "mode") else "right", no_wrap=True)
    for r in lay["rows"]:
        table.add_row(r["layout"], r["payload"], r["bus"], r["mode"], str(r["channels"]),
                      f"{r['pdo_frames_per_cycle']:.1f}" if r["mode"] == "event" else str(round(r["pdo_frames_per_cycle"])),
                      f"{r['bits_per_cycle']:.1f}", str(r["bits_per_cycle_worst"]), f"{100 * r['bus_load']:.1f} %",
                      f"{r['max_sync_hz']:.0f} Hz", f"{r['latency_ms']:.3f} ms")
    return table


def run(args) -> int:
    if args.scene is None and args.taxels is None:
        raise UsageError("--scene FILE or --taxels N is needed (the scene to price, or a number of taxels)")
    scene = fig = None
    if args.scene is not None:
        from taxel_net.scene import load_scene

        scene = load_scene(Path(args.scene))
        if args.taxels is None or args.layouts:
            fig = bandwidth_figures(scene, args.bitrate, args.cycles) if args.taxels is None else None
    lay = None
    if args.layouts or args.taxels is not None:
        bus = scene.bus if scene is not None else None
        nominal = args.bitrate or (bus.bitrate if bus else 1_000_000)
        if args.data_bitrate < nominal:
            raise ParameterError("--data-bitrate", args.data_bitrate,
                                 f"must lie in {nominal}..{DATA_BITRATE_MAX} bit/s (at least the nominal --bitrate)")
        lay = layout_figures(
            args.taxels if args.taxels is not None else scene.n, nominal_bitrate=nominal,
            data_bitrate=args.data_bitrate,
            sync_period_ms=args.sync_ms or (bus.sync_period_ms if bus else 10.0),
            heartbeat_ms=args.heartbeat_ms or (bus.heartbeat_producer_ms if bus else 100.0),
            patch=args.patch, raw=args.raw, p_change=args.p_change, p_one=args.p_one,
            channels=args.channels or (len(bus.channels) if bus else None),
            sync_counter=args.sync_counter if args.sync_counter is not None else (bus.sync_counter if bus else 0))
    if args.json:
        out = dict(fig) if fig is not None else {}
        if lay is not None:
            out["layouts"] = lay
        print(json.dumps(out, indent=2))
        return 0
    from rich.console import Console

    console = Console(width=max(100, Console().width))
    if fig is not None:
        console.print(render_table(fig))
        console.print(f"raw / decision_sync bits per cycle: {fig['raw_over_decision_sync']:.2f}x; "
                      f"bus load > 100 % means the traffic does not fit the SYNC period.")
    if lay is not None:
        console = Console(width=max(120, Console().width))
        console.print(render_layouts(lay))
        console.print(f"{lay['raw']} / decision bus time per SYNC cycle, mean (worst): " + ", ".join(
            f"{k} {v['mean']:.2f}x ({v['worst']:.2f}x)" for k, v in lay["raw_over_decision"].items()))
        console.print("load: busiest channel, heartbeats included; max SYNC: every channel's worst-case cycle fits; "
                      "latency: SYNC to the last PDO of the slowest channel, worst case.")
    return 0
