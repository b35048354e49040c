"""``fusion-center report``: detection error against run time for every rule, on one scene.

The report itself is built by :func:`fusion_center.report.build.build_report` (its docstring
lists the files written); this module is the command line around it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from taxel_net.errors import ParameterError
from taxel_net.scene import load_scene

from . import parse_bitrate

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
    """``"125000,500k,1M"`` -> [125000, 500000, 1000000] (argparse type; each item as ``-b``)."""
    out = []
    for given in text.split(","):
        value = parse_bitrate(given)
        if not 1 <= value <= 1_000_000:
            raise argparse.ArgumentTypeError(f"{given!r}: bit rate must be a whole number in 1..1000000 bit/s "
                                             "(classic CAN)")
        out.append(value)
    return out


def run(args) -> int:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    scene = load_scene(Path(args.scene))
    seed = scene.seed if args.seed is None else args.seed
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ParameterError("--out", args.out, f"an output directory that can be created "
                                                f"({exc.strerror or type(exc).__name__})") from None
    with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn()) as bar:
        task = bar.add_task("report", total=1.0)

        def step(what, frac=None):
            bar.update(task, description=what, completed=0.0 if frac is None else frac)

        data = build_report(scene, Path(args.out), args.trials, seed, args.bitrate, step)
        bar.update(task, description="done", completed=1.0)
    print(f"wrote {', '.join(data['files'])} to {args.out}")
    return 0
