"""The ``fusion-center`` sub-commands (one module each) and the bus plumbing they share.

Bus flags are python-can's own, added by ``can.cli.add_bus_arguments``: ``-i/--interface``,
``-c/--channel``, ``-b/--bitrate``, ``--fd``, ``--data-bitrate``, ``--timing``,
``--bus-kwargs KEY=VALUE ...``. What no flag gives comes from python-can's configuration,
exactly as for ``can.Bus()`` or ``python -m can.logger`` (``can.util.load_config``: the
``CAN_INTERFACE``/``CAN_CHANNEL``/``CAN_BITRATE``/``CAN_CONFIG`` environment variables, then
``~/can.conf``, ``/etc/can.conf``, ``~/.can``, ``~/.canrc``). The result is not handed to
``can.cli.create_bus_from_namespace``: the fusion centre opens one bus per scene channel
itself (``FusionService``), so :func:`resolve_bus` returns the settings it needs.

Additions, for scenes with several channels and for older command lines: ``-c a,b`` (or
``-c a -c b``) gives one bus channel per scene channel; ``-b`` also takes ``125k``/``500k``/
``1M``; ``--bus-option KEY=VALUE`` (repeatable) is the older spelling of ``--bus-kwargs``.
Imports of python-can stay inside the functions: importing this package loads no CAN library.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field

from taxel_net.buscli import BITRATE_RANGE, DATA_BITRATE_MAX, ChannelsAction, parse_bitrate  # noqa: F401
CONFIG_HELP = ("-i/--interface (e.g. -i socketcan -c can0), or python-can's configuration: "
               "CAN_INTERFACE/CAN_CHANNEL/CAN_BITRATE, or an [default] section with interface = ... "
               "in ~/.canrc")


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """python-can's bus flags (``can.cli.add_bus_arguments``) plus the additions above."""
    import can.cli

    can.cli.add_bus_arguments(parser)
    for action in parser._actions:  # noqa: SLF001 - adjust python-can's actions in place
        if action.dest == "channel":
            action.__class__ = ChannelsAction
            action.help = ("bus channel, e.g. can0 (socketcan), PCAN_USBBUS1 (pcan), 239.74.163.2 (udp_multicast); "
                           "a scene with several channels takes one per scene channel: -c can0,can1 "
                           "(default: python-can's configuration, else the scene's channel names)")
        elif action.dest == "bitrate":
            action.type = parse_bitrate
            action.help = (f"nominal bit rate, {BITRATE_RANGE[0]}..{BITRATE_RANGE[1]} bit/s: 125k, 250k, 500k, "
                           "800k, 1M or a number (default: python-can's configuration, else the interface's)")
        elif action.dest == "data_bitrate":
            action.type = parse_bitrate
            action.help = f"CAN FD data-phase bit rate (with --fd), up to {DATA_BITRATE_MAX // 1_000_000}M"
    parser.add_argument("--bus-option", action="append", default=[], metavar="KEY=VALUE",
                        help="one can.Bus keyword argument (repeatable): the older spelling of --bus-kwargs")


@dataclass
class BusChoice:
    """What to open: ``interface``, ``channels`` (one per scene channel, None: the scene's
    names), ``bitrate`` (None: not passed), further ``can.Bus`` keyword arguments, and where
    the interface came from (for the summary)."""
    interface: str
    channels: list | None
    bitrate: int | None
    kwargs: dict = field(default_factory=dict)
    source: str = "command line"

    def describe(self, channel_names) -> str:
        """``udp_multicast 239.74.163.2 (command line)``: the bus of a run, for its summary."""
        rate = f", {self.bitrate // 1000} kbit/s" if self.bitrate else ""
        return f"{self.interface} {', '.join(map(str, channel_names))}{rate} ({self.source})"


def _flag_values(args) -> dict:
    from can.util import cast_from_string

    given = {key: getattr(args, key) for key in ("interface", "channel", "bitrate", "fd", "data_bitrate", "timing")
             if key in args}
    kwargs: dict = {}
    for option in getattr(args, "bus_option", None) or []:
        key, sep, value = option.partition("=")
        if not sep or not key.isidentifier():
            from taxel_net.errors import UsageError

            raise UsageError(f"--bus-option {option!r}: expected KEY=VALUE (e.g. port=43113)")
        kwargs[key] = cast_from_string(value)
    kwargs.update(getattr(args, "bus_kwargs", None) or {})
    return {**kwargs, **given}


def check_bitrate_flags(args) -> None:
    """Range of ``-b``/``--data-bitrate`` given on the command line (before anything is loaded)."""
    from taxel_net.errors import UsageError

    bitrate = getattr(args, "bitrate", None)
    if bitrate is not None:
        check_bitrate(bitrate, "--bitrate")
    data = getattr(args, "data_bitrate", None)
    if data is not None:
        if not getattr(args, "fd", False):
            raise UsageError(f"--data-bitrate {data}: only with --fd (the scenes' nodes speak classic CAN; "
                             "a CAN FD bus carries their frames with --fd)")
        low = bitrate or BITRATE_RANGE[0]
        if not low <= data <= DATA_BITRATE_MAX:
            raise UsageError(f"--data-bitrate {data}: must lie in {low}..{DATA_BITRATE_MAX} bit/s "
                             "(at least the nominal bit rate)")


def check_bitrate(value, source: str) -> int:
    from taxel_net.errors import UsageError

    if isinstance(value, str):
        try:
            value = parse_bitrate(value)
        except argparse.ArgumentTypeError as exc:
            raise UsageError(f"{source} {value!r}: {exc}") from None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) \
            or not BITRATE_RANGE[0] <= value <= BITRATE_RANGE[1]:
        raise UsageError(f"{source} {value}: must be a classic CAN bit rate in {BITRATE_RANGE[0]}..{BITRATE_RANGE[1]} "
                         "bit/s (125k, 250k, 500k, 800k, 1M)")
    return int(value)


CONFIG_FILES = "a python-can config file (~/can.conf, /etc/can.conf, ~/.can, ~/.canrc)"


def _config_source(key: str, given: dict) -> tuple[object, str]:
    """The value python-can's ``load_config`` takes for ``key`` and where from, read with its
    own functions in its order: command line (the given config), ``can.rc``, ``CAN_*``
    environment variables (``CAN_CONFIG`` JSON under them), the config files."""
    import json

    import can
    from can.util import load_environment_config, load_file_config

    env_name = {"interface": "CAN_INTERFACE", "channel": "CAN_CHANNEL", "bitrate": "CAN_BITRATE"}.get(key, "")
    sources = [(given, "command line"), (can.rc, "can.rc"),
               (lambda: load_environment_config(),
                env_name if os.environ.get(env_name) else "CAN_CONFIG"),
               (lambda: load_file_config(), CONFIG_FILES)]
    for source, name in sources:
        try:
            values = source() if callable(source) else source
        except json.JSONDecodeError as exc:
            from taxel_net.errors import UsageError

            raise UsageError(f"CAN_CONFIG {os.environ.get('CAN_CONFIG', '')[:60]!r}: not a JSON object ({exc})") from None
        except Exception as exc:  # noqa: BLE001 - e.g. a config file configparser cannot read
            from taxel_net.errors import UsageError

            raise UsageError(f"{name}: " + " ".join(f"{type(exc).__name__}: {exc}".split())) from None
        value = values.get(key) or (values.get("bustype") if key == "interface" else None)
        if value not in (None, ""):
            return value, name
    return None, ""


def resolve_bus(args, scene, *, required: bool = True) -> BusChoice | None:
    """Flags > python-can's configuration (``can.util.load_config``), as ``can.Bus`` reads it.

    No interface anywhere: :class:`UsageError` saying how to give one (``required``) or None.
    An unknown interface, a bad ``CAN_CONFIG`` or config file, or a bit rate out of range from
    any source: :class:`UsageError` naming the source and the value."""
    import can
    from can.util import load_config

    from taxel_net.errors import UsageError

    given = _flag_values(args)
    value, source = _config_source("interface", given)
    if value is None:
        if required:
            raise UsageError(f"no CAN interface given: use {CONFIG_HELP} "
                             "(`fusion-center demo` runs the node twins on its own virtual bus)")
        return None
    if value not in can.VALID_INTERFACES:
        raise UsageError(f"{source}: interface {value!r}: not a python-can interface (known: "
                         + ", ".join(sorted(can.VALID_INTERFACES)) + ")")
    try:
        config = dict(load_config(config=dict(given)))
    except Exception as exc:  # noqa: BLE001 - CAN_CONFIG not JSON, a bad port in a config file...
        raise UsageError("python-can configuration (CAN_* environment variables, config files): "
                         + " ".join(f"{type(exc).__name__}: {exc}".split())) from None
    interface = config.pop("interface")
    channel = config.pop("channel", None)
    bitrate = config.pop("bitrate", None)
    if bitrate is not None:
        where = _config_source("bitrate", given)[1]
        bitrate = check_bitrate(bitrate, "--bitrate" if where == "command line" else f"{where}: bitrate")
    channels = None
    if channel is not None:
        channels = [c.strip() for c in channel.split(",")] if isinstance(channel, str) else [channel]
        wanted = len(scene.bus.channels)
        if len(channels) != wanted:
            raise UsageError(f"--channel {channel!r}: scene {scene.name!r} has {wanted} channel(s) "
                             f"{list(scene.bus.channels)}: give one bus channel for each, comma-separated "
                             f"(channel from {_config_source('channel', given)[1]})")
    return BusChoice(interface=interface, channels=channels, bitrate=bitrate, kwargs=config,
                     source="python-can config file" if source == CONFIG_FILES else source)


def check_output_paths(args, inputs=(), outputs=()) -> None:
    """Refuse an output that names an input or another output (one line, exit 2), before
    anything is written: :func:`taxel_net.outputs.check_distinct_paths` over the command's
    ``--scene`` (its file and taxels_file), ``--zenoh-config`` and the given ``inputs``, and its
    ``--json-lines``, ``--log``, ``--mcap``, ``--ros2-bag`` and the given ``outputs`` (each an
    ``(option, path)`` pair; options the command does not have are skipped)."""
    from taxel_net.outputs import check_distinct_paths, scene_inputs

    found_inputs = list(scene_inputs(args.scene)) if getattr(args, "scene", None) else []
    found_inputs += [(option, getattr(args, name, None)) for option, name in (("--zenoh-config", "zenoh_config"),)]
    found_inputs += list(inputs)
    found_outputs = [(option, getattr(args, name, None)) for option, name in
                     (("--json-lines", "json_lines"), ("--log", "log"), ("--mcap", "mcap"), ("--ros2-bag", "ros2_bag"))]
    check_distinct_paths(found_inputs, found_outputs + list(outputs))
