"""The gripper drive's frames decoded by the cycle assembler (issue 23, fusion_center.service.drive_frames):
the latest TPDO1/TPDO2 values, the heartbeat, EMCY and liveness when a cycle closes - a function of
the stream alone. Frames are packed here by hand from docs/gripper-drive.md's mapping table."""

import dataclasses

from fusion_center.service import CycleAssembler
from fusion_center.service.drive_frames import state_name
from taxel_net.scene import load_scene

ID = 32


def _scene():
    scene = load_scene("grasp_scripted")
    return dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, heartbeat_consumer_ms=300, sync_window_us=0))


def _tpdo1(sw, torque, pos_um):
    return sw.to_bytes(2, "little") + torque.to_bytes(2, "little", signed=True) + pos_um.to_bytes(4, "little", signed=True)


def _tpdo2(mode, grip, force, width, error):
    return (bytes([mode & 0xFF, grip]) + force.to_bytes(2, "little", signed=True) + width.to_bytes(2, "little")
            + error.to_bytes(2, "little"))


def test_the_latest_drive_values_when_a_cycle_closes():
    a = CycleAssembler(_scene())
    a.feed(0, 0, 0x700 + ID, b"\x00")               # boot-up
    a.feed(1000, 0, 0x080, b"")                      # SYNC 0
    # OPERATION ENABLED (0x27 under mask 0x6F), HOLDING's bits 15 (grip state 4), torque 50 permille, 40 mm
    a.feed(2000, 0, 0x180 + ID, _tpdo1(0x8027 | 0x0400, 50, 40000))
    a.feed(2100, 0, 0x280 + ID, _tpdo2(4, 4, 70, 400, 0))
    a.feed(2200, 0, 0x80 + ID, bytes([0x30, 0x81, 0x11, 0, 0, 0, 0, 0]))  # EMCY 0x8130
    closed = a.feed(11000, 0, 0x080, b"")            # SYNC 1 closes cycle 0
    d = closed.drive
    assert d.heard and not d.lost and d.nmt_state == 5
    assert d.state == "OPERATION ENABLED" and d.torque_permille == 50 and d.position_um == 40000
    assert d.mode == 4 and d.grip_state_name == "HOLDING" and d.force_n == 7.0 and d.width_01mm == 400
    assert d.emcy == ((0x8130, 0x11, 2200),) and d.bootups == 1
    # nothing more from the drive for longer than the consumer time (300 ms): lost, values kept
    closed = a.feed(300000, 0, 0x080, b"")            # closes at 300 ms: heard 297.8 ms ago
    assert closed.drive.emcy == () and closed.drive.bootups == 0 and not closed.drive.lost
    closed = a.feed(410000, 0, 0x080, b"")
    assert closed.drive.lost and closed.drive.state == "OPERATION ENABLED"
    assert a.counters()["drive"] == 4 and a.malformed() == 0


def test_a_malformed_drive_frame_changes_nothing():
    a = CycleAssembler(_scene())
    a.feed(0, 0, 0x080, b"")
    a.feed(100, 0, 0x180 + ID, _tpdo1(0x0040, 0, 60000))
    a.feed(200, 0, 0x180 + ID, b"\x27\x00\x05")         # 3 bytes: refused
    closed = a.feed(10000, 0, 0x080, b"")
    assert closed.drive.state == "SWITCH ON DISABLED" and a.drive.bad == 1


def test_state_names_are_canopens():
    assert state_name(0x0250) == "SWITCH ON DISABLED" and state_name(0x0008) == "FAULT"
    assert state_name(0x0007) == "QUICK STOP ACTIVE" and state_name(0x0021) == "READY TO SWITCH ON"


def test_a_drive_not_nmt_operational_has_no_present_cia402_state():
    """A drive reset (boot-up) or NMT-stopped mid-hold sends no PDO (CiA 301): its last statusword is
    not its state. Before stop 32 the snapshot kept OPERATION ENABLED / HOLDING for ever."""
    a = CycleAssembler(_scene())
    a.feed(0, 0, 0x700 + ID, b"\x00")
    a.feed(500, 0, 0x000, bytes([0x01, 0]))          # NMT start all
    a.feed(1000, 0, 0x080, b"")
    a.feed(2000, 0, 0x180 + ID, _tpdo1(0x8027 | 0x0400, 50, 40000))
    a.feed(2100, 0, 0x280 + ID, _tpdo2(4, 4, 70, 400, 0))
    d = a.feed(11000, 0, 0x080, b"").drive
    assert d.operational and d.state == "OPERATION ENABLED"
    a.feed(12000, 0, 0x700 + ID, b"\x00")            # the drive resets: boot-up, then pre-operational
    d = a.feed(21000, 0, 0x080, b"").drive
    assert d.bootups == 1 and not d.operational and d.state is None and d.force_n is None
    a.feed(22000, 0, 0x700 + ID, b"\x7f")
    d = a.feed(31000, 0, 0x080, b"").drive
    assert d.bootups == 0 and not d.operational and d.state is None
    a.feed(31500, 0, 0x000, bytes([0x01, ID]))       # the centre's NMT start to the drive
    a.feed(32000, 0, 0x180 + ID, _tpdo1(0x0040, 0, 40000))  # SWITCH ON DISABLED after the reset
    d = a.feed(41000, 0, 0x080, b"").drive
    assert d.operational and d.state == "SWITCH ON DISABLED"
    # an NMT stop: heartbeat 4 (or the stop command itself in the stream), the last TPDO1 stale
    a.feed(42000, 0, 0x180 + ID, _tpdo1(0x8027 | 0x0400, 50, 40000))
    d = a.feed(51000, 0, 0x080, b"").drive
    assert d.state == "OPERATION ENABLED"
    a.feed(52000, 0, 0x000, bytes([0x02, ID]))
    d = a.feed(61000, 0, 0x080, b"").drive
    assert not d.operational and d.nmt_state == 4 and d.state is None
    a.feed(62000, 0, 0x700 + ID, b"\x05")            # started by someone: operational again ...
    d = a.feed(71000, 0, 0x080, b"").drive
    assert d.operational and d.state is None          # ... its state unknown until its next TPDO1 (not the stale one)
    a.feed(72000, 0, 0x180 + ID, _tpdo1(0x8027 | 0x0400, 50, 40000))
    d = a.feed(81000, 0, 0x080, b"").drive
    assert d.operational and d.state == "OPERATION ENABLED"
    # the same after an NMT start that did not take effect: the stop, the start in the stream, no
    # frame of the drive yet - no present state (the stale statusword said OPERATION ENABLED)
    a.feed(82000, 0, 0x000, bytes([0x81, ID]))        # a reset command to it
    a.feed(83000, 0, 0x000, bytes([0x01, ID]))        # and a start before its boot-up
    d = a.feed(91000, 0, 0x080, b"").drive
    assert d.operational and d.state is None
