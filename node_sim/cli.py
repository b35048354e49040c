"""``node-sim``: start every node twin of a scene on a CAN bus and run until stopped (the taxel
or patch nodes, and the gripper drive of a ``[gripper]`` table: ``docs/gripper-drive.md``).

    node-sim --scene scenes/matrix57.toml [-i INTERFACE] [-c CH[,CH]] [-b BITRATE]
             [--bus-kwargs KEY=VALUE ...] [--seed S] [--serve 0-3]

The bus flags are python-can's own (``can.cli.add_bus_arguments``: ``-i/--interface``,
``-c/--channel``, ``-b/--bitrate``, ``--fd``, ``--data-bitrate``, ``--timing``,
``--bus-kwargs``); what no flag gives comes from python-can's configuration as for ``can.Bus``
(``can.util.load_config``: ``CAN_INTERFACE``/``CAN_CHANNEL``/``CAN_BITRATE``/``CAN_CONFIG``,
``~/.canrc`` ...). No interface anywhere exits 2 saying how to give one (a ``virtual`` bus in
its own process reaches nobody). One bus per scene channel (``bus.channels``): ``-c a,b`` (or
``-c a -c b``) gives one bus channel per scene channel (default: the scene's channel names).
``-b`` takes 125k..1M (``500k``, ``1M`` or a number); ``--bus-option KEY=VALUE`` (repeatable)
is the older spelling of ``--bus-kwargs``. Prints one "ready" line on stdout once every node
(and the drive) has sent its boot-up, then runs until SIGINT/SIGTERM and shuts down cleanly (exit 0). A bad
scene, an unknown interface, a bit rate out of range, a channel that cannot be opened or a
missing EDS exit 2 with one line.

``--truth-log FILE`` (a scene with ``[gripper]`` and ``[grasp]``, whose drive this process serves;
else exit 2): the grasp world's ground truth, one JSON line per world step (``docs/grasp-world.md``),
flushed per line. ``FILE`` is opened before the twins start and written in place: a regular file
is truncated (not renamed, so it can be followed while node-sim runs), a FIFO, device or
``/dev/stdout`` is written, never replaced nor removed (``taxel_net.outputs.OutputPath``); a
directory, or the scene file itself (or its taxels_file, ``--eds``), exits 2 in one line
(``taxel_net.outputs.check_distinct_paths``). A write that fails (a reader that went away) is reported once on stderr and
ends the log, not the twins.

``--serve`` shards a scene over several processes (or hosts): this one runs only the nodes of
the listed scene channels (indices into ``bus.channels``, ``0-3`` or ``0,2,5``) and opens only
their buses; ``-c`` still names one bus channel per scene channel. The readings are the
scene's (``node_sim.physics``, a function of scene and cycle), so shards agree with each
other and with a single process.

The bit-rate parsing and the adding-up ``-c`` come from ``taxel_net.buscli``, which the fusion
centre's commands use too (the twins import nothing from the centre).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time

import can

from taxel_net.buscli import BITRATE_RANGE, DATA_BITRATE_MAX, ChannelsAction, channel_indices, parse_bitrate
from taxel_net.errors import ParameterError, SceneError, UsageError

from . import od as odx


SEED_MAX = 2**63 - 1   # the scene's [scene] seed range (taxel_net.scene)


def parse_seed(text: str) -> int:
    """``--seed``: ASCII digits, 0..2^63-1 (the scene's rule; numpy's generators refuse a negative seed)."""
    if not (text.isascii() and text.isdigit()) or int(text) > SEED_MAX:
        raise argparse.ArgumentTypeError(f"{text!r}: an integer 0..2^63-1 (the scene's [scene] seed range)")
    return int(text)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("taxel-can")
    except PackageNotFoundError:  # a checkout that was never installed
        return "unknown (not installed)"


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    import can.cli

    p = _Parser(prog="node-sim", description="Run a scene's CANopen taxel node twins on a CAN bus.")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    p.add_argument("--scene", required=True, help="scene file (TOML, docs/scene-format.md)")
    can.cli.add_bus_arguments(p)
    for action in p._actions:  # noqa: SLF001 - adjust python-can's actions in place
        if action.dest == "channel":
            action.__class__ = ChannelsAction
            action.help = ("bus channel, e.g. can0, 239.74.163.2 (udp_multicast); one per scene channel: "
                           "-c can0,can1 (default: python-can's configuration, else the scene's channel names)")
        elif action.dest in ("bitrate", "data_bitrate"):
            action.type = parse_bitrate
            if action.dest == "bitrate":
                action.help = (f"nominal bit rate {BITRATE_RANGE[0]}..{BITRATE_RANGE[1]} bit/s: 125k, 250k, 500k, "
                               "800k, 1M or a number (default: python-can's configuration, else the interface's)")
    p.add_argument("--bus-option", action="append", default=[], metavar="KEY=VALUE",
                   help="one can.Bus keyword argument (repeatable): the older spelling of --bus-kwargs")
    p.add_argument("--seed", type=parse_seed, default=None,
                   help="noise seed, an integer 0..2^63-1 as the scene's [scene] seed (default: the scene's)")
    p.add_argument("--serve", type=parse_channel_indices, default=None, metavar="CHANNELS",
                   help="run only the nodes of these scene channels (indices into bus.channels: 0-3 or 0,2,5); "
                        "shards one scene over several node-sim processes (default: every channel)")
    p.add_argument("--truth-log", default=None, metavar="FILE",
                   help="write the grasp world's ground truth as JSON lines, one per world step (a scene with "
                        "[gripper] and [grasp]; a regular file is written in place, flushed per line; a FIFO or "
                        "device such as /dev/stdout is never replaced)")
    p.add_argument("--eds", default=str(odx.EDS_PATH), help=argparse.SUPPRESS)
    return p


def _check_bitrate(value, source: str) -> int:
    if isinstance(value, str):
        try:
            value = parse_bitrate(value)
        except argparse.ArgumentTypeError as exc:
            raise ParameterError(source, value, str(exc)) from None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) \
            or not BITRATE_RANGE[0] <= value <= BITRATE_RANGE[1]:
        raise ParameterError(source, value, f"must be a classic CAN bit rate in {BITRATE_RANGE[0]}..{BITRATE_RANGE[1]} "
                                            "bit/s (125k, 250k, 500k, 800k, 1M)")
    return int(value)


def resolve_bus(args, scene) -> tuple[str, list | None, int | None, dict]:
    """(interface, channels, bitrate, other can.Bus keywords): the flags, then python-can's
    configuration (``can.util.load_config``, as ``can.Bus`` reads it)."""
    import json
    import os

    from can.util import cast_from_string, load_config, load_environment_config, load_file_config

    given = {key: getattr(args, key) for key in ("interface", "channel", "bitrate", "fd", "data_bitrate", "timing")
             if key in args}
    kwargs: dict = {}
    for option in args.bus_option:
        key, sep, value = option.partition("=")
        if not sep or not key.isidentifier():
            raise ParameterError("--bus-option", option, "expected KEY=VALUE (e.g. port=43113)")
        kwargs[key] = cast_from_string(value)
    kwargs.update(getattr(args, "bus_kwargs", None) or {})
    given = {**kwargs, **given}
    if "bitrate" in given:
        _check_bitrate(given["bitrate"], "--bitrate")
    if given.get("data_bitrate") is not None:
        if not given.get("fd"):
            raise ParameterError("--data-bitrate", given["data_bitrate"], "only with --fd")
        if not given.get("bitrate", BITRATE_RANGE[0]) <= given["data_bitrate"] <= DATA_BITRATE_MAX:
            raise ParameterError("--data-bitrate", given["data_bitrate"],
                                 f"must lie between the nominal bit rate and {DATA_BITRATE_MAX} bit/s")
    try:
        env = load_environment_config()
        files = load_file_config()
    except json.JSONDecodeError as exc:
        raise ParameterError("CAN_CONFIG", os.environ.get("CAN_CONFIG", "")[:60], f"not a JSON object ({exc})") from None
    except Exception as exc:  # noqa: BLE001 - a config file configparser cannot read
        raise ParameterError("python-can config file", type(exc).__name__, " ".join(str(exc).split())) from None
    for values, source in ((given, "--interface"), (can.rc, "can.rc"),
                           (env, "CAN_INTERFACE" if os.environ.get("CAN_INTERFACE") else "CAN_CONFIG"),
                           (files, "python-can config file")):
        interface = values.get("interface") or values.get("bustype")
        if interface:
            break
    else:
        raise ParameterError("interface", None, "no CAN interface given: use -i/--interface (e.g. -i socketcan "
                             "-c can0), or python-can's configuration: CAN_INTERFACE/CAN_CHANNEL/CAN_BITRATE, or an "
                             "[default] section with interface = ... in ~/.canrc")
    if interface not in can.interfaces.VALID_INTERFACES:
        raise ParameterError(f"{source}: interface", interface, "unknown python-can interface (known: "
                             + ", ".join(sorted(can.interfaces.VALID_INTERFACES)) + ")")
    try:
        config = dict(load_config(config=dict(given)))
    except Exception as exc:  # noqa: BLE001 - a bad port in a config file...
        raise ParameterError("python-can configuration", type(exc).__name__, " ".join(str(exc).split())) from None
    config.pop("interface")
    channel = config.pop("channel", None)
    bitrate = config.pop("bitrate", None)
    if bitrate is not None:
        bitrate = _check_bitrate(bitrate, "--bitrate" if "bitrate" in given else "bitrate (python-can configuration)")
    channels = None
    if channel is not None:
        channels = [c.strip() for c in channel.split(",")] if isinstance(channel, str) else [channel]
        if len(channels) != len(scene.bus.channels):
            raise ParameterError("channel", channel, f"scene {scene.name!r} has {len(scene.bus.channels)} channel(s) "
                                 f"{list(scene.bus.channels)}: give one bus channel for each, comma-separated")
    return interface, channels, bitrate, config


def parse_channel_indices(text: str) -> list[int]:
    """argparse type of ``--serve``: ``0-3``, ``0,2,5`` or a mix (``0-2,7``)."""
    try:
        return channel_indices(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: scene channel indices such as 0-3 or 0,2,5") from None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # a bus whose constructor failed is later reported by python-can as "not properly shut
    # down": the one-line error below already says why
    logging.getLogger("can.bus").setLevel(logging.ERROR)
    stop = threading.Event()
    truth_log = rig = None

    def on_signal(signum, frame):
        stop.set()

    try:
        # Ctrl-C during the start (a FIFO's reader awaited) is KeyboardInterrupt -> exit 130 below,
        # whatever disposition was inherited: a parent that ignores SIGINT (a script's background
        # job, a test runner's worker) left it ignored until on_signal below replaced it
        signal.signal(signal.SIGINT, signal.default_int_handler)
    except ValueError:  # main() called off the main thread (in-process callers): left as it is
        pass
    try:
        from taxel_net.scene import load_scene

        from taxel_net.json_lines import is_fifo
        from taxel_net.outputs import check_distinct_paths, scene_inputs

        from .rig import Rig

        # a truth log over the scene or the EDS: one line, before anything is opened
        check_distinct_paths([*scene_inputs(args.scene), ("--eds", args.eds)], [("--truth-log", args.truth_log)])
        scene = load_scene(args.scene)
        odx.check_eds(args.eds, "taxel node")
        interface, channels, bitrate, bus_kwargs = resolve_bus(args, scene)
        rig = Rig(scene, interface=interface, channel=channels, bitrate=bitrate, seed=args.seed,
                  eds_path=args.eds, bus_kwargs=bus_kwargs, serve_channels=args.serve)
        if args.truth_log is not None:
            if is_fifo(args.truth_log):  # opening it waits for a reader: say so, not a silent hang
                print(f"node-sim: --truth-log {args.truth_log!r} is a FIFO: waiting for its reader", flush=True)
            truth_log = TruthLog.open(args.truth_log, scene, rig)
            rig.add_truth_callback(truth_log.write)
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
        rig.start()
    except (ParameterError, SceneError, UsageError, OSError) as exc:  # OSError: e.g. an unreadable scene file
        if truth_log is not None:
            truth_log.close()
        print(f"node-sim: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C before the handlers were set (a FIFO's reader awaited): no traceback
        if truth_log is not None:
            truth_log.close()
        if rig is not None:
            rig.stop()
        print("node-sim: interrupted before it was ready", file=sys.stderr)
        return 130
    try:
        served = [rig.channel_names[i] for i in rig.served]
        taxels = sum(1 for t in scene.taxels if t.channel in rig.served)
        hosts = f"{len(rig.nodes)} patch nodes ({taxels} taxels)" if scene.bus.patch_nodes else f"{taxels} nodes"
        if rig.gripper is not None:
            hosts += f" and gripper drive {rig.gripper.node_id}"
            if rig.world is not None:
                hosts += " with the grasp world"
        print(f"node-sim: ready: {hosts} of scene {scene.name!r} on {interface} "
              f"channel(s) {', '.join(served)}", flush=True)
        # sleep and look, never stop.wait(): a signal handled while this thread is inside
        # Event.wait (holding the event's condition lock) ran stop.set(), which takes that same
        # lock - a deadlock (node-sim still running 30 s after SIGINT in a CI run: the stacks
        # showed on_signal -> Event.set -> Condition.__enter__ under Event.wait)
        while not stop.is_set():
            time.sleep(0.2)
    finally:
        rig.stop()
        if truth_log is not None:
            truth_log.close()
    return 0


class TruthLog:
    """``--truth-log FILE``: the world's records as JSON lines (module docstring), written by
    :class:`taxel_net.json_lines.JsonLinesWriter` (NaN refused, as the log's reader does; a failed
    write ends the file at its last whole line, said once)."""

    def __init__(self, path, writer):
        self.path = path
        self.writer = writer
        self._lock = threading.Lock()

    @classmethod
    def open(cls, path: str, scene, rig) -> "TruthLog":
        from taxel_net.json_lines import JsonLinesWriter
        from taxel_net.outputs import OutputPath

        from .world_runner import has_world

        if not has_world(scene):
            raise UsageError(f"--truth-log {path!r}: scene {scene.name!r} has no grasp world (it needs both a "
                             "[gripper] and a [grasp] table)")
        if not rig.runs_world:
            raise UsageError(f"--truth-log {path!r}: this process does not serve the gripper drive's channel "
                             f"{scene.gripper.channel} (--serve): the world runs beside the drive")
        out = OutputPath(path, option="--truth-log")   # a directory: refused in one line
        # in place (out.path, not a partial file): a FIFO / device is never replaced
        return cls(path, JsonLinesWriter(out.path, _truth_line, option="--truth-log"))

    def write(self, record: dict) -> None:
        with self._lock:
            writer = self.writer
            if writer.write(record) or writer.new_failure is None:
                return
            kind, error = writer.new_failure
            end = "no more truth lines" if kind == "io" else "the line is left out (further ones only counted)"
            print(f"node-sim: --truth-log {self.path!r}: write failed ({error}); {end}", file=sys.stderr, flush=True)

    def close(self) -> None:
        with self._lock:
            self.writer.close()
            if self.writer.failure:
                print(f"node-sim: {self.writer.failure}", file=sys.stderr, flush=True)


def _truth_line(record: dict) -> bytes:
    import json

    return json.dumps(record, separators=(",", ":"), allow_nan=False).encode()


if __name__ == "__main__":
    sys.exit(main())
