"""Node twin protocol behaviour on a python-can virtual bus, seen from a master's side.

The master side is canopen's own client stack (``canopen.Network`` + ``RemoteNode`` with the
same EDS) plus a raw monitor bus that records every frame with its bus timestamp. Waits
are generous and event-based; nothing asserts wall-clock speed. Inhibit time and event timer
are protocol behaviour and are checked on the frames' timestamps.
"""

from __future__ import annotations

import itertools
import math
import struct
import threading
import time
import uuid

import can
import canopen
import numpy as np
import pytest

from taxel_net.scene import TAXEL_KINDS, BusSpec, FaultSpec, Scene, TaxelSpec
from node_sim import emcy as em
from node_sim.od import EDS_PATH
from node_sim.rig import Rig

WAIT = 5.0  # generous upper bound for "eventually"


MARKER_ID = 0x1ABCDEF  # extended ID: the node twins and canopen's master ignore it


class Monitor:
    """Records every frame on a virtual channel (bus timestamps, set by the sender's ``send``).

    ``since=t`` (a ``time.time()`` taken after the test saw a state change) keeps only frames
    sent after it; :meth:`barrier` returns once every frame sent before the call is recorded
    (python-can's virtual bus queues are FIFO), so "no such frame" checks cannot race."""

    def __init__(self, channel: str):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        self.frames: list[can.Message] = []
        self._lock = threading.Lock()
        self._markers = itertools.count()
        self.notifier = can.Notifier(self.bus, [self._on], timeout=0.05)

    def _on(self, msg: can.Message) -> None:
        with self._lock:
            self.frames.append(msg)

    def snapshot(self) -> list[can.Message]:
        with self._lock:
            return list(self.frames)

    def of(self, can_id: int, since: float = -math.inf) -> list[can.Message]:
        return [m for m in self.snapshot()
                if m.arbitration_id == can_id and not m.is_extended_id and m.timestamp > since]

    def barrier(self) -> None:
        tag = struct.pack("<Q", next(self._markers))
        self.bus.send(can.Message(arbitration_id=MARKER_ID, data=tag, is_extended_id=True))
        self.wait_for(lambda m: m.is_extended_id and m.arbitration_id == MARKER_ID and bytes(m.data) == tag)

    def wait_for(self, pred, timeout: float = WAIT) -> list[can.Message]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hits = [m for m in self.snapshot() if pred(m)]
            if hits:
                return hits
            time.sleep(0.005)
        raise AssertionError("expected frame never arrived")

    def wait_count(self, can_id: int, count: int, timeout: float = WAIT,
                   since: float = -math.inf) -> list[can.Message]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hits = self.of(can_id, since)
            if len(hits) >= count:
                return hits
            time.sleep(0.005)
        raise AssertionError(f"0x{can_id:03X}: {len(self.of(can_id, since))} frames, expected {count}")

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


def make_scene(channel: str, n: int = 3, **bus) -> Scene:
    taxels = tuple(TaxelSpec(node_id=i + 1, kind=("R", "C", "P")[i % 3], zeta_mv=1.5, noise_mv=0.5,
                             noise_sigma_mv=0.0, x=10.0 * i, y=-2.5, slope=0.1661, intercept=-0.0155)
                   for i in range(n))
    bus.setdefault("heartbeat_producer_ms", 20)
    return Scene(path="<test>", name="test", taxels=taxels, bus=BusSpec(channels=(channel,), **bus))


@pytest.fixture
def channel():
    return f"test-node-{uuid.uuid4().hex[:10]}"


class Setup:
    def __init__(self, channel, scene, source):
        self.monitor = Monitor(channel)
        self.rig = Rig(scene, reading_source=source).start()
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=channel)
        self.remote = {}
        for t in scene.taxels:
            rn = canopen.RemoteNode(t.node_id, str(EDS_PATH))
            rn.sdo.RESPONSE_TIMEOUT = 2.0
            self.network.add_node(rn)
            self.remote[t.node_id] = rn

    def sync(self, count: int = 1, gap: float = 0.0) -> None:
        for _ in range(count):
            before = self.rig.cycle()
            self.network.send_message(0x80, b"")
            target = 0 if before is None else before + 1
            assert self.rig.wait_cycle(target, timeout=WAIT)
            if gap:
                time.sleep(gap)

    def nmt(self, command: int, node_id: int = 0) -> None:
        self.network.send_message(0x000, bytes([command, node_id]))

    def close(self):
        self.network.disconnect()
        self.rig.stop()
        self.monitor.close()


@pytest.fixture
def setup_factory(channel):
    made = []

    def make(source=None, n=3, **bus):
        scene = make_scene(channel, n, **bus)
        if source is None:
            def source(cycle):
                return np.full(n, 0.0)
        s = Setup(channel, scene, source)
        made.append(s)
        return s

    yield make
    for s in made:
        s.close()


def wait_until(pred, timeout=WAIT):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.005)
    return False


def heartbeat_state(s: Setup, node_id: int) -> int:
    """State byte of the first heartbeat sent after the call (the node sends its state and
    changes it under one lock, so a beat sent later carries the state the test saw)."""
    hb = s.monitor.wait_count(0x700 + node_id, 1, since=time.time())
    return hb[0].data[0]


def from_bootup(frames: list[can.Message]) -> list[bytes]:
    """Payloads from the (single) boot-up frame on: what the node sent after a reset."""
    payloads = [bytes(f.data) for f in frames]
    assert payloads.count(b"\x00") == 1, payloads
    return payloads[payloads.index(b"\x00"):]


# ------------------------------------------------------------------------ boot-up / heartbeat

def test_boot_up_then_pre_operational_heartbeats(setup_factory):
    s = setup_factory()
    for nid in (1, 2, 3):
        frames = s.monitor.wait_count(0x700 + nid, 3)
        assert bytes(frames[0].data) == b"\x00"                 # boot-up
        assert all(bytes(f.data) == b"\x7f" for f in frames[1:])  # pre-operational heartbeats
        gaps = np.diff([f.timestamp for f in frames[1:]])
        assert np.all(gaps >= 0.020 * 0.85), gaps              # producer time 0x1017 = 20 ms
        assert s.remote[nid].sdo[0x1017].raw == 20


# ------------------------------------------------------------------------ NMT

def test_nmt_addressed_and_broadcast(setup_factory):
    s = setup_factory()
    s.monitor.wait_count(0x703, 2)
    s.nmt(0x01, 2)                                   # start node 2 only
    assert wait_until(lambda: s.rig.node(2).state == 0x05)
    assert heartbeat_state(s, 2) == 0x05
    assert heartbeat_state(s, 1) == 0x7F and heartbeat_state(s, 3) == 0x7F
    s.nmt(0x02, 0)                                   # stop all
    assert wait_until(lambda: all(s.rig.node(i).state == 0x04 for i in (1, 2, 3)))
    assert {heartbeat_state(s, i) for i in (1, 2, 3)} == {0x04}
    with pytest.raises(canopen.SdoCommunicationError):  # no SDO in STOPPED
        s.remote[1].sdo.RESPONSE_TIMEOUT = 0.3
        s.remote[1].sdo[0x1000].raw
    s.nmt(0x80, 3)                                   # node 3 to pre-operational
    assert wait_until(lambda: s.rig.node(3).state == 0x7F)
    assert heartbeat_state(s, 3) == 0x7F and heartbeat_state(s, 1) == 0x04
    s.nmt(0x01, 0)                                   # start all (from stopped and pre-op)
    assert wait_until(lambda: all(s.rig.node(i).state == 0x05 for i in (1, 2, 3)))
    s.nmt(0x80, 0)
    assert wait_until(lambda: all(s.rig.node(i).state == 0x7F for i in (1, 2, 3)))
    s.nmt(0x01, 9)                                   # a node-ID that is not on the bus
    assert s.remote[2].sdo[0x1000].raw == 0          # answered after the NMT frame was handled
    assert all(s.rig.node(i).state == 0x7F for i in (1, 2, 3))


def test_reset_node_restores_scene_values_and_boots(setup_factory):
    s = setup_factory()
    s.monitor.wait_count(0x702, 2)
    rn = s.remote[2]
    rn.sdo[0x2001][1].raw = 4.25          # ζ (manufacturer area)
    rn.sdo[0x1017].raw = 35               # heartbeat (communication area)
    rn.sdo[0x6126][1].raw = 2.0           # CiA 404 area
    s.nmt(0x01, 2)
    assert wait_until(lambda: s.rig.node(2).state == 0x05)
    t0 = time.time()
    s.nmt(0x81, 2)
    assert wait_until(lambda: len(s.monitor.of(0x702, t0)) >= 2
                      and b"\x00" in [bytes(f.data) for f in s.monitor.of(0x702, t0)[:-1]])
    assert from_bootup(s.monitor.of(0x702, t0))[:2] == [b"\x00", b"\x7f"]   # boot-up, pre-op beat
    assert s.rig.node(2).state == 0x7F
    assert rn.sdo[0x2001][1].raw == pytest.approx(1.5)       # scene ζ
    assert rn.sdo[0x1017].raw == 20                          # scene heartbeat
    assert rn.sdo[0x6126][1].raw == pytest.approx(0.1661, rel=1e-6)  # scene slope (REAL32)
    assert s.rig.node(1).state == 0x7F and b"\x00" not in [bytes(f.data) for f in s.monitor.of(0x701, t0)]


def test_reset_communication_restores_only_comm_area(setup_factory):
    s = setup_factory()
    s.monitor.wait_count(0x701, 2)
    rn = s.remote[1]
    rn.sdo[0x2001][1].raw = 4.25
    rn.sdo[0x1017].raw = 35
    rn.sdo[0x1800][5].raw = 123
    t0 = time.time()
    s.nmt(0x82, 0)
    for nid in (1, 2, 3):
        assert wait_until(lambda: b"\x00" in [bytes(f.data) for f in s.monitor.of(0x700 + nid, t0)[:-1]])
        assert from_bootup(s.monitor.of(0x700 + nid, t0))[:2] == [b"\x00", b"\x7f"]
    assert rn.sdo[0x1017].raw == 20
    assert rn.sdo[0x1800][5].raw == 0
    assert rn.sdo[0x2001][1].raw == pytest.approx(4.25)      # not communication area: kept


# ------------------------------------------------------------------------ SYNC-driven TPDOs

def _readings_by_cycle(cycle: int) -> np.ndarray:
    # node 1 alternates around its threshold: X - N = 1.5 (>= ζ = 1.5: present) / 1.49 (absent)
    x1 = 2.0 if cycle % 2 == 0 else 1.99
    return np.array([x1, 0.0, 7.0])


def test_sync_tpdo_type_1_carries_local_decisions(setup_factory):
    s = setup_factory(_readings_by_cycle)
    s.sync(2)                                  # pre-operational: samples, but no TPDO
    s.monitor.barrier()
    assert s.monitor.of(0x181) == []
    assert s.remote[1].sdo[0x2000].raw == -1   # cycle 1: X = 1.99 -> absent
    assert s.remote[1].sdo[0x6130][1].raw == pytest.approx(1.99, rel=1e-6)
    s.nmt(0x01)
    assert wait_until(lambda: all(s.rig.node(i).state == 0x05 for i in (1, 2, 3)))
    s.sync(6, gap=0.005)
    for nid, expected in ((1, [1, -1, 1, -1, 1, -1]), (2, [-1] * 6), (3, [1] * 6)):
        frames = s.monitor.wait_count(0x180 + nid, 6)
        assert [struct.unpack("<b", bytes(f.data))[0] for f in frames] == expected
        assert all(len(f.data) == 1 for f in frames)
    s.monitor.barrier()
    assert s.monitor.of(0x281) == []           # TPDO2 (raw mode) disabled in decision mode


def test_sync_tpdo_every_third_sync(setup_factory):
    s = setup_factory(_readings_by_cycle, transmission_type=3)
    s.nmt(0x01)
    assert wait_until(lambda: s.rig.node(1).state == 0x05)
    s.sync(9, gap=0.003)
    s.monitor.barrier()
    syncs = [m.timestamp for m in s.monitor.of(0x080)]
    tpdos = s.monitor.of(0x181)
    assert len(syncs) == 9 and len(tpdos) == 3
    # sent after the 3rd, 6th and 9th SYNC (cycles 2, 5, 8): X = 2.0, 1.99, 2.0
    assert [struct.unpack("<b", bytes(f.data))[0] for f in tpdos] == [1, -1, 1]
    for k, f in enumerate(tpdos):
        assert syncs[3 * k + 2] <= f.timestamp
        if 3 * k + 3 < len(syncs):
            assert f.timestamp <= syncs[3 * k + 3]


def test_raw_mode_enables_tpdo2_with_process_value(setup_factory):
    s = setup_factory(_readings_by_cycle, mode="raw")
    s.nmt(0x01)
    assert wait_until(lambda: s.rig.node(1).state == 0x05)
    s.sync(2, gap=0.005)
    frames = s.monitor.wait_count(0x281, 2)
    values = [struct.unpack("<f", bytes(f.data))[0] for f in frames]
    assert values == [pytest.approx(2.0), pytest.approx(1.99, rel=1e-6)]
    assert s.remote[3].sdo[0x1801][1].raw == 0x40000283   # valid, bit 30: no RTR


# ------------------------------------------------------------------------ event-driven TPDOs

def test_event_driven_inhibit_time_spacing(setup_factory):
    # node 1's decision flips on every SYNC; SYNCs come every ~2 ms; inhibit time 40 ms
    s = setup_factory(_readings_by_cycle, transmission_type=254, inhibit_time_100us=400)
    s.nmt(0x01)
    assert wait_until(lambda: s.rig.node(1).state == 0x05)
    s.sync(60, gap=0.002)
    # a change inside the inhibit window goes out when the window ends (<= 40 ms after the
    # last transmission): wait that long, then until every timer due by now has run
    time.sleep(0.040)
    timers_ran = threading.Event()
    s.rig.node(1).link.scheduler.call_at(time.monotonic(), timers_ran.set)
    assert timers_ran.wait(WAIT)
    s.monitor.barrier()
    frames = s.monitor.of(0x181)
    assert len(frames) >= 2
    gaps = np.diff([f.timestamp for f in frames])
    assert np.all(gaps >= 0.040 - 0.0005), gaps
    # the last frame carries the decision of the last cycle (59: X = 1.99 -> absent)
    assert struct.unpack("<b", bytes(frames[-1].data))[0] == -1
    # node 3 never changes: the transmission on entering operational (OD default -1, nothing
    # sampled yet), then +1 from the first SYNC on, and nothing more
    assert [bytes(f.data) for f in s.monitor.of(0x183)] == [b"\xff", b"\x01"]


def test_event_timer_refreshes_unchanged_data(setup_factory):
    s = setup_factory(transmission_type=255, event_timer_ms=30)
    s.nmt(0x01, 2)
    frames = s.monitor.wait_count(0x182, 4)
    gaps = np.diff([f.timestamp for f in frames])
    assert np.all(gaps >= 0.030 * 0.95), gaps
    assert all(bytes(f.data) == b"\xff" for f in frames)
    assert s.monitor.of(0x181) == []  # node 1 still pre-operational
    s.nmt(0x80, 2)
    assert wait_until(lambda: s.rig.node(2).state == 0x7F)
    t0 = time.time()
    time.sleep(0.1)                        # > 3 event-timer periods
    s.monitor.barrier()
    assert s.monitor.of(0x182, t0) == []   # no refresh outside operational


# ------------------------------------------------------------------------ SDO

def _abort(fn) -> int:
    with pytest.raises(canopen.SdoAbortedError) as info:
        fn()
    return info.value.code


def test_sdo_reads_and_configuration_writes(setup_factory):
    s = setup_factory(_readings_by_cycle)
    rn = s.remote[2]
    assert rn.sdo[0x1000].raw == 0  # device type: no device profile
    assert rn.sdo[0x1018][2].raw == 0x7A01
    assert rn.sdo[0x1200][1].raw == 0x602 and rn.sdo[0x1200][2].raw == 0x582
    assert rn.sdo[0x2001][3].raw == TAXEL_KINDS["C"]   # node 2 = second taxel, kind C
    assert rn.sdo[0x2001][4].raw == pytest.approx(10.0)
    assert rn.sdo[0x2001][5].raw == pytest.approx(-2.5)
    assert rn.sdo[0x2001][2].raw == pytest.approx(0.5)
    for code in TAXEL_KINDS.values():
        rn.sdo[0x2001][3].raw = code
        assert rn.sdo[0x2001][3].raw == code
    # a new ζ changes the decision on the next SYNC: node 2 reads 0.0 (X - N = -0.5)
    s.remote[2].sdo[0x2001][2].raw = -1.0   # N = -1: X - N = 1.0
    s.remote[2].sdo[0x2001][1].raw = 1.0    # ζ = 1.0 -> present (1.0 >= 1.0)
    s.sync(1)
    assert rn.sdo[0x2000].raw == 1
    rn.sdo[0x2001][1].raw = 1.01
    s.sync(1)
    assert rn.sdo[0x2000].raw == -1


def test_sdo_abort_codes(setup_factory):
    s = setup_factory()
    rn = s.remote[1]
    zeta = rn.sdo[0x2001][1]
    assert _abort(lambda: setattr(zeta, "raw", -0.5)) == 0x06090032          # below LowLimit 0
    assert _abort(lambda: setattr(zeta, "raw", math.nan)) == 0x06090030       # not finite
    assert _abort(lambda: setattr(zeta, "raw", math.inf)) == 0x06090030
    assert _abort(lambda: setattr(rn.sdo[0x2001][2], "raw", math.nan)) == 0x06090030
    assert zeta.raw == pytest.approx(1.5)                                      # unchanged
    kind = rn.sdo[0x2001][3]
    assert _abort(lambda: setattr(kind, "raw", 7)) == 0x06090031              # above HighLimit 6
    assert _abort(lambda: setattr(kind, "raw", 0)) == 0x06090032              # below LowLimit 1
    assert _abort(lambda: rn.sdo.download(0x2000, 0, b"\x01")) == 0x06010002  # read-only
    assert _abort(lambda: rn.sdo.download(0x1000, 0, b"\0\0\0\0")) == 0x06010002
    assert _abort(lambda: rn.sdo.download(0x1018, 1, b"\0\0\0\0")) == 0x06010002
    assert _abort(lambda: rn.sdo.upload(0x2FFF, 0)) == 0x06020000             # no such object
    assert _abort(lambda: rn.sdo.download(0x2FFF, 0, b"\0")) == 0x06020000
    assert _abort(lambda: rn.sdo.download(0x2001, 1, b"\0\0")) == 0x06070010  # REAL32 needs 4 bytes
    assert _abort(lambda: rn.sdo.download(0x1017, 0, b"\x10")) == 0x06070010
    assert _abort(lambda: rn.sdo.download(0x1800, 2, bytes([245]))) == 0x06090030  # reserved type
    assert _abort(lambda: rn.sdo.download(0x1003, 0, b"\x02")) == 0x06090030  # only 0 clears
    # PDO mapping: only while the PDO is not valid, sub 0 first, mappable objects only
    tpdo_map = rn.sdo[0x1A00]
    assert _abort(lambda: setattr(tpdo_map[0], "raw", 0)) == 0x06010000       # PDO still valid
    rn.sdo[0x1800][1].raw = 0x80000181
    tpdo_map[0].raw = 0
    assert _abort(lambda: setattr(tpdo_map[1], "raw", 0x20010120)) == 0x06040041  # ζ not mappable
    assert _abort(lambda: setattr(tpdo_map[1], "raw", 0x30000008)) == 0x06040041  # no such object
    assert _abort(lambda: setattr(tpdo_map[1], "raw", 0x20000010)) == 0x06040041  # wrong length
    tpdo_map[1].raw = 0x20000008
    tpdo_map[0].raw = 1
    rn.sdo[0x1800][1].raw = 0x181


def test_sdo_transfer_protocols_seen_by_a_canopen_master(setup_factory):
    s = setup_factory()
    rn = s.remote[1]
    # expedited upload of a REAL32: scs 2, e = 1, s = 1, n = 0 -> command byte 0x43
    t0 = time.time()
    assert struct.unpack("<f", rn.sdo.upload(0x2001, 1))[0] == 1.5
    response = s.monitor.wait_count(0x581, 1, since=t0)[0]
    assert bytes(response.data) == bytes([0x43, 0x01, 0x20, 0x01]) + struct.pack("<f", 1.5)
    # identity object (CiA 301 0x1018), expedited UNSIGNED32s
    assert [rn.sdo[0x1018][sub].raw for sub in range(4)] == [4, 0, 0x7A01, 0x00010000]
    assert rn.sdo[0x1018][4].raw & 0xFFFF == 0x0001     # serial: channel 0, node-ID 1 (+ scene hash)
    # segmented upload of the 15-byte device name 0x1008: initiate (0x41, size 15), then
    # segments of 7, 7 and 1 bytes: 0x00 (toggle 0), 0x10 (toggle 1), 0x0D (toggle 0, 6 unused, last)
    t0 = time.time()
    assert rn.sdo[0x1008].raw == "taxel node twin"
    s.monitor.barrier()
    frames = [bytes(f.data) for f in s.monitor.of(0x581, t0)]
    assert frames[0] == bytes([0x41, 0x08, 0x10, 0x00, 15, 0, 0, 0])
    assert [f[0] for f in frames[1:]] == [0x00, 0x10, 0x0D]
    assert b"".join([frames[1][1:], frames[2][1:], frames[3][1:2]]) == b"taxel node twin"
    # segmented download of a REAL32 goes through the same range checks as an expedited one
    rn.sdo.download(0x2001, 1, struct.pack("<f", 2.25), force_segment=True)
    assert rn.sdo[0x2001][1].raw == 2.25
    assert _abort(lambda: rn.sdo.download(0x2001, 1, struct.pack("<f", -1.0), force_segment=True)) == 0x06090032
    # sub-index that does not exist, of a VAR and of a RECORD
    assert _abort(lambda: rn.sdo.upload(0x1017, 1)) == 0x06090011
    assert _abort(lambda: rn.sdo.upload(0x2001, 9)) == 0x06090011
    assert _abort(lambda: rn.sdo.download(0x1008, 0, b"x")) == 0x06010002      # const
    # no block transfer (and no protocol switch allowed by canopen's client): refused
    assert _abort(lambda: rn.sdo[0x2001][1].open("rb", block_transfer=True).read()) == 0x05040001
    assert _abort(lambda: rn.sdo[0x2001][1].open("wb", block_transfer=True).write(b"\0" * 4)) == 0x05040001


def test_canopen_nmt_master_and_heartbeat_consumer(setup_factory):
    s = setup_factory()
    rn = s.remote[3]
    assert wait_until(lambda: rn.nmt.wait_for_heartbeat(WAIT) == "PRE-OPERATIONAL")
    rn.nmt.state = "OPERATIONAL"
    assert wait_until(lambda: rn.nmt.wait_for_heartbeat(WAIT) == "OPERATIONAL")
    s.network.nmt.state = "STOPPED"                       # broadcast
    assert wait_until(lambda: s.remote[1].nmt.wait_for_heartbeat(WAIT) == "STOPPED")
    assert wait_until(lambda: rn.nmt.wait_for_heartbeat(WAIT) == "STOPPED")
    t0 = time.time()
    rn.nmt.state = "RESET"
    assert wait_until(lambda: b"\x00" in [bytes(f.data) for f in s.monitor.of(0x703, t0)])
    assert wait_until(lambda: rn.nmt.wait_for_heartbeat(WAIT) == "PRE-OPERATIONAL")
    assert s.remote[1].nmt.wait_for_heartbeat(WAIT) == "STOPPED"   # addressed: node 1 untouched


def test_master_remaps_tpdo1_with_canopen_pdo_api(setup_factory):
    s = setup_factory(_readings_by_cycle)
    rn = s.remote[1]
    rn.tpdo.read()
    assert rn.tpdo[1].cob_id == 0x181 and rn.tpdo[1].enabled and rn.tpdo[1].trans_type == 1
    assert [(v.index, v.subindex) for v in rn.tpdo[1].map] == [(0x2000, 0)]
    assert not rn.tpdo[2].enabled
    rn.tpdo[1].clear()
    rn.tpdo[1].add_variable(0x2000)
    rn.tpdo[1].add_variable(0x6130, 1)
    rn.tpdo[1].add_variable(0x6150, 1)
    rn.tpdo[1].trans_type = 1
    rn.tpdo[1].enabled = True
    rn.tpdo[1].save()
    s.nmt(0x01, 1)
    assert wait_until(lambda: s.rig.node(1).state == 0x05)
    s.sync(2, gap=0.005)
    frames = s.monitor.wait_count(0x181, 2)
    u, x, status = struct.unpack("<bfB", bytes(frames[0].data))
    assert (u, x, status) == (1, pytest.approx(2.0), 0)
    # the master's canopen PDO decoder reads the same values
    before = rn.tpdo[1].timestamp
    s.sync(1)
    assert wait_until(lambda: rn.tpdo[1].timestamp != before)
    decoded = [v.raw for v in rn.tpdo[1].map]    # cycle 2: X = 2.0
    assert decoded[0] == 1 and decoded[1] == pytest.approx(2.0) and decoded[2] == 0


# ------------------------------------------------------------------------ EMCY, 0x1001, 0x1003

def test_emcy_open_circuit_and_clear(setup_factory):
    def source(cycle):
        x1 = math.nan if 2 <= cycle < 4 else 3.0          # node 1: open circuit (NaN) in cycles 2, 3
        x2 = 5000.0 if cycle >= 5 else 3.0               # node 2: beyond full scale (1000 mV) from 5
        return np.array([x1, x2, 3.0])

    s = setup_factory(source)
    s.nmt(0x01)
    assert wait_until(lambda: s.rig.node(1).state == 0x05)
    s.sync(2, gap=0.003)
    s.monitor.barrier()
    assert s.monitor.of(0x081) == []
    s.sync(1)
    frame = s.monitor.wait_count(0x081, 1)[0]
    code, register, fault_id, reading = em.parse_emcy(bytes(frame.data))
    assert (code, register, fault_id) == (0x5000, 0x21, em.FAULT_OPEN_CIRCUIT) and math.isnan(reading)
    assert len(frame.data) == 8
    rn = s.remote[1]
    assert rn.sdo[0x1001].raw == 0x21
    assert rn.sdo[0x1003][0].raw == 1 and rn.sdo[0x1003][1].raw & 0xFFFF == 0x5000
    assert rn.sdo[0x2000].raw == -1                    # faulted: absent ...
    assert rn.sdo[0x6150][1].raw & 0x01 == 0x01        # ... and flagged (PV not valid)
    s.sync(1)                                          # cycle 3: still faulted, no new EMCY
    s.sync(1)                                          # cycle 4: fine again
    s.monitor.barrier()
    frames = s.monitor.of(0x081)
    assert len(frames) == 2
    assert em.parse_emcy(bytes(frames[1].data))[:2] == (0x0000, 0x00)
    assert rn.sdo[0x1001].raw == 0 and rn.sdo[0x2000].raw == 1 and rn.sdo[0x6150][1].raw == 0
    assert rn.sdo[0x1003][0].raw == 1                  # history survives the reset EMCY
    s.sync(1)                                          # cycle 5: node 2 over range
    f2 = s.monitor.wait_count(0x082, 1)[0]
    code, register, fault_id, reading = em.parse_emcy(bytes(f2.data))
    assert (code, fault_id, reading) == (0x5000, em.FAULT_OPEN_CIRCUIT, 5000.0)
    assert s.remote[2].sdo[0x6150][1].raw == 0x03      # not valid + positive overload
    # the master's canopen EMCY consumer sees the active error
    assert wait_until(lambda: [e.code for e in s.remote[2].emcy.active] == [0x5000])
    assert [e.code for e in s.remote[1].emcy.log] == [0x5000, 0x0000] and s.remote[1].emcy.active == []
    # 0x1003: writing 0 clears the history
    rn.sdo[0x1003][0].raw = 0
    assert rn.sdo[0x1003][0].raw == 0 and rn.sdo[0x1003][1].raw == 0


def test_emcy_stuck_reading_and_history_newest_first(setup_factory):
    def source(cycle):
        x1 = 2.0 + 0.01 * cycle if cycle < 3 or cycle >= 8 else 2.5   # constant in cycles 3..7
        x1 = math.nan if cycle == 10 else x1
        return np.array([x1, 0.1 * cycle, 0.2 * cycle])

    s = setup_factory(source)
    rn = s.remote[1]
    rn.sdo[0x2002][2].raw = 4              # M = 4 identical samples
    s.nmt(0x01)
    assert wait_until(lambda: s.rig.node(1).state == 0x05)
    s.sync(6)                               # cycles 0..5: 2.5 seen in 3, 4, 5
    s.monitor.barrier()
    assert s.monitor.of(0x081) == []
    s.sync(1)                               # cycle 6: 4th identical sample
    f = s.monitor.wait_count(0x081, 1)[0]
    assert em.parse_emcy(bytes(f.data))[:3] == (0x7300, 0x21, em.FAULT_STUCK)
    assert rn.sdo[0x2000].raw == -1
    s.sync(2)                               # cycles 7, 8: changes at 8 -> clear
    frames = s.monitor.wait_count(0x081, 2)
    assert em.parse_emcy(bytes(frames[1].data))[:2] == (0, 0)
    s.sync(2)                               # cycle 10: open circuit
    s.monitor.wait_count(0x081, 3)
    assert rn.sdo[0x1003][0].raw == 2
    assert rn.sdo[0x1003][1].raw & 0xFFFF == 0x5000   # newest first
    assert rn.sdo[0x1003][2].raw & 0xFFFF == 0x7300
    s.monitor.barrier()
    assert s.monitor.of(0x082) == [] and s.monitor.of(0x083) == []


def test_emcy_not_sent_when_stopped_but_error_register_set(setup_factory):
    s = setup_factory(lambda c: np.array([math.nan, 0.0, 0.0]))
    s.nmt(0x02)
    assert wait_until(lambda: s.rig.node(1).state == 0x04)
    s.sync(2)
    s.monitor.barrier()
    assert s.monitor.of(0x081) == []
    assert s.rig.node(1).read(0x1001) == 0x21


# ------------------------------------------------------------------------ silent node

def test_drop_and_restore_node(setup_factory):
    s = setup_factory(_readings_by_cycle)
    s.nmt(0x01)
    assert wait_until(lambda: s.rig.node(2).state == 0x05)
    s.rig.drop_node(2)
    t0 = time.time()
    s.sync(3, gap=0.01)
    s.monitor.wait_count(0x701, 3, since=t0)  # others keep beating
    s.monitor.barrier()
    assert s.monitor.of(0x702, t0) == [] and s.monitor.of(0x182, t0) == []
    assert len(s.monitor.of(0x181, t0)) == 3
    s.rig.restore_node(2)
    assert heartbeat_state(s, 2) == 0x05     # resumes in its NMT state, no boot-up
    s.sync(1)
    s.monitor.wait_count(0x182, 1)


def test_scene_silent_fault_window(channel):
    scene = make_scene(channel, 2)
    scene = Scene(path=scene.path, name=scene.name, taxels=scene.taxels, bus=scene.bus,
                  faults=(FaultSpec(node_id=1, fault="silent", from_cycle=2, until_cycle=4),))
    s = Setup(channel, scene, lambda c: np.array([3.0, 3.0]))
    try:
        s.nmt(0x01)
        assert wait_until(lambda: s.rig.node(1).state == 0x05)
        s.sync(6, gap=0.004)
        s.monitor.barrier()
        frames = s.monitor.of(0x181)
        assert len(frames) == 4 and len(s.monitor.of(0x182)) == 6   # cycles 2, 3 missing
        syncs = [m.timestamp for m in s.monitor.of(0x080)]
        assert frames[1].timestamp < syncs[2] and frames[2].timestamp > syncs[4]
    finally:
        s.close()


def test_a_reading_beyond_real32_is_an_infinite_sample_and_an_open_circuit(setup_factory):
    """A finite reading no REAL32 holds (an injected source, a model gone wild) is sampled as the
    IEEE conversion rounds it - ±inf: open circuit, overload flagged, its EMCY's REAL32 field
    ±3.4e38 as for an infinite reading - and never stops the node's SYNC handling."""
    def source(cycle):
        big = 1e40 if cycle >= 2 else 3.0
        return np.array([big, -big, 3.0])

    s = setup_factory(source)
    s.nmt(0x01)
    assert wait_until(lambda: s.rig.node(1).state == 0x05)
    s.sync(3, gap=0.003)
    for node, sign, overload in ((1, 1, 0x02), (2, -1, 0x04)):
        frame = s.monitor.wait_count(0x080 + node, 1)[0]
        code, register, fault_id, reading = em.parse_emcy(bytes(frame.data))
        assert (code, fault_id) == (0x5000, em.FAULT_OPEN_CIRCUIT)
        assert reading == pytest.approx(sign * 3.4e38, rel=1e-6)
        rn = s.remote[node]
        assert rn.sdo[0x6150][1].raw == 0x01 | overload   # not valid + its overload
        assert rn.sdo[0x6130][1].raw == sign * math.inf   # the sample: REAL32 ±inf
        assert rn.sdo[0x2000].raw == -1
    s.sync(1)                                             # the nodes keep answering SYNCs
    assert s.monitor.wait_count(0x183, 4)
