"""LSS slave of the node twins (CiA 305), driven by canopen's ``LssMaster`` on a python-can
virtual bus, by raw frames, and unit by unit (``node_sim.lss.LssSlave``)."""

from __future__ import annotations

import struct
import threading
import time
import uuid

import can
import canopen
import pytest
from canopen.lss import LssError

from node_sim import lss as lssx
from node_sim.od import EDS_PATH
from node_sim.rig import Rig, identity_serial
from taxel_net.scene import BusSpec, MasterSpec, Scene, TaxelSpec

WAIT = 10.0
# a scene name whose serial numbers have few 1 bits (crc32 & 0xFFFF = 0x0044): canopen's
# fast scan waits one response time-out for every 1 bit of the LSS address
NAME = "lss-650"


def scene(node_ids=(1, 2, 4), assign_ids="lss", name=NAME):
    channel = f"test-lss-{uuid.uuid4().hex[:10]}"
    return Scene(path="<test>", name=name, bus=BusSpec(channels=(channel,)),
                 taxels=tuple(TaxelSpec(node_id=n, kind="R") for n in node_ids),
                 master=MasterSpec(assign_ids=assign_ids))


class Master:
    """canopen's master (``Network``: LssMaster, SDO client) plus a frame recorder."""

    def __init__(self, channel):
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=channel)
        self.lss = self.network.lss
        self.lss.RESPONSE_TIMEOUT = 0.2
        self.frames: list[tuple[int, bytes]] = []
        self.lock = threading.Lock()
        self.network.notifier.add_listener(self._record)

    def _record(self, msg):
        with self.lock:
            self.frames.append((msg.arbitration_id, bytes(msg.data)))

    def of(self, can_id):
        with self.lock:
            return [d for i, d in self.frames if i == can_id]

    def wait(self, can_id, count=1):
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline:
            if len(self.of(can_id)) >= count:
                return self.of(can_id)
            time.sleep(0.005)
        raise AssertionError(f"0x{can_id:03X}: {len(self.of(can_id))} < {count}")

    def mark(self):
        with self.lock:
            return len(self.frames)

    def wait_bootup(self, node_id, since=0):
        """The boot-up of ``node_id`` (0x700+id, state 0) seen after frame number ``since``."""
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline:
            with self.lock:
                if (0x700 + node_id, b"\x00") in self.frames[since:]:
                    return
            time.sleep(0.005)
        raise AssertionError(f"no boot-up of node {node_id}")

    def raw(self, cs, payload=b""):
        self.network.send_message(lssx.LSS_MASTER_COB, bytes((cs,)) + payload.ljust(7, b"\x00"))

    def answers_to(self, frames, barrier):
        """Send raw LSS frames, then return the LSS answers they caused. ``barrier``: a
        configured node's ID; its SDO answer to a read sent after the frames comes after every
        answer to them (the twins of a channel handle frames in order, one thread)."""
        before = len(self.of(lssx.LSS_SLAVE_COB))
        for cs, payload in frames:
            self.raw(cs, payload)
        self.sdo_read(barrier, 0x1018, 4)
        return self.of(lssx.LSS_SLAVE_COB)[before:]

    def sdo_read(self, node_id, index, sub):
        node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
        self.network.add_node(node)
        try:
            return struct.unpack("<I", node.sdo.upload(index, sub))[0]
        finally:
            del self.network[node_id]

    def close(self):
        self.network.disconnect()


def select(master, address):
    """Switch state selective by the 128-bit LSS address (canopen's LssMaster)."""
    return master.lss.send_switch_state_selective(*address)


def wait_for(predicate, what):
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.005)
    raise AssertionError(what)


# ---------------------------------------------------------------------------------------
# canopen's LssMaster against the rig
# ---------------------------------------------------------------------------------------

def test_fast_scan_finds_every_unconfigured_twin_and_assigns_ids():
    s = scene((1, 2, 4))
    with Rig(s) as rig:
        assert rig.nodes == {}  # non-configured: no boot-up, no node on the bus
        assert all(sl.active_node_id == 0xFF for sl in rig.lss_slaves.values())
        master = Master(s.bus.channels[0])
        try:
            expected = {identity_serial(s, t) for t in s.taxels}
            found, attempts = {}, 0
            while True:
                attempts += 1
                ok, address = master.lss.fast_scan()
                if not ok:
                    if len(found) == len(expected) or attempts > 3 * len(expected):
                        break
                    continue  # a late answer misread as a 1 bit fails the last confirmation: again
                assert address[:3] == [0, 0x7A01, 0x00010000]
                assert master.lss.inquire_node_id() == 0xFF
                assert master.lss.inquire_lss_address(lssx.CS_INQUIRE_IDENTITY[3]) == address[3]
                node_id = 100 + len(found)
                master.lss.configure_node_id(node_id)
                master.lss.store_configuration()
                master.lss.send_switch_state_global(master.lss.WAITING_STATE)
                found[address[3]] = node_id
                master.wait_bootup(node_id)  # boot-up under the new node-ID
            assert set(found) == expected
            assert sorted(nid for _, nid in rig.nodes) == [100, 101, 102]
            for serial, node_id in found.items():
                assert master.sdo_read(node_id, 0x1018, 4) == serial  # the same device over SDO
            assert all(sl.stored_node_id == found[sl.address[3]] for sl in rig.lss_slaves.values())
            ok, _ = master.lss.fast_scan()  # nothing left to find
            assert not ok
        finally:
            master.close()


def test_configured_twin_takes_a_new_node_id_at_reset_communication():
    s = scene((5, 6), assign_ids="scene")
    with Rig(s) as rig:
        master = Master(s.bus.channels[0])
        try:
            address = rig.lss_slaves[0].address
            assert address[3] == identity_serial(s, s.taxels[0])
            assert select(master, address)
            assert master.lss.inquire_node_id() == 5
            for k, cs in enumerate(lssx.CS_INQUIRE_IDENTITY):
                assert master.lss.inquire_lss_address(cs) == address[k]
            master.lss.configure_node_id(9)
            assert master.lss.inquire_node_id() == 5  # pending, not active yet
            master.lss.send_switch_state_global(master.lss.WAITING_STATE)
            assert sorted(nid for _, nid in rig.nodes) == [5, 6]  # a configured node waits for the reset
            mark = master.mark()
            master.network.nmt.send_command(0x82)  # reset communication, all nodes
            master.wait_bootup(9, mark)
            master.wait_bootup(6, mark)
            assert sorted(nid for _, nid in rig.nodes) == [6, 9]
            assert master.sdo_read(9, 0x1018, 4) == address[3]
            # not stored: a reset node brings back the stored node-ID (5)
            mark = master.mark()
            master.network.send_message(0x000, bytes((0x81, 9)))
            master.wait_bootup(5, mark)
            assert sorted(nid for _, nid in rig.nodes) == [5, 6]
        finally:
            master.close()


def test_store_keeps_the_node_id_across_reset_node_and_0xff_unconfigures():
    s = scene((5,), assign_ids="scene")
    with Rig(s) as rig:
        master = Master(s.bus.channels[0])
        try:
            slave = rig.lss_slaves[0]
            assert select(master, slave.address)
            master.lss.configure_node_id(17)
            master.lss.store_configuration()
            master.lss.send_switch_state_global(master.lss.WAITING_STATE)
            master.network.send_message(0x000, bytes((0x81, 5)))  # reset node: stored -> active
            master.wait_bootup(17)
            assert [nid for _, nid in rig.nodes] == [17] and slave.stored_node_id == 17
            # configure 0xFF: after the reset the node is non-configured (LSS only)
            master.lss.send_switch_state_global(master.lss.CONFIGURATION_STATE)
            master.lss.configure_node_id(0xFF)
            master.lss.send_switch_state_global(master.lss.WAITING_STATE)
            master.network.send_message(0x000, bytes((0x82, 0)))
            wait_for(lambda: rig.nodes == {}, "the node left the bus")
            assert slave.active_node_id == 0xFF
            ok, address = master.lss.fast_scan()  # found again by fast scan
            assert ok and tuple(address) == slave.address
        finally:
            master.close()


def test_configuration_services_refuse_what_the_node_cannot_take():
    s = scene((5,), assign_ids="scene")
    with Rig(s, bitrate=500_000) as rig:
        master = Master(s.bus.channels[0])
        try:
            slave = rig.lss_slaves[0]
            # not in configuration state: configuration requests are not answered
            with pytest.raises(LssError, match="No LSS response"):
                master.lss.inquire_node_id()
            master.lss.send_switch_state_global(master.lss.CONFIGURATION_STATE)
            for bad in (0, 128, 0xFE):
                with pytest.raises(LssError, match="LSS Error: 1"):
                    master.lss.configure_node_id(bad)
            assert slave.pending_node_id == 5
            # the EDS supports 125, 250, 500 and 1000 kbit/s; 5 is reserved, 9 automatic
            # detection, 10 outside the CiA 301 table
            assert canopen.import_od(str(EDS_PATH)).device_information.allowed_baudrates == {
                125_000, 250_000, 500_000, 1_000_000}
            for bad in (1, 5, 6, 7, 8, 9, 10):
                with pytest.raises(LssError, match="LSS Error: 1"):
                    master.lss.configure_bit_timing(bad)
            assert slave.bit_rate == 500_000
            master.lss.configure_bit_timing(3)  # 250 kbit/s
            assert slave.pending_bit_rate == 250_000 and slave.bit_rate == 500_000
            master.lss.activate_bit_timing(1000)  # switch after 1 s, silent for 2 s
            with pytest.raises(LssError, match="No LSS response"):
                master.lss.store_configuration()
            wait_for(lambda: slave.bit_rate == 250_000, "bit rate switched after the delay")
            wait_for(lambda: not slave.switching, "second switch delay over")
            master.lss.store_configuration()
            assert slave.stored_bit_rate == 250_000
        finally:
            master.close()


def test_identify_services_and_fastscan_answer_once_per_request():
    s = scene((1, 2, 4))
    with Rig(s) as rig:
        master = Master(s.bus.channels[0])
        try:
            slaves = sorted(rig.lss_slaves.values(), key=lambda sl: sl.address[3])
            serials = [sl.address[3] for sl in slaves]
            # the first one configured (node-ID 10) serves as the barrier of answers_to
            assert select(master, slaves[0].address)
            master.lss.configure_node_id(10)
            master.lss.send_switch_state_global(master.lss.WAITING_STATE)
            master.wait_bootup(10)
            u32 = struct.Struct("<I").pack

            def ask(*frames):
                return master.answers_to(frames, barrier=10)

            def identify(vendor, product, rev, serial):
                return ask((0x46, u32(vendor)), (0x47, u32(product)), (0x48, u32(rev[0])), (0x49, u32(rev[1])),
                           (0x4A, u32(serial[0])), (0x4B, u32(serial[1])))

            ident = bytes((0x4F,)) + bytes(7)
            # three match (configured or not): one frame on the bus (identical answers arbitrate as one)
            assert identify(0, 0x7A01, (0, 0xFFFFFFFF), (0, 0xFFFFFFFF)) == [ident]
            assert identify(0, 0x7A01, (0x10000, 0x10000), (serials[1], serials[1])) == [ident]
            assert identify(0, 0x7A01, (0x10001, 0xFFFFFFFF), (0, 0xFFFFFFFF)) == []        # revision
            assert identify(1, 0x7A01, (0, 0xFFFFFFFF), (0, 0xFFFFFFFF)) == []              # vendor
            assert identify(0, 0x7A02, (0, 0xFFFFFFFF), (0, 0xFFFFFFFF)) == []              # product
            assert identify(0, 0x7A01, (0, 0xFFFFFFFF), (serials[2] + 1, 0xFFFFFFFF)) == []  # serial
            nonconf = bytes((0x50,)) + bytes(7)
            assert ask((0x4C, b"")) == [nonconf]
            # a request of another length is ignored
            master.network.send_message(lssx.LSS_MASTER_COB, bytes((0x4C,)))
            assert ask() == []
            # fastscan reset: the two non-configured slaves answer (one frame)
            assert ask((0x51, bytes(4) + bytes((0x80, 0, 0)))) == [ident]
            # configure the others: no one answers identify non-configured or fastscan any more
            for k, sl in enumerate(slaves[1:], 11):
                assert select(master, sl.address)
                master.lss.configure_node_id(k)
                master.lss.send_switch_state_global(master.lss.WAITING_STATE)
                master.wait_bootup(k)
            assert ask((0x4C, b"")) == []
            assert ask((0x51, bytes(4) + bytes((0x80, 0, 0)))) == []
            # in configuration state, inquire node-ID: one answer per node (they differ)
            master.lss.send_switch_state_global(master.lss.CONFIGURATION_STATE)
            assert sorted(a[:2] for a in ask((0x5E, b""))) == [b"\x5e\x0a", b"\x5e\x0b", b"\x5e\x0c"]
        finally:
            master.close()


def test_dead_node_answers_no_lss_request():
    s = scene((5, 6), assign_ids="scene")
    with Rig(s) as rig:
        master = Master(s.bus.channels[0])
        try:
            rig.drop_node(5)
            with pytest.raises(LssError, match="No LSS response"):
                select(master, rig.lss_slaves[0].address)
            rig.restore_node(5)
            master.lss.send_switch_state_global(master.lss.WAITING_STATE)
            assert select(master, rig.lss_slaves[0].address)
            assert master.lss.inquire_node_id() == 5
        finally:
            master.close()


# ---------------------------------------------------------------------------------------
# LssSlave on its own
# ---------------------------------------------------------------------------------------

ADDRESS = (0, 0x7A01, 0x00010000, 0x00440007)


def frame(cs, value=0, *rest):
    return bytes((cs,)) + struct.pack("<I", value) + bytes(rest).ljust(3, b"\x00")


def fastscan(slave, value, bit, sub, nxt):
    return slave.on_request(frame(0x51, value, bit, sub, nxt)) is not None


def test_fastscan_protocol_step_by_step():
    slave = lssx.LssSlave(ADDRESS)
    assert fastscan(slave, 0, 31, 0, 0)               # the scan position starts at the vendor-ID
    assert not fastscan(slave, 1 << 31, 31, 0, 0)     # vendor bit 31 is 0
    assert fastscan(slave, 0, 0x80, 0, 0)             # reset: every non-configured slave answers
    assert fastscan(slave, 0, 31, 0, 0)               # vendor bit 31 = 0
    assert fastscan(slave, 0, 0, 0, 1)                # vendor complete, next: product
    assert not fastscan(slave, 0, 0, 0, 1)            # no longer at the vendor-ID
    assert not fastscan(slave, 0x7A00, 0, 1, 2)       # wrong product
    assert fastscan(slave, 0x7A00, 1, 1, 1)           # bits 1..31 match
    assert fastscan(slave, 0x7A01, 0, 1, 2)
    assert fastscan(slave, 0x00010000, 0, 2, 3)
    assert slave.state == lssx.WAITING
    assert not fastscan(slave, 0x00440006, 0, 3, 0)   # serial mismatch in bit 0
    assert fastscan(slave, 0x00440000, 3, 3, 3)       # bits 3..31 of the serial
    assert fastscan(slave, 0x00440007, 0, 3, 0)       # whole address: configuration state
    assert slave.state == lssx.CONFIGURATION
    assert not fastscan(slave, 0, 0x80, 0, 0)         # fastscan only in the waiting state
    assert slave.on_request(frame(0x5E)) == bytes((0x5E, 0xFF)) + bytes(6)
    # invalid BitChecked / LSSSub / LSSNext are ignored
    slave.on_request(frame(0x04, 0))
    assert fastscan(slave, 0, 0x80, 0, 0)
    for bit, sub, nxt in ((32, 0, 0), (0x7F, 0, 0), (0, 4, 0), (0, 0, 4)):
        assert not fastscan(slave, 0, bit, sub, nxt)


def test_switch_state_selective_needs_the_whole_address_in_one_sequence():
    slave = lssx.LssSlave(ADDRESS, node_id=7)
    for cs, v in zip(range(0x40, 0x44), ADDRESS):
        answer = slave.on_request(frame(cs, v))
    assert answer == bytes((0x44,)) + bytes(7) and slave.state == lssx.CONFIGURATION
    slave.on_request(frame(0x04, 0))
    # a serial frame alone (the first three of an earlier sequence are forgotten) selects nothing
    assert slave.on_request(frame(0x43, ADDRESS[3])) is None and slave.state == lssx.WAITING
    # a configured node takes no part in fastscan and "identify non-configured"
    assert not fastscan(slave, 0, 0x80, 0, 0)
    assert slave.on_request(frame(0x4C)) is None


def test_node_id_activation_rules():
    started = []
    slave = lssx.LssSlave(ADDRESS, activate=started.append)
    slave.on_request(frame(0x04, 1))  # switch state global: configuration
    assert slave.on_request(frame(0x11, 0x23)) == bytes((0x11, 0)) + bytes(6)
    assert slave.pending_node_id == 0x23 and slave.active_node_id == 0xFF and started == []
    assert not slave.non_configured  # a node-ID is pending: out of fastscan
    slave.on_request(frame(0x04, 0))  # back to waiting: a non-configured node starts
    assert started == [0x23] and slave.active_node_id == 0x23
    # not stored: a reset node returns to the stored node-ID (non-configured)
    assert slave.on_reset(application=True) == 0xFF
    slave.on_request(frame(0x04, 1))
    slave.on_request(frame(0x11, 0x24))
    slave.on_request(frame(0x17))  # store
    slave.on_request(frame(0x04, 0))
    assert started == [0x23, 0x24]
    assert slave.on_reset(application=True) == 0x24
    assert slave.on_reset(application=False) == 0x24
    assert slave.state == lssx.WAITING
