"""``fusion-center dcf``: the CiA 306 device configuration file (DCF) of a scene's nodes.

A DCF is the node's EDS plus what commissioning gave this one device: a
``[DeviceComissioning]`` section (NodeID, NodeName, Baudrate in kbit/s, NetNumber,
NetworkName, CANopenManager, LSS_SerialNumber) and a ``ParameterValue=`` in the section of
every object the fusion centre configures, with the value it writes over SDO
(``fusion_center.service.master.node_configuration``: ζ, N_i, kind, x, y, calibration,
heartbeat, SYNC counter and window, TPDO parameters and mapping; the last value written
where an object is written twice, e.g. a TPDO COB-ID made invalid, then valid).

The DCF is written from the EDS text itself, every line kept: the tools that take the EDS as
shipped take the DCF within their documented limits (canopen's ``import_od`` reads the
commissioning and every ``ParameterValue``; eds-utils ignores ``ParameterValue``; objdictgen
refuses ``[DeviceComissioning]``, docs/node-twins.md).

    fusion-center dcf --scene S --node N -o FILE.dcf     (N, or C:N for a node of channel C > 0)
    fusion-center dcf --scene S --all -o DIR             (one file per node)
"""

from __future__ import annotations

import argparse
import configparser
import re
import struct
from pathlib import Path

HELP = "write the CiA 306 DCF of a scene's node (--node N) or of every node (--all) with its configured values"

REAL_TYPES = (0x0008, 0x0011)          # REAL32, REAL64
UNSIGNED32 = 0x0007
_SECTION = re.compile(r"^\[([^\]]+)\]\s*$")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True, help="scene file (TOML) or a bundled scene's name")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--node", metavar="N", help="node-ID (C:N for a node of scene channel C > 0)")
    which.add_argument("--all", action="store_true", help="every node of the scene: -o names a directory")
    parser.add_argument("-o", "--output", required=True, metavar="PATH",
                        help="the DCF file (--node; '-' for stdout) or the directory (--all; created if missing)")
    parser.add_argument("--eds", default=None, help=argparse.SUPPRESS)


def node_index(scene, text: str) -> int:
    """Scene index of ``--node`` ``N`` (channel 0) or ``C:N``; UsageError naming the value."""
    from taxel_net.errors import UsageError
    from taxel_net.scene import taxel_index

    channel, sep, node = text.rpartition(":")
    try:
        node_id, ch = int(node, 0), int(channel, 0) if sep else 0
    except ValueError:
        raise UsageError(f"--node {text!r}: expected a node-ID N or C:N (scene channel C)") from None
    try:
        return taxel_index(scene, node_id, ch)
    except KeyError:
        where = f"channel {ch}" if sep else "channel 0 (use C:N for another channel)"
        raise UsageError(f"--node {text!r}: no node {node_id} on {where} of scene {scene.name!r}") from None


def file_name(scene, index: int) -> str:
    """``<scene>_node017.dcf``, or ``<scene>_ch1_node017.dcf`` off channel 0."""
    t = scene.taxels[index]
    channel = f"_ch{t.channel}" if t.channel else ""
    return f"{scene.name}{channel}_node{t.node_id:03d}.dcf"


def configured_values(scene, index: int) -> dict[tuple[int, int], object]:
    """(index, sub-index) -> the value the centre leaves there (its last SDO write)."""
    from ..service.master import node_configuration

    values: dict[tuple[int, int], object] = {}
    for obj, sub, value in node_configuration(scene, index):
        values.pop((obj, sub), None)  # re-inserted: objects in the order of their last write
        values[(obj, sub)] = value
    return values


def _format(value, data_type: int) -> str:
    if data_type in REAL_TYPES:
        value = float(value)
        if data_type == 0x0008:  # the REAL32 the node stores, written as the shortest decimal of it
            value = struct.unpack("<f", struct.pack("<f", value))[0]
            text = repr(value)
            for digits in range(1, 10):
                short = f"{value:.{digits}g}"
                if struct.pack("<f", float(short)) == struct.pack("<f", value):
                    text = short
                    break
            return text
        return repr(value)
    if data_type == UNSIGNED32:
        return f"0x{int(value):08X}"
    return str(int(value))


def dcf_text(scene, index: int, eds_text: str, name: str | None = None) -> str:
    """The DCF of taxel ``index`` of ``scene``, made from the EDS text ``eds_text``."""
    from taxel_net.errors import UsageError

    from ..service.lss import expected_serial

    t = scene.taxels[index]
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), strict=False)
    parser.optionxform = str
    parser.read_string(eds_text)
    sections = {s.upper(): s for s in parser.sections()}
    if "DEVICECOMISSIONING" in sections:
        raise UsageError("EDS already has a [DeviceComissioning] section: give the EDS, not a DCF")
    values: dict[str, list[str]] = {}
    for (obj, sub), value in configured_values(scene, index).items():
        section = sections.get(f"{obj:04X}SUB{sub:X}")
        if section is None and sub == 0:
            section = sections.get(f"{obj:04X}")
        if section is None or not parser.has_option(section, "DataType"):
            raise UsageError(f"EDS has no entry 0x{obj:04X}:{sub} (the node's configuration writes it)")
        data_type = int(parser.get(section, "DataType"), 0)
        values[section.upper()] = [f"ParameterValue={_format(value, data_type)}"]
    label = t.node_id if t.channel == 0 else f"{t.channel}:{t.node_id}"
    commissioning = [
        "[DeviceComissioning]",
        f"NodeID={t.node_id}",
        f"NodeName=taxel {label} ({t.kind})",
        f"Baudrate={scene.bus.bitrate // 1000}",
        f"NetNumber={t.channel + 1}",
        f"NetworkName={scene.bus.channels[t.channel]}",
        "CANopenManager=0",
        f"LSS_SerialNumber=0x{expected_serial(scene, t):08X}",
        "",
    ]
    out: list[str] = []
    current: str | None = None
    pending: list[str] = []  # lines to add at the end of the current section

    def close_section() -> None:
        # after the section's last non-blank line
        tail = []
        while out and out[-1].strip() == "":
            tail.append(out.pop())
        out.extend(pending)
        out.extend(reversed(tail))

    for line in eds_text.splitlines():
        m = _SECTION.match(line)
        if m:
            close_section()
            current = m.group(1)
            pending = list(values.get(current.upper(), ()))
            if current.upper() == "DUMMYUSAGE":
                out.extend(commissioning)
        elif current is not None and current.upper() == "FILEINFO":
            key = line.partition("=")[0].strip()
            if key == "FileName":
                out.append(f"FileName={name or 'node.dcf'}")
                line = f"LastEDS={line.partition('=')[2].strip()}"  # CiA 306: the EDS it comes from
            elif key == "Description":
                line = f"{line} - DCF of node {label} of scene {scene.name}"
        out.append(line)
    close_section()
    if "DUMMYUSAGE" not in sections:
        out.append("")
        out.extend(commissioning)
    return "\n".join(out).rstrip("\n") + "\n"


def run(args) -> int:
    import sys

    from taxel_net.errors import UsageError
    from taxel_net.resources import eds_path
    from taxel_net.scene import load_scene

    scene = load_scene(args.scene)
    source = Path(args.eds) if args.eds else eds_path()
    try:
        eds_text = source.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"EDS file {str(source)!r} cannot be read: {exc}") from None
    out = Path(args.output)
    try:
        if args.all:
            if out.exists() and not out.is_dir():
                raise UsageError(f"-o {args.output!r}: not a directory (--all writes one DCF per node)")
            out.mkdir(parents=True, exist_ok=True)
            for index in range(scene.n):
                name = file_name(scene, index)
                (out / name).write_text(dcf_text(scene, index, eds_text, name), encoding="utf-8")
            print(f"{scene.n} DCFs of scene {scene.name!r} written to {out}")
            return 0
        index = node_index(scene, args.node)
        if args.output == "-":
            sys.stdout.write(dcf_text(scene, index, eds_text, file_name(scene, index)))
            return 0
        if out.is_dir():
            out = out / file_name(scene, index)
        text = dcf_text(scene, index, eds_text, out.name)
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"-o {args.output!r}: cannot write: {exc.strerror or exc}") from None
    t = scene.taxels[index]
    print(f"DCF of node {args.node} ({t.kind}) of scene {scene.name!r} written to {out}: "
          f"{text.count('ParameterValue=')} parameter values")
    return 0
