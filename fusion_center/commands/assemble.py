"""``fusion-center assemble``: the cycle assembler of a group of scene channels, in its own
process or host, feeding the fuser (``fusion-center run --assemblers HOST:PORT``).

    fusion-center assemble --scene S --serve 0-3 -i udp_multicast -c G0,G1,... --fuser HOST:PORT

It opens the buses of the served channels only (``-c`` lists one bus channel per scene
channel, as for ``run``), listens (it sends nothing on the buses), assembles every SYNC
cycle of its channels and sends it to the fuser (:mod:`fusion_center.service.assemblers`).
It ends when the fuser ends (exit 0), on Ctrl-C / SIGTERM (exit 0), or when the fuser went
away without saying so and was not back within ``--reconnect-timeout`` (exit 1): until then it
keeps assembling its buses (the cycles closed meanwhile are not sent) and connects again.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

HELP = "assemble the SYNC cycles of some scene channels and feed them to a fuser (run --assemblers)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from . import add_bus_arguments
    from .run import add_mode_argument

    parser.add_argument("--scene", required=True, metavar="FILE",
                        help="scene file or bundled scene name (the fuser's scene)")
    add_bus_arguments(parser)
    parser.add_argument("--serve", required=True, metavar="CHANNELS",
                        help="scene channel indices this assembler serves: 0-3, 0,2,5 or a mix")
    parser.add_argument("--fuser", required=True, metavar="ENDPOINT",
                        help="the Zenoh endpoint `fusion-center run --assemblers ENDPOINT` listens on: HOST:PORT "
                             "(tcp) or PROTO/HOST:PORT such as tls/robot:7447 (on loopback the key of this user's "
                             "fuser is found by itself; beyond loopback, or a fuser of another user: the same "
                             "FUSION_CENTER_AUTHKEY on both sides)")
    parser.add_argument("--connect-timeout", type=float, default=30.0, metavar="S",
                        help="seconds to keep trying to reach the fuser (default 30)")
    parser.add_argument("--reconnect-timeout", type=float, default=60.0, metavar="S",
                        help="when the link to the fuser breaks without its goodbye: seconds to keep "
                             "trying to connect again before exiting 1 (default 60)")
    add_mode_argument(parser)
    from ..service.zenoh_config import add_arguments as add_zenoh_arguments

    add_zenoh_arguments(parser, publication=False)


def parse_serve(text: str) -> list[int]:
    from taxel_net.buscli import channel_indices
    from taxel_net.errors import UsageError

    try:
        return channel_indices(text)
    except ValueError:
        raise UsageError(f"--serve {text!r}: expected scene channel indices such as 0-3 or 0,2,5") from None


def run(args) -> int:
    import math

    from taxel_net.errors import UsageError
    from taxel_net.scene import load_scene
    from ..service.assembler_parts import check_serve
    from ..service.assembler_process import AssemblerProcess
    from ..service.zenoh_config import endpoint
    from . import check_bitrate_flags, resolve_bus
    from .run import apply_mode, setup_logging

    setup_logging()
    fuser = endpoint(args.fuser, "--fuser")
    if not (math.isfinite(args.connect_timeout) and 0 < args.connect_timeout <= 3600):
        raise UsageError(f"--connect-timeout {args.connect_timeout}: must be a number of seconds in (0, 3600]")
    if not (math.isfinite(args.reconnect_timeout) and 0 < args.reconnect_timeout <= 86400):
        raise UsageError(f"--reconnect-timeout {args.reconnect_timeout}: must be a number of seconds in (0, 86400]")
    serve = parse_serve(args.serve)
    check_bitrate_flags(args)
    scene = apply_mode(load_scene(args.scene), args.mode)
    serve = check_serve(serve, scene, args.serve)
    bus = resolve_bus(args, scene)
    process = AssemblerProcess(scene, serve, fuser=fuser, interface=bus.interface, channel_names=bus.channels,
                               bitrate=bus.bitrate, bus_kwargs=bus.kwargs, reconnect_timeout_s=args.reconnect_timeout,
                               zenoh_config=args.zenoh_config)
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
    with process:
        process.connect(args.connect_timeout)
        lay = process.layout
        print(f"fusion-center assemble: ready: channel(s) {', '.join(process.channel_names)} "
              f"(scene channels {lay.name}, {len(lay.taxels)} taxels) of scene {scene.name!r} on {bus.interface}, "
              f"fuser {process.fuser}", flush=True)
        while not stop.is_set() and not process.closed.wait(0.2):
            pass
    counters = process.group.assembler.counters()
    print(f"fusion-center assemble: {process.parts_sent} cycles sent, {process.parts_unsent} not sent, "
          f"{process.events} frames, {process.reconnects} reconnects, {process.bad_messages} bad messages from "
          "the fuser; " + ", ".join(f"{k} {v}" for k, v in counters.items() if v), flush=True)
    if process.closed.is_set() and not process.bye and not stop.is_set():
        print(f"fusion-center assemble: {process.gave_up or 'the fuser went away'}", file=sys.stderr)
        return 1
    return 0
