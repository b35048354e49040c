"""bench/grip_player.py (a grasp scene's taxel nodes at hardware speed for bench/grip_latency.py's
``player`` transport): what it records from an observed run, and how its nodes answer NMT, SDO
and SYNC - CiA 301's boot-up, heartbeat states, expedited download confirmations - without a
socket (the burst sender is a list)."""

from __future__ import annotations

import sys
from pathlib import Path

import can
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
from grip_player import TaxelNodes, record_answers  # noqa: E402

from taxel_net.patches import devices  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402


def _msg(can_id, data=b""):
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False)


@pytest.fixture(scope="module")
def scene():
    return load_scene("grasp_lift_patch")


def test_record_answers_keeps_each_cycles_taxel_tpdos_only(scene):
    cobs = [t.cob_id for d in devices(scene) for t in d.tpdos]
    assert len(cobs) == 2
    drive = scene.gripper.node_id
    frames = [_msg(0x701, b"\x05"), _msg(cobs[0], b"\x00\x00\x00\x00"),     # before the first SYNC: dropped
              _msg(0x80), _msg(0x180 + drive, bytes(8)), _msg(cobs[0], b"\x01\x02\x03\x04"),
              _msg(cobs[1], b"\x05\x06\x07\x08"), _msg(0x200 + drive, bytes(8)),
              _msg(0x80), _msg(cobs[1], b"\x0a\x0b\x0c\x0d"), _msg(0x700 + 1, b"\x05"),
              _msg(0x80)]
    assert record_answers(scene, frames) == [
        [(cobs[0], "01020304"), (cobs[1], "05060708")],
        [(cobs[1], "0a0b0c0d")],
        [],
    ]


def _nodes(scene, cycles):
    sent: list[list[tuple]] = []
    return TaxelNodes(scene, cycles, sent.append), sent


def test_nmt_boot_up_heartbeat_states_and_sdo(scene):
    nodes, sent = _nodes(scene, [[]])
    ids = [d.node_id for d in devices(scene)]
    assert nodes.node_ids == ids == [1, 2]
    nodes.on_message_received(_msg(0x000, bytes((0x82, 0))))               # reset communication, all
    assert sent.pop() == [(0x701, b"\x00"), (0x702, b"\x00")]              # boot-ups
    nodes.heartbeats()
    assert sent.pop() == [(0x701, b"\x7f"), (0x702, b"\x7f")]              # pre-operational
    nodes.on_message_received(_msg(0x000, bytes((0x01, 2))))               # start node 2 only
    nodes.heartbeats()
    assert sent.pop() == [(0x701, b"\x7f"), (0x702, b"\x05")]
    # an expedited download of 0x1017:0 = 50 ms to node 1: confirmed (scs 3, the same multiplexer)
    nodes.on_message_received(_msg(0x601, bytes((0x2B, 0x17, 0x10, 0x00, 50, 0, 0, 0))))
    assert sent.pop() == [(0x581, bytes((0x60, 0x17, 0x10, 0x00, 0, 0, 0, 0)))]
    # an upload: aborted with "command specifier not valid" (0x05040001)
    nodes.on_message_received(_msg(0x602, bytes((0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0))))
    assert sent.pop() == [(0x582, bytes((0x80, 0x00, 0x10, 0x00, 0x01, 0x00, 0x04, 0x05)))]
    nodes.on_message_received(_msg(0x640, bytes(8)))                        # the drive's SDO: not ours
    assert sent == []


def test_sync_plays_the_cycles_once_every_node_is_operational(scene):
    cobs = [t.cob_id for d in devices(scene) for t in d.tpdos]
    cycles = [[(cobs[0], "01020304"), (cobs[1], "05060708")], [(cobs[1], "0a0b0c0d")]]
    nodes, sent = _nodes(scene, cycles)
    nodes.on_message_received(_msg(0x000, bytes((0x81, 0))))
    sent.clear()
    nodes.on_message_received(_msg(0x80))                                  # not operational: silent
    assert sent == []
    nodes.on_message_received(_msg(0x000, bytes((0x81, 0))))               # the world restarts: cycle 0
    nodes.on_message_received(_msg(0x000, bytes((0x01, 0))))
    sent.clear()
    for _ in range(3):
        nodes.on_message_received(_msg(0x80))
    assert sent == [[(cobs[0], b"\x01\x02\x03\x04"), (cobs[1], b"\x05\x06\x07\x08")],
                    [(cobs[1], b"\x0a\x0b\x0c\x0d")],
                    [(cobs[0], b"\x01\x02\x03\x04"), (cobs[1], b"\x05\x06\x07\x08")]]   # the recording again


def test_a_tagged_tpdo_carries_the_syncs_counter():
    from dataclasses import replace

    scene = load_scene("grasp_lift_patch")
    scene = replace(scene, bus=replace(scene.bus, sync_counter=16))
    tpdos = [t for d in devices(scene) for t in d.tpdos]
    assert all(t.tagged for t in tpdos)
    nodes, sent = _nodes(scene, [[(tpdos[0].cob_id, "07aabbccdd")]])
    nodes.on_message_received(_msg(0x000, bytes((0x01, 0))))
    sent.clear()
    nodes.on_message_received(_msg(0x80, b"\x0c"))
    assert sent == [[(tpdos[0].cob_id, b"\x0c\xaa\xbb\xcc\xdd")]]
