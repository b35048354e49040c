"""``fusion-center report``: detection error against run time for every rule, on one scene.

The report itself is built by :func:`fusion_center.report.build.build_report` (its docstring
lists the files written); this module is the command line around it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from taxel_net.scene import load_scene

from ..report.build import DEFAULT_TRIALS, build_report

HELP = "detection error vs bus/CPU time of every fusion rule and the centralised raw test (JSON + PNG)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True, help="scene file (TOML)")
    parser.add_argument("--out", required=True, help="output directory (created)")
    parser.add_argument("--trials", type=int, default=DEFAULT_TRIALS,
                        help=f"Monte Carlo trials per hypothesis (default {DEFAULT_TRIALS})")
    parser.add_argument("--seed", type=int, default=None, help="RNG seed (default: the scene's seed)")
    parser.add_argument("--bitrate", type=parse_bitrates, default=None, metavar="B[,B...]",
                        help="bit/s for the bus figures, one or several comma-separated "
                             "(e.g. 125000,500000,1000000; default: the scene's)")


def parse_bitrates(text: str) -> list[int]:
    """``"125000,500000,1000000"`` -> [125000, 500000, 1000000] (argparse type)."""
    out = []
    for given in text.split(","):
        item = given.strip().lower().replace("_", "")
        scale = 1000 if item.endswith("k") else 1_000_000 if item.endswith("m") else 1
        try:
            value = float(item.rstrip("km")) * scale
        except ValueError:
            raise argparse.ArgumentTypeError(f"{given!r} is not a bit rate (e.g. 500000 or 500k)") from None
        if value != int(value) or not 1 <= value <= 1_000_000:
            raise argparse.ArgumentTypeError(f"{given!r}: bit rate must be a whole number in 1..1000000 bit/s "
                                             "(classic CAN)")
        out.append(int(value))
    return out


def run(args) -> int:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    scene = load_scene(Path(args.scene))
    seed = scene.seed if args.seed is None else args.seed
    with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn()) as bar:
        task = bar.add_task("report", total=1.0)

        def step(what, frac=None):
            bar.update(task, description=what, completed=0.0 if frac is None else frac)

        data = build_report(scene, Path(args.out), args.trials, seed, args.bitrate, step)
        bar.update(task, description="done", completed=1.0)
    print(f"wrote {', '.join(data['files'])} to {args.out}")
    return 0
