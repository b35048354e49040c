"""The robotics flags of ``run``, ``demo`` and ``replay`` (docs/robotics.md) and their set-up:
``--mcap FILE``, ``--foxglove [HOST:]PORT`` (live runs), ``--ros2-bag DIR`` (``run``, ``replay``).
Everything is checked before the run starts (one line, exit 2).

In ``run`` and ``demo`` the live outputs - ``--foxglove`` and ``--zenoh`` - run in the robotics
bridge process (:mod:`.bridge_link`, docs/robotics.md *The bridge process*); ``--mcap`` and
``--ros2-bag`` are written in the centre's process (:class:`.outputs.RoboticsOutputs`)."""

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
                                 "never cycles; served by the robotics bridge process beside the centre "
                                 "(docs/robotics.md)")
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


def open_outputs(args, scene, *, threaded: bool, source: dict | None = None, zenoh: dict | None = None):
    """The run's outputs, or None when no robotics flag is given: a
    :class:`~.outputs.RoboticsOutputs`, or - with ``source`` (``run``, ``demo``: how the bridge
    loads the scene, :class:`.bridge_link.RoboticsBridge`) and ``--foxglove`` or ``zenoh`` (the
    ``--zenoh`` settings) - a :class:`LiveRunOutputs` of the bridge and the in-process files."""
    mcap = getattr(args, "mcap", None)
    listen = getattr(args, "foxglove", None)
    bag = getattr(args, "ros2_bag", None)
    from .foxglove_live import parse_listen
    from .outputs import RoboticsOutputs

    foxglove = parse_listen(listen) if listen is not None else None
    if source is not None and (foxglove is not None or zenoh is not None):
        from .bridge_link import RoboticsBridge

        bridge = RoboticsBridge(scene, source, zenoh=zenoh, foxglove=foxglove).open()
        try:
            local = RoboticsOutputs(scene, mcap=mcap, ros2_bag=bag, threaded=threaded) if mcap or bag else None
        except BaseException:
            bridge.close()
            raise
        return LiveRunOutputs(local, bridge)
    if not (mcap or foxglove is not None or bag):
        return None
    return RoboticsOutputs(scene, mcap=mcap, foxglove=foxglove, ros2_bag=bag, threaded=threaded)


class LiveRunOutputs:
    """``run`` / ``demo``'s outputs: the bridge (``--zenoh``, ``--foxglove``) and the in-process
    files (``--mcap``, ``--ros2-bag``; or None), with :class:`~.outputs.RoboticsOutputs`'
    ``attach`` / ``close``; ``close`` returns both's figures (the bridge's ``zenoh``,
    ``foxglove`` and ``bridge``)."""

    def __init__(self, local, bridge):
        self.local = local
        self.bridge = bridge

    def attach(self, service) -> None:
        self.bridge.attach(service)
        if self.local is not None:
            self.local.attach(service)

    def close(self, ok: bool = True) -> dict:
        try:
            stats = self.bridge.close()
        finally:
            if self.local is not None:
                stats_local = self.local.close(ok=ok)
        if self.local is not None:
            stats = {**stats_local, **stats}
        return stats
