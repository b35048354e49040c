"""``fusion-center replay``: re-fuse a recorded CAN trace offline (same records as the live run)."""

from __future__ import annotations

import argparse
import sys

from .run import add_mode_argument

HELP = "re-fuse a recorded CAN trace (python-can LogReader: .log, .asc, .blf, .trc, .csv) offline"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True, metavar="FILE", help="the scene of the recorded run")
    parser.add_argument("trace", metavar="TRACE", help="trace written by `run --log` / `demo --log`")
    parser.add_argument("--json-lines", metavar="OUT", default=None,
                        help="write the records here (default: print them on stdout)")
    add_mode_argument(parser)
    parser.add_argument("--truth-log", metavar="FILE", default=None,
                        help="the grasp world's truth of the run (`node-sim --truth-log`): records of a scene "
                             "with [gripper] and [grasp] then carry grasp_truth")
    from ..robotics.cli import add_arguments as add_robotics_arguments

    add_robotics_arguments(parser, live=False, bag=True)
    parser.add_argument("--force", action="store_true",
                        help="replay even when the trace does not match the scene (a channel the scene does "
                             "not have, node-IDs of another scene, the other mode, a .csv of several channels)")


def run(args) -> int:
    from taxel_net.errors import UsageError
    from taxel_net.outputs import discard_stale
    from taxel_net.scene import load_scene
    from ..service import replay_trace
    from ..service.records import dumps
    from ..service.traces import check_trace
    from .run import apply_mode, setup_logging

    from ..robotics import cli as robotics

    from . import check_output_paths

    setup_logging()
    # before anything is read or written: an output naming the trace, the truth log, the scene or
    # another output is refused (a failed check below would else delete it as a stale output)
    check_output_paths(args, inputs=[("TRACE", args.trace), ("--truth-log", args.truth_log)])
    scene = apply_mode(load_scene(args.scene), args.mode)  # the mode of the recorded run
    grasp_truth = None
    if args.truth_log is not None:
        from ..service.grasp_truth import TruthTable

        if scene.gripper is None or getattr(scene, "grasp", None) is None:
            raise UsageError(f"--truth-log: scene {scene.name!r} has no grasp world ([gripper] and [grasp])")
        grasp_truth = TruthTable.from_file(args.truth_log)
    robotics.check(args)
    if not args.force:
        try:
            check_trace(scene, args.trace)  # before anything is written
        except UsageError:
            inputs = [args.trace, args.truth_log, scene.path]
            for stale in (args.json_lines, args.mcap):
                if stale and not _names_any(stale, inputs):  # never an input (checked above; kept safe)
                    discard_stale(stale)  # an output of an earlier replay must not pass for this one's
            raise
    on_record = None if args.json_lines else (lambda r: print(dumps(r)))
    outputs = robotics.open_outputs(args, scene, threaded=False)
    try:
        records, counters = replay_trace(scene, args.trace, json_lines=args.json_lines, on_record=on_record,
                                         grasp_truth=grasp_truth,
                                         on_cycle=outputs.on_cycle if outputs is not None else None)
    except BaseException:
        if outputs is not None:
            outputs.close(ok=False)
        raise
    robotics_stats = outputs.close(ok=True) if outputs is not None else {}
    out = sys.stderr if not args.json_lines else sys.stdout
    print(f"records: {len(records)}", file=out)
    print(f"counters: {({k: v for k, v in counters.items() if v})}", file=out)
    from ..robotics.outputs import incomplete_files, summary_lines

    for label, text in summary_lines(robotics_stats):
        print(f"{label}: {text}", file=out)
    status = 0
    if grasp_truth is not None:
        # how much of the truth log the records met (a log of another run, cut or shifted, matches
        # few or none: said, never silent - 2026-11-30, stop 32)
        matched = sum(1 for r in records if r.get("grasp_truth") is not None)
        print(f"grasp_truth: {matched} of {len(records)} records matched to {args.truth_log!r} "
              f"({grasp_truth.steps} world steps)", file=out)
        if records and not matched:
            print(f"fusion-center replay: error: --truth-log {args.truth_log!r}: no record's cycle matched "
                  "a world step of it (a truth log of another run?)", file=sys.stderr)
            status = 2
    for _, text in incomplete_files(robotics_stats):
        print(f"fusion-center replay: error: {text}", file=sys.stderr)
        status = 2
    return status


def _names_any(path, others) -> bool:
    """``path`` names the same file as one of ``others`` (resolved, or ``os.path.samefile``)."""
    import os

    for other in others:
        if other is None:
            continue
        try:
            if os.path.realpath(path) == os.path.realpath(other) or os.path.samefile(path, other):
                return True
        except OSError:  # one of them does not exist: not the same file
            continue
    return False
