"""``fusion-center export``: a run's decision log as a ROS 2 bag (``--ros2 DIR``) and/or an MCAP
file of Foxglove messages (``--mcap FILE``) - the messages ``run --ros2-bag`` / ``--mcap`` write,
without the raw readings (a decision log carries none; docs/robotics.md)."""

from __future__ import annotations

import argparse

HELP = "export a decision log (RUN.jsonl) as a ROS 2 bag (--ros2 DIR) or an MCAP file (--mcap FILE)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="RUN.jsonl", help="decision log written by run/demo/replay --json-lines")
    parser.add_argument("out", metavar="OUT_DIR", nargs="?", default=None,
                        help="the bag's directory (new), with --ros2")
    parser.add_argument("--ros2", action="store_true", help="write a ROS 2 bag (rosbag2, MCAP storage) into OUT_DIR")
    parser.add_argument("--mcap", metavar="FILE", default=None, help="write the Foxglove MCAP file FILE")
    parser.add_argument("--scene", metavar="FILE", required=True,
                        help="the scene of the run, file or bundled name (as for replay): the taxel maps' pads "
                             "and sites come from it; a log of another taxel count is refused")


def read_log(path) -> list[dict]:
    """Every record of a decision log; a line that is not one JSON object: one line naming the
    file and the line (:func:`taxel_net.json_lines.iter_log`)."""
    from taxel_net.errors import UsageError
    from taxel_net.json_lines import iter_log

    records = [record for _, record in iter_log(path, check=_not_a_record)]
    if not records:
        raise UsageError(f"decision log {str(path)!r}: no records")
    return records


def _not_a_record(record) -> str | None:
    if not isinstance(record, dict) or not isinstance(record.get("cycle"), int) \
            or not isinstance(record.get("t"), (int, float)) or isinstance(record.get("t"), bool):
        return "not a record of the decision log (a JSON object with an integer 'cycle' and a number 't')"
    return None


def run(args) -> int:
    from taxel_net.errors import UsageError
    from taxel_net.scene import load_scene

    from ..robotics import cli as robotics
    from ..robotics.outputs import RoboticsOutputs, summary_lines

    if args.ros2 and args.out is None:
        raise UsageError("--ros2: give the bag's directory: fusion-center export --ros2 RUN.jsonl OUT_DIR")
    if not args.ros2 and args.out is not None:
        raise UsageError(f"{args.out!r}: an output directory is for --ros2 (a ROS 2 bag); for MCAP give --mcap FILE")
    if not args.ros2 and not args.mcap:
        raise UsageError("nothing to export: give --ros2 OUT_DIR and/or --mcap FILE")
    bag = args.out if args.ros2 else None
    from taxel_net.outputs import check_distinct_paths, scene_inputs

    check_distinct_paths([("RUN.jsonl", args.log), *scene_inputs(args.scene)],
                         [("--mcap", args.mcap), ("OUT_DIR", bag)])  # one line, before anything is written
    robotics.check(argparse.Namespace(mcap=args.mcap))
    if bag is not None:
        from ..robotics.ros2_bag import check_bag_target

        check_bag_target(bag, "OUT_DIR")
    records = read_log(args.log)
    scene = load_scene(args.scene)
    for number, record in enumerate(records, 1):
        if record.get("n_expected") not in (None, scene.n):
            raise UsageError(f"decision log {str(args.log)!r}: record {number} (cycle {record['cycle']}) has "
                             f"n_expected {record['n_expected']}, scene {scene.name!r} has {scene.n} taxels: "
                             "give the run's --scene")
    outputs = RoboticsOutputs(scene, mcap=args.mcap, ros2_bag=bag)
    ok = False
    try:
        for record in records:
            outputs.on_cycle(record)
        ok = True
    finally:
        stats = outputs.close(ok=ok)
    for label, text in summary_lines(stats):
        print(f"{label}: {text}")
    return 0
