"""``node-sim``: start every taxel node twin of a scene on a CAN bus and run until stopped.

    node-sim --scene scenes/matrix57.toml [--interface virtual|udp_multicast|socketcan|...]
             [--channel CH ...] [--bitrate B] [--seed S] [--bus-option KEY=VALUE ...]

One bus per scene channel (``bus.channels``); ``--channel`` is given once per scene channel
(default: the scene's channel names, which suit the ``virtual`` interface). Any python-can
interface works by name; ``--bus-option`` passes extra ``can.Bus`` keyword arguments (e.g.
``port=43113`` for udp_multicast). Prints one "ready" line on stdout once every node has
sent its boot-up, then runs until SIGINT/SIGTERM and shuts down cleanly (exit 0). A bad scene,
an unknown interface, a channel that cannot be opened or a missing EDS exit 2 with one line.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

import can

from taxel_net.errors import ParameterError, SceneError

from . import od as odx


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("taxel-can")
    except PackageNotFoundError:  # a checkout that was never installed
        return "unknown (not installed)"


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def _bus_option(text: str) -> tuple[str, object]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"{text!r}: expected KEY=VALUE")
    key, value = text.split("=", 1)
    low = value.lower()
    if low in ("true", "false"):
        return key, low == "true"
    for conv in (int, float):
        try:
            return key, conv(value)
        except ValueError:
            pass
    return key, value


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="node-sim", description="Run a scene's CANopen taxel node twins on a CAN bus.")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    p.add_argument("--scene", required=True, help="scene file (TOML, docs/scene-format.md)")
    p.add_argument("--interface", default="virtual", help="python-can interface name (default: virtual)")
    p.add_argument("--channel", action="append", default=None,
                   help="bus channel; once per scene channel (default: the scene's channel names)")
    p.add_argument("--bitrate", type=int, default=None, help="bit rate passed to can.Bus (default: not passed)")
    p.add_argument("--seed", type=int, default=None, help="noise seed (default: the scene's)")
    p.add_argument("--bus-option", type=_bus_option, action="append", default=[], metavar="KEY=VALUE",
                   help="extra can.Bus keyword argument, e.g. port=43113 (repeatable)")
    p.add_argument("--eds", default=str(odx.EDS_PATH), help=argparse.SUPPRESS)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # a bus whose constructor failed is later reported by python-can as "not properly shut
    # down": the one-line error below already says why
    logging.getLogger("can.bus").setLevel(logging.ERROR)
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    try:
        from taxel_net.scene import load_scene

        from .rig import Rig

        if args.interface not in can.interfaces.VALID_INTERFACES:
            raise ParameterError("interface", args.interface,
                                 "unknown python-can interface (known: "
                                 + ", ".join(sorted(can.interfaces.VALID_INTERFACES)) + ")")
        scene = load_scene(args.scene)
        channel = None
        if args.channel:
            channel = args.channel[0] if len(args.channel) == 1 and len(scene.bus.channels) == 1 else args.channel
        rig = Rig(scene, interface=args.interface, channel=channel, bitrate=args.bitrate, seed=args.seed,
                  eds_path=args.eds, bus_kwargs=dict(args.bus_option))
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
        rig.start()
    except (ParameterError, SceneError) as exc:
        print(f"node-sim: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. an unreadable scene file
        print(f"node-sim: error: {exc}", file=sys.stderr)
        return 2
    try:
        print(f"node-sim: ready: {scene.n} nodes of scene {scene.name!r} on {args.interface} "
              f"channel(s) {', '.join(rig.channel_names)}", flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        rig.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
