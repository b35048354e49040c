"""The gripper drive of a scene's ``[gripper]`` table on the rig (node_sim.rig, issue 22): booted
beside the taxel nodes with the scene's start-up values (read back over SDO by a canopen master,
restored by NMT reset-node), driven by canopen's BaseNode402 with the scene's parameters, and
absent when the scene has no table or its channel is not served.

Expected values by hand from scenes/grasp_drive.toml: rated force 140.0 N per jaw (0x2103 = 1400),
max torque 800 ‰, slope 4000 ‰/s = 40 ‰ per 10 ms SYNC, stroke 2..60 mm."""

from __future__ import annotations

import dataclasses
import sys
import time
import uuid
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
from canopen.profiles.p402 import BaseNode402

from node_sim.gripper.drive import GRIPPER_EDS_PATH
from node_sim.rig import Rig
from taxel_net.errors import ParameterError
from taxel_net.gripper import startup_values
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from process_helpers import node_sim  # noqa: E402

DRIVE = 32
MASTER = 127
WAIT_S = 5.0


def scene_on(channel: str):
    scene = load_scene("grasp_drive")
    return dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, channels=(channel,)))


@pytest.fixture
def rig_and_master():
    channel = f"g22b-{uuid.uuid4().hex[:8]}"
    scene = scene_on(channel)
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel)
    boots: list[int] = []
    net.subscribe(0x700 + DRIVE, lambda cob, data, ts: boots.append(data[0]) if data == b"\x00" else None)
    rig = Rig(scene, interface="virtual", reading_source=lambda c: np.zeros(scene.n)).start()
    try:
        yield rig, net, scene, boots
    finally:
        net.disconnect()
        rig.stop()


def wait(condition, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.005)


def test_the_drive_boots_with_the_scene_start_up_values(rig_and_master):
    rig, net, scene, boots = rig_and_master
    assert rig.gripper is not None and rig.gripper.node_id == DRIVE
    node = canopen.RemoteNode(DRIVE, str(GRIPPER_EDS_PATH))
    net.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    wait(lambda: boots, "the drive's boot-up")
    expected = startup_values(scene)
    got = {(i, s): (node.sdo[i].raw if s == 0 else node.sdo[i][s].raw) for i, s in expected}
    assert got == expected
    # by hand from the scene file
    assert (got[(0x2103, 0)], got[(0x6072, 0)], got[(0x6087, 0)]) == (1400, 800, 4000)
    assert (got[(0x607D, 1)], got[(0x607D, 2)], got[(0x6060, 0)]) == (2000, 60000, 4)
    assert got[(0x1016, 1)] == MASTER << 16 | 150 and got[(0x1017, 0)] == 50
    assert node.sdo[0x6064].raw == 60000                      # the jaws start open (0x607D:2)
    # the taxels are there as before
    assert sorted(nid for _, nid in rig.nodes) == [1, 2, 3, 4, 5, 6]
    # reset node: the start-up values, not the SDO-written ones
    node.sdo[0x2103].raw = 500
    boots.clear()
    node.nmt.send_command(0x81)
    wait(lambda: boots, "boot-up after reset node")
    assert node.sdo[0x2103].raw == 1400


def test_base_node_402_grips_with_the_scene_parameters(rig_and_master):
    rig, net, scene, boots = rig_and_master
    node = BaseNode402(DRIVE, str(GRIPPER_EDS_PATH))
    net.add_node(node)
    heartbeat = net.send_periodic(0x700 + MASTER, b"\x05", 0.05)
    net.sync.start(0.01)
    rpdo = None
    try:
        node.nmt.wait_for_heartbeat(WAIT_S)
        node.setup_402_state_machine()
        node.nmt.state = "OPERATIONAL"
        rpdo = node.rpdo[1]
        rpdo.start(0.01)
        assert node.op_mode == "PROFILED TORQUE"                  # 0x6060 = 4 at start-up
        node.state = "OPERATION ENABLED"
        assert node.state == "OPERATION ENABLED"
        with rig.gripper.lock:
            rig.gripper.drive.jaw_blocked_at(30.0)
        node.rpdo_pointers[0x6071].raw = 1000                     # beyond max torque 800: clamped
        deadline = time.monotonic() + WAIT_S
        while not (node.tpdo_values.get(0x2100) == 4 and node.tpdo_values.get(0x6077) == 800):
            assert time.monotonic() < deadline, node.tpdo_values
            node.check_statusword(timeout=max(0.01, deadline - time.monotonic()))  # not canopen's 0.2 s
        assert node.tpdo_values[0x2101] == 1120                   # 800 ‰ x 140.0 N = 112.0 N per jaw
        assert node.statusword & 0x0800                           # internal limit: the clamp
        with rig.gripper.lock:
            assert rig.gripper.drive.grip_force_n == pytest.approx(112.0)
    finally:
        if rpdo is not None:
            rpdo.stop()
        net.sync.stop()
        heartbeat.stop()


def test_no_drive_without_the_table_or_on_a_channel_not_served():
    channel = f"g22b-{uuid.uuid4().hex[:8]}"
    plain = load_scene("gripper18")
    plain = dataclasses.replace(plain, bus=dataclasses.replace(plain.bus, channels=(channel,)))
    with Rig(plain, reading_source=lambda c: np.zeros(plain.n)) as rig:
        assert rig.gripper is None
    two = scene_on(channel)
    two = dataclasses.replace(two, bus=dataclasses.replace(two.bus, channels=(channel, channel + "b")),
                              gripper=dataclasses.replace(two.gripper, channel=1))
    with Rig(two, reading_source=lambda c: np.zeros(two.n), serve_channels=[0]) as rig:
        assert rig.gripper is None
    with Rig(two, reading_source=lambda c: np.zeros(two.n)) as rig:
        assert rig.gripper is not None and rig.gripper.channel == channel + "b"


def test_a_scene_object_with_a_colliding_node_id_is_refused():
    """The loader refuses it (tests/test_scene_gripper.py); a Scene built in code is checked by the rig."""
    scene = scene_on(f"g22b-{uuid.uuid4().hex[:8]}")
    bad = dataclasses.replace(scene, gripper=dataclasses.replace(scene.gripper, node_id=3))
    with pytest.raises(ParameterError) as info:
        Rig(bad)
    assert "gripper" in str(info.value) and "\n" not in str(info.value)


def test_node_sim_says_the_drive_is_ready():
    with node_sim("--scene", "grasp_drive", "-i", "virtual", "-c", f"g22b-{uuid.uuid4().hex[:8]}",
                  stop_s=30) as proc:
        line = proc.ready_line
    assert line.startswith("node-sim: ready: 6 nodes and gripper drive 32 of scene 'grasp_drive'"), line
    assert proc.returncode == 0, proc.stderr.read()


def test_drive_host_filters_take_only_what_the_drive_consumes():
    """The drive's bus object lets through NMT, its SDO requests, heartbeats, its SYNC and its
    RPDOs only: the taxels' TPDOs on the same channel never reach its receive thread (before,
    every frame of the channel went through it and took the drive's lock). An RPDO moved by an
    SDO download (0x1400:1) is let through at its new COB-ID and the old one no longer."""
    from node_sim.gripper.host import DriveHost

    channel = f"drive-filters-{uuid.uuid4().hex[:8]}"
    host = DriveHost(DRIVE, "virtual", channel)
    seen: list[int] = []
    dispatch = host._dispatch
    host._dispatch = lambda can_id, data: (seen.append(can_id), dispatch(can_id, data))[1]
    with host, can_bus(channel) as master:
        taxel_frames = [0x181, 0x182, 0x281, 0x0A1, 0x080 + 5, 0x5A0, 0x601, 0x7E5]
        for can_id in taxel_frames:
            master.send(can.Message(arbitration_id=can_id, data=b"\x01", is_extended_id=False))
        rpdo1 = 0x200 + DRIVE
        master.send(can.Message(arbitration_id=0x77F, data=b"\x05", is_extended_id=False))  # a heartbeat
        master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))        # SYNC
        master.send(can.Message(arbitration_id=rpdo1, data=bytes(8), is_extended_id=False))
        # SDO download 0x1400:1 = 0x80000000 | old (RPDO1 invalid), then a new valid COB-ID 0x300 + id
        for value in (0x8000_0000 | rpdo1, 0x8000_0000 | (0x300 + DRIVE), 0x300 + DRIVE):
            master.send(can.Message(arbitration_id=0x600 + DRIVE, is_extended_id=False,
                                    data=bytes([0x23, 0x00, 0x14, 0x01]) + value.to_bytes(4, "little")))
            answer = master.recv(WAIT_S)
            while answer is not None and answer.arbitration_id != 0x580 + DRIVE:
                answer = master.recv(WAIT_S)
            assert answer is not None and answer.data[0] == 0x60, answer
        for can_id in (rpdo1, 0x300 + DRIVE):
            master.send(can.Message(arbitration_id=can_id, data=bytes(8), is_extended_id=False))
        master.send(can.Message(arbitration_id=0x000, data=bytes([0x01, DRIVE]), is_extended_id=False))
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline and (not seen or seen[-1] != 0x000):
            time.sleep(0.01)
    assert not set(taxel_frames) & set(seen), seen
    assert seen == [0x77F, 0x080, rpdo1, 0x600 + DRIVE, 0x600 + DRIVE, 0x600 + DRIVE, 0x300 + DRIVE, 0x000], \
        [hex(i) for i in seen]


def can_bus(channel: str):
    return can.Bus(interface="virtual", channel=channel)
