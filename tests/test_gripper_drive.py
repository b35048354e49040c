"""The gripper-drive twin (node_sim.gripper) driven end to end by canopen's own CiA 402 master,
``canopen.profiles.p402.BaseNode402``, unmodified, on python-can's virtual bus: the master produces
SYNC every 10 ms and its heartbeat, sends RPDO1 (controlword, target torque, target position) every
10 ms (``PdoMap.start``: BaseNode402 itself sends a synchronous RPDO only on ``transmit()``), reads
the statusword from TPDO1 (it times out when the statusword is older than 0.2 s).

Expected values come from the drive's parameters by hand: torque slope 5000 ‰/s at 10 ms per SYNC
is 50 ‰ per SYNC; profile velocity 50 mm/s is 0.5 mm per SYNC; grip force per jaw = torque ‰ / 1000
x rated grip force 100.0 N (0x2103 = 1000 x 0.1 N)."""

from __future__ import annotations

import struct
import time
import uuid

import canopen
import pytest
from canopen.profiles.p402 import BaseNode402
from canopen.sdo import SdoAbortedError

from node_sim.gripper.drive import GRIPPER_EDS_PATH
from node_sim.gripper.host import DriveHost

NODE = 5
MASTER = 0x7F
SYNC_S = 0.01
WAIT_S = 5.0            # bound of every wait below (never reached when the drive works)


class Bench:
    """A drive host and a canopen master (BaseNode402) on one virtual channel."""

    def __init__(self, startup=None):
        channel = f"g22-{uuid.uuid4().hex[:8]}"
        values = {(0x1017, 0): 50, (0x1016, 1): MASTER << 16 | 300}
        values.update(startup or {})
        self.host = DriveHost(NODE, "virtual", channel, startup=values).start()
        self.net = canopen.Network()
        self.net.connect(interface="virtual", channel=channel)
        self.heartbeat = self.net.send_periodic(0x700 + MASTER, b"\x05", 0.05)
        self.node = BaseNode402(NODE, str(GRIPPER_EDS_PATH))
        self.net.add_node(self.node)
        self.net.sync.start(SYNC_S)
        self.node.nmt.wait_for_heartbeat(WAIT_S)
        self.node.setup_402_state_machine()
        self.node.nmt.state = "OPERATIONAL"
        self.rpdo = self.node.rpdo[1]
        self.rpdo.start(SYNC_S)
        self.torques: list[int] = []
        self.node.tpdo[1].add_callback(lambda m: self.torques.append(self.node.tpdo_values[0x6077]))
        self.wait(lambda: self.node.state == "SWITCH ON DISABLED")

    def wait(self, condition, what: str = "condition") -> None:
        deadline = time.monotonic() + WAIT_S
        while not condition():
            assert time.monotonic() < deadline, f"{what} not reached (statusword 0x{self.node.statusword:04X})"
            self.next_tpdo(deadline)

    def syncs(self, n: int) -> None:
        """Let ``n`` TPDO1s (SYNCs) pass."""
        deadline = time.monotonic() + WAIT_S
        for _ in range(n):
            self.next_tpdo(deadline)

    def next_tpdo(self, deadline: float) -> None:
        """The next TPDO1 (canopen's ``check_statusword``), waited for until ``deadline``: its own
        default (``TIMEOUT_CHECK_TPDO``, 0.2 s) raised on a host that held this process for longer
        between two SYNCs (CI, load ~2 a core)."""
        self.node.check_statusword(timeout=max(0.01, deadline - time.monotonic()))

    def emcy(self, code: int) -> None:
        """Wait for an EMCY with ``code`` in the master's log (canopen's ``EmcyConsumer``)."""
        self.wait(lambda: any(e.code == code for e in self.node.emcy.log), f"EMCY 0x{code:04X}")

    @property
    def values(self) -> dict[int, int]:
        return self.node.tpdo_values

    def close(self) -> None:
        self.rpdo.stop()
        self.heartbeat.stop()
        self.net.sync.stop()
        self.net.disconnect()
        self.host.stop()


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def grip_bits(statusword: int) -> int:
    """Grip state from statusword bits 8 (bit 0), 14 (bit 1), 15 (bit 2)."""
    return (statusword >> 8 & 1) | (statusword >> 14 & 1) << 1 | (statusword >> 15 & 1) << 2


def hold_part(b: Bench, torque: int = 500, width_mm: float = 30.0) -> None:
    b.node.op_mode = "PROFILED TORQUE"
    b.node.state = "OPERATION ENABLED"
    with b.host.lock:
        b.host.drive.jaw_blocked_at(width_mm)
    b.node.rpdo_pointers[0x6071].raw = torque
    b.wait(lambda: b.values[0x2100] == 4 and b.values[0x6077] == torque, "HOLDING")


def test_setup_finds_the_pdos_and_every_state_is_reached(bench):
    b, node = bench, bench.node
    assert 0x6040 in node.rpdo_pointers and 0x6041 in node.tpdo_values and 0x6061 in node.tpdo_values
    node.sdo[0x605A].raw = 6                 # stay in QUICK STOP ACTIVE (transition 16 allowed)
    seen = [node.state]
    for target in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED", "QUICK STOP ACTIVE",
                   "OPERATION ENABLED", "SWITCHED ON", "READY TO SWITCH ON", "SWITCH ON DISABLED"):
        node.state = target
        seen.append(node.state)
    assert seen == ["SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED",
                    "QUICK STOP ACTIVE", "OPERATION ENABLED", "SWITCHED ON", "READY TO SWITCH ON",
                    "SWITCH ON DISABLED"]
    # FAULT REACTION ACTIVE (the quick-stop ramp of 0x605E = 2 from a held force) and FAULT
    node.state = "OPERATION ENABLED"
    hold_part(b)
    states = []
    node.tpdo[1].add_callback(lambda m: states.append(node.state))
    node.sdo[0x2110].raw = 0x4310
    b.wait(lambda: node.state == "FAULT", "FAULT")
    assert "FAULT REACTION ACTIVE" in states
    assert b.host.drive.drive.sm.state.label == "FAULT"


def test_modes_only_those_of_0x6502(bench):
    node = bench.node
    node.op_mode = "PROFILED TORQUE"
    assert node.op_mode == "PROFILED TORQUE"
    node.op_mode = "PROFILED POSITION"
    assert node.op_mode == "PROFILED POSITION"
    with pytest.raises(TypeError):
        node.op_mode = "PROFILED VELOCITY"
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x6060].raw = 3
    assert info.value.code == 0x06090030


def test_profile_torque_actual_follows_the_slope_to_the_target(bench):
    b = bench
    hold_part(b, torque=500, width_mm=30.0)
    rising = [t for t in b.torques if 0 < t <= 500]
    steps = {y - x for x, y in zip(rising, rising[1:])}
    assert rising[0] == 50 and rising[-1] == 500 and steps <= {0, 50}
    assert len([t for t in rising if t < 500]) == 9               # 50, 100, ..., 450: one per SYNC
    sw = b.node.statusword
    assert sw & 0x0400 and not sw & 0x0800                        # target reached, no limit
    assert grip_bits(sw) == 4 == b.values[0x2100]                 # HOLDING, in the statusword too
    assert b.values[0x6064] == 30000 and b.values[0x2102] == 300  # width stopped at the part (µm, 0.1 mm)
    assert b.values[0x2101] == 500                                # 500 ‰ x 100.0 N / 1000 = 50.0 N = 500 x 0.1 N
    with b.host.lock:
        assert b.host.drive.grip_force_n == pytest.approx(50.0) and b.host.drive.width_mm == pytest.approx(30.0)


def test_profile_torque_beyond_max_torque_is_clamped_and_flagged(bench):
    b = bench
    b.node.sdo[0x6072].raw = 800
    hold_part(b, torque=800)
    b.node.rpdo_pointers[0x6071].raw = 1200
    b.syncs(5)
    assert b.values[0x6077] == 800 and b.node.statusword & 0x0800 and b.node.statusword & 0x0400


def test_grasp_without_part_is_no_part_then_part_lost(bench):
    b = bench
    b.node.op_mode = "PROFILED TORQUE"
    b.node.state = "OPERATION ENABLED"
    b.node.rpdo_pointers[0x6071].raw = 300
    b.wait(lambda: b.values[0x2100] == 2, "NO_PART")              # closed to the stroke limit 0 mm
    assert b.values[0x6064] == 0 and b.values[0x2101] == 0 and b.node.statusword & 0x0800
    b.node.rpdo_pointers[0x6071].raw = -300                       # open: RELEASED
    b.wait(lambda: b.values[0x2100] == 5 and b.values[0x6064] >= 40000, "RELEASED")
    with b.host.lock:
        b.host.drive.jaw_blocked_at(30.0)
    b.node.rpdo_pointers[0x6071].raw = 300
    b.wait(lambda: b.values[0x2100] == 4, "HOLDING")
    with b.host.lock:
        b.host.drive.part_lost()
    b.wait(lambda: b.values[0x2100] == 3 and b.values[0x6064] == 0, "PART_LOST, jaws closed")
    assert b.values[0x2101] == 0


def test_profile_position_open_and_close(bench):
    b, node = bench, bench.node
    node.op_mode = "PROFILED POSITION"
    node.state = "OPERATION ENABLED"
    assert b.values[0x6064] == 80000                              # starts open (0x607D:2)

    def move(target_um: int) -> None:
        node.rpdo_pointers[0x607A].raw = target_um
        node.controlword = 0x1F                                   # new set-point
        b.wait(lambda: node.statusword & 0x1000, "set-point acknowledge")
        node.controlword = 0x0F
        b.wait(lambda: node.statusword & 0x1000 == 0, "acknowledge cleared")

    positions = []
    node.tpdo[1].add_callback(lambda m: positions.append(node.tpdo_values[0x6064]))
    move(20000)
    b.wait(lambda: b.values[0x6064] == 20000 and node.statusword & 0x0400, "closed to 20 mm")
    moving = [p for p in positions if 20000 < p < 80000]
    assert moving and {x - y for x, y in zip(moving, moving[1:])} <= {0, 500}   # 50 mm/s: 0.5 mm a SYNC
    move(70000)
    b.wait(lambda: b.values[0x6064] == 70000 and node.statusword & 0x0400, "opened to 70 mm")
    with b.host.lock:
        b.host.drive.jaw_blocked_at(30.0)
    move(10000)                                                    # closes on the part at 30 mm
    b.wait(lambda: b.values[0x6064] == 30000 and b.values[0x6077] == 1000, "blocked at the part")
    assert not node.statusword & 0x0400 and node.statusword & 0x0800   # not reached, internal limit
    assert b.values[0x2100] == 4 and b.values[0x2101] == 1000     # HOLDING at max torque: 100.0 N per jaw
    move(90000)                                                    # beyond the stroke: clamped
    b.wait(lambda: b.values[0x6064] == 80000, "opened to the stroke limit")
    assert b.values[0x2100] == 5 and node.statusword & 0x0800


def test_quick_stop_ramps_the_force_to_zero(bench):
    b = bench
    hold_part(b, torque=500)
    b.torques.clear()
    b.node.state = "QUICK STOP ACTIVE"                            # 0x605A = 2: ramp, then SWITCH ON DISABLED
    b.wait(lambda: b.node.state == "SWITCH ON DISABLED", "SWITCH ON DISABLED after the ramp")
    falling = [t for t in b.torques if t < 500]
    assert falling[:9] == list(range(450, 0, -50)) and b.values[0x6077] == 0
    assert b.values[0x2101] == 0 and b.values[0x2100] == 5       # the part is let go: RELEASED


def test_quick_stop_option_6_stays_and_transition_16_returns(bench):
    b = bench
    b.node.sdo[0x605A].raw = 6
    hold_part(b, torque=400)
    b.node.state = "QUICK STOP ACTIVE"
    b.wait(lambda: b.values[0x6077] == 0 and b.node.statusword & 0x0400, "quick stop done")
    assert b.node.state == "QUICK STOP ACTIVE"
    b.node.state = "OPERATION ENABLED"                            # transition 16
    b.wait(lambda: b.values[0x6077] == 400, "torque back")
    with pytest.raises(SdoAbortedError):
        b.node.sdo[0x605A].raw = 3                                # current-limit stop: not supported


def test_fault_then_reset_from_fault(bench):
    b, node = bench, bench.node
    hold_part(b, torque=500)
    with pytest.raises(SdoAbortedError):
        node.sdo[0x2110].raw = 0x8130                             # not a device fault code
    node.emcy.reset()
    node.sdo[0x2110].raw = 0x2310                                 # continuous over-current
    b.wait(lambda: node.state == "FAULT", "FAULT")
    b.emcy(0x2310)
    assert b.values[0x603F] == 0x2310 and node.sdo[0x603F].raw == 0x2310
    assert node.sdo[0x1001].raw & 0x03 == 0x03                    # generic + current
    assert b.values[0x6077] == 0 and b.values[0x2101] == 0
    node.reset_from_fault()
    assert node.state == "OPERATION ENABLED"
    b.wait(lambda: b.values[0x603F] == 0, "error code cleared")
    assert node.sdo[0x2110].raw == 0 and node.sdo[0x1001].raw == 0
    assert not node.emcy.active                                   # the error-reset EMCY arrived


@pytest.mark.parametrize("option, state_after, force_kept", [
    (0, "OPERATION ENABLED", True),            # the default: no action, the part stays held
    (1, "FAULT", False),
    (2, "SWITCH ON DISABLED", False),
    (3, "SWITCH ON DISABLED", False),          # quick stop, 0x605A = 2: ramp, then disabled
])
def test_lost_master_abort_connection(option, state_after, force_kept):
    b = Bench()
    try:
        node = b.node
        if option:
            node.sdo[0x6007].raw = option
        assert node.sdo[0x6007].raw == option
        hold_part(b, torque=500)
        node.emcy.reset()
        b.rpdo.stop()                          # the master falls silent: no heartbeat, no RPDO ...
        b.heartbeat.stop()                     # ... (SYNC from elsewhere keeps the TPDOs coming)
        b.emcy(0x8130)
        b.wait(lambda: node.statusword & 0x0080, "warning bit 7")
        b.wait(lambda: node.state == state_after, state_after)
        b.syncs(30)                            # 0.3 s later
        assert b.values[0x603F] == 0x8130 and node.sdo[0x1001].raw & 0x11 == 0x11
        if force_kept:
            assert b.values[0x6077] == 500 and b.values[0x2101] == 500 and b.values[0x2100] == 4
        else:
            assert b.values[0x6077] == 0 and b.values[0x2101] == 0 and b.values[0x2100] == 5
        b.heartbeat = b.net.send_periodic(0x700 + MASTER, b"\x05", 0.05)   # the master is back
        b.wait(lambda: not node.statusword & 0x0080, "warning cleared")
        if option != 1:
            b.wait(lambda: b.values[0x603F] == 0, "error code cleared")
    finally:
        b.close()


def test_rpdo_length_error_and_mapping_rules(bench):
    b, node = bench, bench.node
    node.state = "OPERATION ENABLED"
    node.emcy.reset()
    b.rpdo.stop()
    b.net.send_message(0x200 + NODE, bytes([0x06, 0x00]))      # 2 of the 8 mapped bytes: not processed
    b.emcy(0x8210)
    b.syncs(3)
    assert node.state == "OPERATION ENABLED"                   # the short frame's controlword not applied
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x1600][0].raw = 0                            # mapping while the RPDO is valid
    assert info.value.code == 0x06010000
    node.sdo[0x1400][1].raw = 0x80000200 + NODE                # not valid: now it may be mapped
    node.sdo[0x1600][0].raw = 0
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x1600][1].raw = 0x60410010                   # the statusword is read-only
    assert info.value.code == 0x06040041
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x1600][1].raw = 0x60400020                   # controlword is 16 bits, not 32
    assert info.value.code == 0x06040041
    node.sdo[0x1600][1].raw = 0x60400010
    node.sdo[0x1600][0].raw = 1
    node.sdo[0x1400][1].raw = 0x200 + NODE
    b.net.send_message(0x200 + NODE, bytes([0x06, 0x00]))      # now 2 bytes is the whole RPDO
    b.wait(lambda: node.state == "READY TO SWITCH ON", "shutdown applied at the next SYNC")


# -- 2026-11-30 (stop 32): parameters that would hang the drive, RPDO-written parameters,
#    NMT stop as an abort-connection event, the RPDO length error's EMCY episode

@pytest.mark.parametrize("index", [0x6087, 0x6081], ids=["0x6087", "0x6081"])
def test_torque_slope_and_profile_velocity_refuse_zero(bench, index):
    """0x6087 = 0: a stop ramp that never ends (a fault kept torque on for good); 0x6081 = 0: jaws
    that never move. Both abort 0x06090032 (value too low), by the EDS's LowLimit and the drive's
    own rule (which holds for an OD whose EDS has no LowLimit)."""
    node = bench.node
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[index].raw = 0
    assert info.value.code == 0x06090032
    assert node.sdo[index].raw == {0x6087: 5000, 0x6081: 50000}[index]
    with bench.host.lock:
        with pytest.raises(SdoAbortedError) as info:
            bench.host.drive.drive.check_write(index, 0, 0, False)
    assert info.value.code == 0x06090032
    node.sdo[index].raw = 1                                   # the least allowed


def test_a_zero_slope_that_bypassed_the_sdo_still_ends_the_fault_reaction(bench):
    """A torque slope of 0 in the OD (as a DCF or an RPDO could leave it before the rules held):
    the fault reaction's stop ramp ends at once (torque 0, FAULT), so a fault reset works."""
    b, node = bench, bench.node
    hold_part(b, torque=500)
    with b.host.lock:
        b.host.drive.objects.store(0x6087, 0, 0)
        b.host.drive.drive.invalidate()
    node.sdo[0x2110].raw = 0x2310
    b.wait(lambda: node.state == "FAULT", "FAULT after the fault reaction")
    assert b.values[0x6077] == 0 and b.values[0x2101] == 0
    node.reset_from_fault()
    assert node.state == "OPERATION ENABLED"


def map_rpdo1(b: Bench, entries: list[int]) -> None:
    """RPDO1 (0x1400/0x1600) mapped to ``entries`` by SDO, the master's own RPDO sender stopped."""
    node = b.node
    b.rpdo.stop()
    node.sdo[0x1400][1].raw = 0x80000200 + NODE
    node.sdo[0x1600][0].raw = 0
    for sub, entry in enumerate(entries, start=1):
        node.sdo[0x1600][sub].raw = entry
    node.sdo[0x1600][0].raw = len(entries)
    node.sdo[0x1400][1].raw = 0x200 + NODE


def test_rpdo_written_parameters_obey_the_sdo_rules_and_take_effect(bench):
    """0x6060 and 0x6072 are mappable: an RPDO's value goes by the SDO's rules (a PDO cannot abort:
    a refused value is not written, one manufacturer EMCY 0xFF10 names the object), and an
    accepted parameter takes effect (the drive re-reads it as after an SDO download)."""
    b, node = bench, bench.node
    map_rpdo1(b, [0x60400010, 0x60710010, 0x60600008, 0x60720010])
    node.emcy.reset()

    def send(cw, torque, mode, max_torque, n=5):
        for _ in range(n):
            b.net.send_message(0x200 + NODE, struct.pack("<HhbH", cw, torque, mode, max_torque))
            b.syncs(1)

    send(0x06, 0, 4, 1000)
    send(0x0F, 0, 4, 1000)
    assert node.state == "OPERATION ENABLED" and b.values[0x6061] == 4
    send(0x0F, 0, 3, 1000)                                     # mode 3: not supported (SDO: 0x06090030)
    assert node.sdo[0x6060].raw == 4 and b.values[0x6061] == 4
    b.emcy(0xFF10)
    refused = [e for e in node.emcy.log if e.code == 0xFF10]
    assert len(refused) == 1                                   # one per episode, not one per frame
    assert struct.unpack_from("<HBB", refused[0].data) == (0x6060, 0, 1)
    assert refused[0].register == 0x11 == node.sdo[0x1001].raw
    send(0x0F, 0, 4, 200)                                      # a correct RPDO ends the episode
    b.wait(lambda: any(e.code == 0 for e in node.emcy.log), "error-reset EMCY")
    assert node.sdo[0x1001].raw == 0 and node.sdo[0x6072].raw == 200
    with b.host.lock:
        b.host.drive.jaw_blocked_at(30.0)
    send(0x0F, 600, 4, 200, n=40)                              # max torque 200 from the RPDO holds
    assert b.values[0x6077] == 200 and node.statusword & 0x0800
    send(0x0F, 600, 4, 5000, n=3)                              # beyond 0x6072's HighLimit 3000
    assert node.sdo[0x6072].raw == 200 and b.values[0x6077] == 200
    assert len([e for e in node.emcy.log if e.code == 0xFF10]) == 2


def test_position_limit_min_not_below_max_aborts_max_less_than_min(bench):
    node = bench.node
    for sub, value in ((1, 80000), (1, 90000), (2, 0)):
        with pytest.raises(SdoAbortedError) as info:
            node.sdo[0x607D][sub].raw = value
        assert info.value.code == 0x06090036                   # CiA 301: max less than min
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x607D][2].raw = 6553501
    assert info.value.code == 0x06090031


def nmt_stop_and_start(b: Bench) -> None:
    """NMT stop, seen by the drive, then NMT start (the master's heartbeat keeps coming)."""
    b.node.nmt.state = "STOPPED"
    deadline = time.monotonic() + WAIT_S
    while True:
        with b.host.lock:
            if b.host.drive.state_name == "STOPPED":
                break
        assert time.monotonic() < deadline, "NMT stop not seen"
        time.sleep(0.01)
    b.node.nmt.state = "OPERATIONAL"
    b.syncs(3)


def test_nmt_stop_with_abort_connection_fault_sends_its_emcy_after_the_stop():
    b = Bench({(0x6007, 0): 1})
    try:
        node = b.node
        hold_part(b, torque=500)
        node.emcy.reset()
        nmt_stop_and_start(b)
        b.emcy(0x8130)                                         # owed while STOPPED, sent on leaving it
        b.wait(lambda: node.state == "FAULT", "FAULT after the fault reaction")
        assert b.values[0x603F] == 0x8130
        first = [e for e in node.emcy.log if e.code == 0x8130][0]
        assert first.register == 0x11 == node.sdo[0x1001].raw  # generic + communication
        assert b.values[0x6077] == 0
        node.reset_from_fault()                                # the master is there: the fault clears
        b.wait(lambda: b.values[0x603F] == 0, "error code cleared")
        b.emcy(0x0000)
        assert node.sdo[0x1001].raw == 0 and not node.statusword & 0x0080
    finally:
        b.close()


def test_nmt_stop_then_start_ends_the_communication_warning(bench):
    b, node = bench, bench.node                                # 0x6007 = 0: no action
    hold_part(b, torque=500)
    nmt_stop_and_start(b)
    b.wait(lambda: not node.statusword & 0x0080, "warning bit 7 cleared")
    b.wait(lambda: b.values[0x603F] == 0, "0x603F cleared")
    assert node.state == "OPERATION ENABLED" and b.values[0x6077] == 500 and node.sdo[0x1001].raw == 0


def test_short_rpdos_are_one_emcy_episode_ended_by_a_correct_one(bench):
    b, node = bench, bench.node
    node.state = "OPERATION ENABLED"
    node.emcy.reset()
    b.rpdo.stop()
    for _ in range(10):
        b.net.send_message(0x200 + NODE, bytes([0x0F, 0x00]))  # 2 of the 8 mapped bytes
        b.syncs(1)
    b.emcy(0x8210)
    assert node.emcy.log[-1].register == 0x11 == node.sdo[0x1001].raw
    b.net.send_message(0x200 + NODE, struct.pack("<Hhi", 0x0F, 0, 0))
    b.emcy(0x0000)
    assert len([e for e in node.emcy.log if e.code == 0x8210]) == 1       # not one per frame
    with b.host.lock:
        assert b.host.drive.rpdo.length_errors == 10                     # every one counted
    assert node.sdo[0x1001].raw == 0 and not node.emcy.active
    assert node.state == "OPERATION ENABLED"


@pytest.mark.parametrize("index", [0x6087, 0x6081], ids=["0x6087", "0x6081"])
def test_a_start_up_value_of_zero_is_refused_too(index):
    """The DCF / start-up path (GripperDrive.configure, the SDO's rules with startup=True)."""
    from taxel_net.errors import ParameterError

    host = DriveHost(NODE, "virtual", f"g22-{uuid.uuid4().hex[:8]}", startup={(index, 0): 0})
    try:
        with pytest.raises(ParameterError, match="0x06090032"):
            host.start()
    finally:
        host.stop()


def test_a_parameter_written_by_a_synchronous_rpdo_holds_from_its_sync():
    """0x6072 (max torque) mapped in a synchronous RPDO: the SYNC that writes it steps with it
    (before: the step of that SYNC used the old limit, the new one held one SYNC later)."""
    host = DriveHost(NODE, "virtual", f"g22-{uuid.uuid4().hex[:8]}").start()
    try:
        with host.lock:
            d = host.drive
            d.objects.store(0x1600, 0, 0)
            for sub, entry in enumerate((0x60400010, 0x60710010, 0x60600008, 0x60720010), start=1):
                d.objects.store(0x1600, sub, entry)
            d.objects.store(0x1600, 0, 4)
            d.objects.store(0x1400, 2, 1)                        # synchronous: applied at the SYNC
            d.rpdo.invalidate()
            d.on_nmt(0x01)
            app = d.drive
            app.sample()
            assert app.axis.limits.max_torque == 1000.0
            d.on_rpdo(0x200 + NODE, struct.pack("<HhbH", 0x06, 0, 4, 200))
            assert app.axis.limits.max_torque == 1000.0          # latched, not yet written
            app.sample()                                         # the SYNC that writes it
            assert d.objects.read(0x6072) == 200 and app.axis.limits.max_torque == 200.0
    finally:
        host.stop()
