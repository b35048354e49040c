"""``fusion-center bandwidth``: exact bus cost of raw-data vs decision streaming for a scene.

The figures come from :func:`fusion_center.report.bandwidth.bandwidth_figures` (its module
docstring defines the three modes and every figure); this module is the command line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from taxel_net.scene import load_scene

from ..report.bandwidth import bandwidth_figures
from .report import parse_bitrates


def parse_bitrates_one(text: str) -> int:
    """argparse type of ``--bitrate``: one classic CAN bit rate (``500k``, ``1M``, ``125000``)."""
    values = parse_bitrates(text)
    if len(values) != 1:
        raise argparse.ArgumentTypeError(f"{text!r}: one bit rate")
    return values[0]

HELP = "bus cost per cycle of raw-data vs decision streaming (exact CAN bits, load, max rate, latency)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True, help="scene file (TOML, docs/scene-format.md)")
    parser.add_argument("--bitrate", type=parse_bitrates_one, help="bit/s, e.g. 500000, 500k or 1M "
                        "(default: the scene's bus.bitrate)")
    parser.add_argument("--cycles", type=int, help="cycles simulated (default: the scene's cycles)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")


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


def run(args) -> int:
    path = Path(args.scene)
    scene = load_scene(path)
    fig = bandwidth_figures(scene, args.bitrate, args.cycles)
    if args.json:
        print(json.dumps(fig, indent=2))
        return 0
    from rich.console import Console

    console = Console(width=max(100, Console().width))
    console.print(render_table(fig))
    console.print(f"raw / decision_sync bits per cycle: {fig['raw_over_decision_sync']:.2f}x; "
                  f"bus load > 100 % means the traffic does not fit the SYNC period.")
    return 0
