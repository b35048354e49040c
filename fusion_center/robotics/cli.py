"""The robotics flags of ``run``, ``demo`` and ``replay`` (docs/robotics.md) and their set-up:
``--mcap FILE``, ``--foxglove [HOST:]PORT`` (live runs), ``--ros2-bag DIR`` (``run``, ``replay``).
Everything is checked before the run starts (one line, exit 2)."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser, *, live: bool, bag: bool) -> None:
    parser.add_argument("--mcap", metavar="FILE", default=None,
                        help="every cycle as Foxglove messages in an MCAP file (taxel maps, decision per rule, "
                             "contact, slip, forces, grip, truth, bus; log time = SYNC time; docs/robotics.md)")
    if live:
        parser.add_argument("--foxglove", metavar="[HOST:]PORT", default=None,
                            help="a live Foxglove WebSocket server with the same channels (loopback 127.0.0.1 "
                                 "unless HOST is given; 0: any free port); a slow viewer loses messages, "
                                 "never cycles")
    if bag:
        parser.add_argument("--ros2-bag", metavar="DIR", default=None,
                            help="a ROS 2 bag (rosbag2, MCAP storage, standard message types) in the new "
                                 "directory DIR")


def check(args) -> None:
    """Refuse bad robotics flags before anything runs (the outputs themselves open later)."""
    from taxel_net.outputs import OutputPath

    if getattr(args, "mcap", None):
        OutputPath(args.mcap, option="--mcap")  # a directory: one line
    if getattr(args, "foxglove", None) is not None:
        from .foxglove_live import parse_listen

        parse_listen(args.foxglove)
    if getattr(args, "ros2_bag", None):
        from .ros2_bag import check_bag_target

        check_bag_target(args.ros2_bag)


def open_outputs(args, scene, *, threaded: bool):
    """The run's :class:`~.outputs.RoboticsOutputs`, or None when no robotics flag is given."""
    mcap = getattr(args, "mcap", None)
    listen = getattr(args, "foxglove", None)
    bag = getattr(args, "ros2_bag", None)
    if not (mcap or listen is not None or bag):
        return None
    from .foxglove_live import parse_listen
    from .outputs import RoboticsOutputs

    return RoboticsOutputs(scene, mcap=mcap, foxglove=parse_listen(listen) if listen is not None else None,
                           ros2_bag=bag, threaded=threaded)
