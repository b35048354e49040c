"""``fusion-center dcf``: the CiA 306 device configuration file (DCF) of a scene's nodes.

A DCF is the node's EDS plus what commissioning gave this one device: a
``[DeviceComissioning]`` section (NodeID, NodeName, Baudrate in kbit/s, NetNumber,
NetworkName, CANopenManager, LSS_SerialNumber) and a ``ParameterValue=`` in the section of
every object the fusion centre configures, with the value it writes over SDO
(``fusion_center.service.node_config.node_configuration``: ζ, N_i, kind, x, y, calibration,
heartbeat, SYNC counter and window, TPDO parameters and mapping; the last value written
where an object is written twice, e.g. a TPDO COB-ID made invalid, then valid).

The DCF is written from the EDS text itself, every line kept: the tools that take the EDS as
shipped take the DCF within their documented limits (canopen's ``import_od`` reads the
commissioning and every ``ParameterValue``; eds-utils ignores ``ParameterValue``; objdictgen
refuses ``[DeviceComissioning]``, docs/node-twins.md).

One DCF per CANopen node, i.e. per device of :func:`taxel_net.patches.devices`. In a
one-taxel scene that is one per taxel (device k is taxel k), from ``eds/taxel_node.eds``. In a
patch scene (``[bus] patch_nodes = true``) it is one per patch node, from
``eds/taxel_patch.eds`` (``taxel_net.resources.patch_eds_path``), with the values of
``fusion_center.service.node_config.patch_configuration`` (with the detector arrays, as the master
writes them by default): ζ and N_i of every taxel (ARRAY entries, sections ``[2010subK]`` /
``[2011subK]`` with K in hex for the device's taxel K - 1), 0x2032 in raw mode, heartbeat,
0x1016, SYNC counter and window, and every TPDO's parameters and mapping. The patches' kind,
x and y (0x2012-0x2014) are no part of it: the master does not write them (the node keeps its
stored values). NodeName says ``patch node N (n taxels)``. LSS_SerialNumber is the serial
number the node reports in 0x1018:4: the patch twin reports its device's
(``node_sim.rig.identity_serial`` of its first taxel: scene, channel and node-ID, so the same
for each of its taxels), although its EDS says ``LSS_Supported=0`` (the scene loader refuses
LSS node-ID assignment with patch nodes): the key names the device's identity, which it has.

A scene with a ``[gripper]`` table has one more node, its CiA 402 gripper drive: ``--node`` with
the drive's node-ID (``C:N`` off channel 0) writes its DCF, and ``--all`` writes it beside the
taxels' (``<scene>_gripper_node032.dcf``), from ``eds/gripper_drive.eds``
(``taxel_net.resources.gripper_eds_path``) with the drive's start-up values
(``taxel_net.gripper.startup_values``: what the twin starts with, the ``[gripper]`` parameters,
0x1017 / 0x1019 / 0x1006 / 0x1016:1 / 0x1018:4) as ``ParameterValue``; NodeName says
``gripper drive N (CiA 402)``; LSS_SerialNumber is its 0x1018:4.

    fusion-center dcf --scene S --node N -o FILE.dcf     (N, or C:N for a node of channel C > 0)
    fusion-center dcf --scene S --all -o DIR             (one file per node)

A DCF that would be written over the scene file, its taxels_file or ``--eds`` (``-o`` itself, or a
file ``--all`` / a directory ``-o`` would hold) exits 2 in one line before anything is written
(``taxel_net.outputs.check_distinct_paths``).
"""

from __future__ import annotations

import argparse
import configparser
import re
import struct
from functools import lru_cache
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


_devices_of: list = [None, ()]  # the last scene and its devices (--all asks once per node)


def _devices(scene):
    from taxel_net.patches import devices

    if _devices_of[0] is not scene:
        _devices_of[:] = [scene, devices(scene)]
    return _devices_of[1]


def node_index(scene, text: str) -> int:
    """Device index (:func:`taxel_net.patches.devices`; the taxel's index in a one-taxel scene)
    of ``--node`` ``N`` (channel 0) or ``C:N``; UsageError naming the value."""
    from taxel_net.errors import UsageError

    channel, sep, node = text.rpartition(":")
    try:
        node_id, ch = int(node, 0), int(channel, 0) if sep else 0
    except ValueError:
        raise UsageError(f"--node {text!r}: expected a node-ID N or C:N (scene channel C)") from None
    for index, device in enumerate(_devices(scene)):
        if device.node_id == node_id and device.channel == ch:
            return index
    where = f"channel {ch}" if sep else "channel 0 (use C:N for another channel)"
    raise UsageError(f"--node {text!r}: no node {node_id} on {where} of scene {scene.name!r}")


def file_name(scene, index: int) -> str:
    """``<scene>_node017.dcf``, or ``<scene>_ch1_node017.dcf`` off channel 0 (node ``index``
    as :func:`node_index` numbers them)."""
    d = _devices(scene)[index]
    channel = f"_ch{d.channel}" if d.channel else ""
    return f"{scene.name}{channel}_node{d.node_id:03d}.dcf"


def configured_values(scene, index: int) -> dict[tuple[int, int], object]:
    """(index, sub-index) -> the value the centre leaves there (its last SDO write) in node
    ``index`` (:func:`node_index`): ``node_configuration`` of a one-taxel node,
    ``patch_configuration`` of a patch node."""
    from ..service.node_config import node_configuration, patch_configuration

    if scene.bus.patch_nodes:
        writes = [(obj, sub, value) for obj, sub, value, _ in patch_configuration(scene, _devices(scene)[index])]
    else:
        writes = node_configuration(scene, index)
    values: dict[tuple[int, int], object] = {}
    for obj, sub, value in writes:
        values.pop((obj, sub), None)  # re-inserted: objects in the order of their last write
        values[(obj, sub)] = value
    return values


def node_description(scene, index: int) -> str:
    """``taxel 17 (C)`` of a one-taxel node, ``patch node 1:3 (192 taxels)`` of a patch node."""
    d = _devices(scene)[index]
    if scene.bus.patch_nodes:
        return f"patch node {d.label} ({len(d.taxels)} taxels)"
    return f"taxel {d.label} ({scene.taxels[d.taxels[0]].kind})"


@lru_cache(maxsize=4)
def _eds_entries(eds_text: str) -> tuple[dict[str, str], dict[str, int | None]]:
    """Parsed once per EDS text (the patch EDS has 4,249 sections): section name by its upper
    case, and each section's DataType (None without one)."""
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), strict=False)
    parser.optionxform = str
    parser.read_string(eds_text)
    sections = {s.upper(): s for s in parser.sections()}
    types = {key: int(parser.get(s, "DataType"), 0) if parser.has_option(s, "DataType") else None
             for key, s in sections.items()}
    return sections, types


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


def dcf_text(scene, index: int, eds_text: str, name: str | None = None, *, eds_name: str | None = None) -> str:
    """The DCF of node ``index`` of ``scene`` (:func:`node_index`: the taxel's index in a
    one-taxel scene, the patch node's in a patch scene), made from the EDS text ``eds_text``
    (of the file ``eds_name``, named in the errors)."""
    from ..service.lss import expected_serial

    d = _devices(scene)[index]
    patch = "patch " if scene.bus.patch_nodes else ""
    # 0x1018:4 of the node; a patch node's is its first taxel's (the same for all of them)
    serial = expected_serial(scene, scene.taxels[d.taxels[0]])
    return _dcf(scene, eds_text, configured_values(scene, index), d.node_id, d.channel,
                node_description(scene, index), serial, f"{patch}node {d.label}", name, eds_name)


def drive_dcf_text(scene, eds_text: str, name: str | None = None) -> str:
    """The DCF of the scene's gripper drive (``[gripper]``) from the drive's EDS text: its
    start-up values (:func:`taxel_net.gripper.startup_values`) as ``ParameterValue``."""
    from taxel_net.gripper import identity_serial, startup_values
    from taxel_net.patches import node_label

    g = scene.gripper
    return _dcf(scene, eds_text, startup_values(scene), g.node_id, g.channel, drive_description(scene),
                identity_serial(scene), f"gripper drive {node_label(g.channel, g.node_id)}", name)


def drive_description(scene) -> str:
    return f"gripper drive {scene.gripper.node_id} (CiA 402)"


def drive_file_name(scene) -> str:
    """``<scene>_gripper_node032.dcf`` (``_ch1`` before ``_gripper`` off channel 0)."""
    g = scene.gripper
    channel = f"_ch{g.channel}" if g.channel else ""
    return f"{scene.name}{channel}_gripper_node{g.node_id:03d}.dcf"


def _dcf(scene, eds_text: str, configured: dict, node_id: int, channel: int, node_name: str, serial: int,
         what: str, name: str | None, eds_name: str | None = None) -> str:
    """The EDS text with a ParameterValue for each of ``configured`` and the commissioning."""
    from taxel_net.errors import UsageError

    sections, types = _eds_entries(eds_text)
    if "DEVICECOMISSIONING" in sections:
        raise UsageError(f"EDS{f' file {eds_name!r}' if eds_name else ''} already has a [DeviceComissioning] "
                         "section: give the EDS, not a DCF")
    values: dict[str, list[str]] = {}
    for (obj, sub), value in configured.items():
        key = f"{obj:04X}SUB{sub:X}"
        if key not in sections and sub == 0:
            key = f"{obj:04X}"
        if types.get(key) is None:
            raise UsageError(f"EDS{f' file {eds_name!r}' if eds_name else ''} has no entry 0x{obj:04X}:{sub} "
                             "(the node's configuration writes it)")
        values[key] = [f"ParameterValue={_format(value, types[key])}"]
    commissioning = [
        "[DeviceComissioning]",
        f"NodeID={node_id}",
        f"NodeName={node_name}",
        f"Baudrate={scene.bus.bitrate // 1000}",
        f"NetNumber={channel + 1}",
        f"NetworkName={scene.bus.channels[channel]}",
        "CANopenManager=0",
        f"LSS_SerialNumber=0x{serial:08X}",
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
                line = f"{line} - DCF of {what} of scene {scene.name}"
        out.append(line)
    close_section()
    if "DUMMYUSAGE" not in sections:
        out.append("")
        out.extend(commissioning)
    return "\n".join(out).rstrip("\n") + "\n"


def _drive_eds_text() -> str:
    from taxel_net.errors import UsageError
    from taxel_net.resources import gripper_eds_path

    source = gripper_eds_path()
    try:
        return source.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"EDS file {str(source)!r} cannot be read: {exc}") from None


def is_drive(scene, text: str) -> bool:
    """``--node`` ``N`` / ``C:N`` names the scene's gripper drive."""
    g = scene.gripper
    if g is None:
        return False
    channel, sep, node = text.rpartition(":")
    try:
        return (int(node, 0), int(channel, 0) if sep else 0) == (g.node_id, g.channel)
    except ValueError:
        return False


def _check_paths(args, scene, drive: bool, out: Path) -> None:
    """Refuse a DCF that would be written over the scene (its file, its taxels_file) or ``--eds``
    (:func:`taxel_net.outputs.check_distinct_paths`): ``-o`` itself, and with ``--all`` or a
    directory every file it would hold."""
    from taxel_net.outputs import check_distinct_paths, scene_inputs

    inputs = [*scene_inputs(args.scene), ("--eds", args.eds)]
    if args.output == "-":
        return
    if args.all or out.is_dir():
        names = ([file_name(scene, i) for i in range(len(_devices(scene)))] if args.all
                 else [drive_file_name(scene) if drive else file_name(scene, node_index(scene, args.node))])
        if args.all and scene.gripper is not None:
            names.append(drive_file_name(scene))
        outputs = [("-o", str(out / name)) for name in names]
    else:
        outputs = [("-o", args.output)]
    check_distinct_paths(inputs, outputs)


def run(args) -> int:
    import sys

    from taxel_net.errors import UsageError
    from taxel_net.resources import eds_path, gripper_eds_path, patch_eds_path
    from taxel_net.scene import load_scene

    scene = load_scene(args.scene)
    drive = not args.all and is_drive(scene, args.node)
    # the EDS the DCF is made from: --eds (the drive's when --node names the drive: it was read
    # as a taxel EDS and then dropped), else the shipped one of the node's kind
    source = (Path(args.eds) if args.eds else gripper_eds_path() if drive
              else patch_eds_path() if scene.bus.patch_nodes else eds_path())
    if args.eds:  # a user's EDS: one line for any content canopen or configparser would stumble on
        from taxel_net.eds_file import import_eds

        import_eds(source, 1)  # EdsError (a ParameterError: exit 2) naming the file
    try:
        eds_text = source.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"EDS file {str(source)!r} cannot be read: {exc}") from None
    out = Path(args.output)
    _check_paths(args, scene, drive, out)  # an output naming the scene or the EDS: one line, nothing written
    try:
        if args.all:
            if out.exists() and not out.is_dir():
                raise UsageError(f"-o {args.output!r}: not a directory (--all writes one DCF per node)")
            out.mkdir(parents=True, exist_ok=True)
            n = len(_devices(scene))
            for index in range(n):
                name = file_name(scene, index)
                (out / name).write_text(dcf_text(scene, index, eds_text, name, eds_name=str(source)),
                                        encoding="utf-8")
            if scene.gripper is not None:
                name = drive_file_name(scene)
                (out / name).write_text(drive_dcf_text(scene, _drive_eds_text(), name), encoding="utf-8")
            print(f"{n} DCFs of scene {scene.name!r} written to {out}"
                  + (f" (one per patch node, {scene.n} taxels)" if scene.bus.patch_nodes else "")
                  + (f", and the gripper drive's ({drive_file_name(scene)})" if scene.gripper is not None else ""))
            return 0
        index = None if drive else node_index(scene, args.node)
        name = drive_file_name(scene) if drive else file_name(scene, index)
        if args.output == "-":
            sys.stdout.write(drive_dcf_text(scene, eds_text, name) if drive
                             else dcf_text(scene, index, eds_text, name, eds_name=str(source)))
            return 0
        if out.is_dir():
            out = out / name
        text = (drive_dcf_text(scene, eds_text, out.name) if drive
                else dcf_text(scene, index, eds_text, out.name, eds_name=str(source)))
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"-o {args.output!r}: cannot write: {exc.strerror or exc}") from None
    if drive:
        print(f"DCF of gripper drive {args.node} (CiA 402) of scene {scene.name!r} written to {out}: "
              f"{text.count('ParameterValue=')} parameter values")
        return 0
    what = node_description(scene, index).partition(" (")[2].rstrip(")")
    kind = "patch node" if scene.bus.patch_nodes else "node"
    print(f"DCF of {kind} {args.node} ({what}) of scene {scene.name!r} written to {out}: "
          f"{text.count('ParameterValue=')} parameter values")
    return 0
