"""The serial number (0x1018:4) the scene gives each of its CANopen devices - one rule for the
twins (taxel and patch nodes, the gripper drive), the master's LSS and the DCFs."""

from __future__ import annotations

import zlib


def identity_serial(scene, device) -> int:
    """0x1018:4 of ``device`` (a taxel, a patch node's first taxel, the ``[gripper]`` spec:
    anything with ``channel`` and ``node_id``): ``crc32(scene name) & 0xFFFF`` in bits 16-31,
    the channel in bits 8-15, the node-ID in bits 0-7 - distinct for every node of a scene
    (node-IDs are unique per channel) and the same in every run and process of that scene."""
    return (zlib.crc32(scene.name.encode("utf-8")) & 0xFFFF) << 16 | (device.channel & 0xFF) << 8 | device.node_id
