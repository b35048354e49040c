"""The node twins' SYNC hot path gives the same protocol behaviour as the slow path it replaced.

* ``local_decision_pm1`` (scalar eqs 1-4) equals ``fusion_center.core.encoding.local_decision`` on
  random and boundary inputs (NaN, ±inf, X - N == ζ exactly, one ulp either side);
* the values a SYNC writes into the OD are the CiA 301 encodings (INTEGER8, REAL32,
  UNSIGNED8 - packed here with ``struct``, independently of canopen and of the node), and a
  canopen master reads them back over SDO and in the TPDOs;
* the cached detector parameters follow SDO writes and NMT resets;
* a SYNC burst keeps the frame order and starts the inhibit time when the frames really left;
* the rig's cheap deep copy is python-can's ``Message.__deepcopy__`` field for field;
* physics readings computed ahead are the canonical ones; an injected source is never read ahead.

No wall-clock limits: waits are event-based (FIFO barriers, cycle counters, timer barriers).
"""

from __future__ import annotations

import copy
import math
import struct
import threading
import time
import uuid

import can
import canopen
import numpy as np
import pytest

from fusion_center.core.encoding import local_decision
from taxel_net.scene import BusSpec, Scene, TaxelSpec
from node_sim import physics
from node_sim.detector import local_decision_pm1
from node_sim.link import NodeLink, Scheduler
from node_sim.pdo import _TpdoRuntime
from node_sim.od import EDS_PATH
from taxel_net.canmsg import TxMessage
from node_sim.rig import Rig

WAIT = 5.0


# --------------------------------------------------------------------------- scalar detector

def test_scalar_detector_hand_examples():
    # eqs 2-4: u = +1 iff X - N >= ζ
    assert local_decision_pm1(2.0, 0.5, 1.5) == 1      # Y = 1.5 = ζ: present (>=)
    assert local_decision_pm1(1.99, 0.5, 1.5) == -1    # Y = 1.49 < ζ
    assert local_decision_pm1(0.0, -1.0, 1.0) == 1     # negative noise estimate
    assert local_decision_pm1(0.0, 0.0, 0.0) == 1      # ζ = 0, Y = 0
    assert local_decision_pm1(math.nan, 0.0, 0.0) == -1  # NaN is never present


def test_scalar_detector_equals_local_decision():
    rng = np.random.default_rng(20240611)
    m = 20_000
    x = rng.normal(0.0, 5.0, m)
    n = rng.normal(0.5, 2.0, m)
    z = np.abs(rng.normal(2.0, 2.0, m))
    # boundaries: Y == ζ exactly where representable, and one ulp either side of X
    k = m // 4
    x[:k] = n[:k] + z[:k]
    x[k:2 * k] = np.nextafter(n[k:2 * k] + z[k:2 * k], np.inf)
    x[2 * k:3 * k] = np.nextafter(n[2 * k:3 * k] + z[2 * k:3 * k], -np.inf)
    special = np.array([math.nan, math.inf, -math.inf, 0.0, -0.0, 5e-324, -5e-324, 1e308, -1e308])
    xs = np.concatenate([x, np.repeat(special, 3)])
    ns = np.concatenate([n, np.tile([0.0, 1e308, -2.5], special.size)])
    zs = np.concatenate([z, np.tile([0.0, 3.0, 1e308], special.size)])
    with np.errstate(over="ignore", invalid="ignore"):  # ±1e308 - ∓1e308 overflows to ±inf
        reference = local_decision(xs, ns, zs, "pm1")
    scalar = np.array([local_decision_pm1(float(a), float(b), float(c)) for a, b, c in zip(xs, ns, zs)])
    assert np.array_equal(scalar, reference)
    # the first block really sits on the boundary Y == ζ (present there, eq 3's ">=")
    on_boundary = (x[:k] - n[:k]) == z[:k]
    assert on_boundary.sum() > k // 2 and np.all(scalar[:k][on_boundary] == 1)


# --------------------------------------------------------------------------- rig harness

def make_scene(channel: str, n: int = 3, sigma: float = 0.0, **bus) -> Scene:
    taxels = tuple(TaxelSpec(node_id=i + 1, kind=("R", "C", "P")[i % 3], zeta_mv=1.5, noise_mv=0.5,
                             noise_sigma_mv=sigma, signal_mv=4.0, x=10.0 * i, y=-2.5)
                   for i in range(n))
    bus.setdefault("heartbeat_producer_ms", 0)
    return Scene(path="<test>", name="fastpath", taxels=taxels, bus=BusSpec(channels=(channel,), **bus))


class Harness:
    """Rig + canopen master + a FIFO monitor bus on one virtual channel."""

    def __init__(self, scene: Scene, source=None):
        channel = scene.bus.channels[0]
        self.monitor = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        self.frames: list[can.Message] = []
        self._lock = threading.Lock()
        self._notifier = can.Notifier(self.monitor, [self._on], timeout=0.05)
        self.rig = Rig(scene, reading_source=source).start()
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=channel)
        self.remote = {}
        for t in scene.taxels:
            rn = canopen.RemoteNode(t.node_id, str(EDS_PATH))
            rn.sdo.RESPONSE_TIMEOUT = 2.0
            self.network.add_node(rn)
            self.remote[t.node_id] = rn
        self._marker = 0

    def _on(self, msg):
        with self._lock:
            self.frames.append(msg)

    def of(self, can_id: int) -> list[bytes]:
        with self._lock:
            return [bytes(m.data) for m in self.frames if m.arbitration_id == can_id and not m.is_extended_id]

    def barrier(self) -> None:
        """Every frame sent before the call has been recorded (virtual queues are FIFO)."""
        self._marker += 1
        tag = struct.pack("<Q", self._marker)
        self.monitor.send(can.Message(arbitration_id=0x1ABCDEF, data=tag, is_extended_id=True))
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline:
            with self._lock:
                if any(m.is_extended_id and bytes(m.data) == tag for m in self.frames):
                    return
            time.sleep(0.002)
        raise AssertionError("barrier frame never came back")

    def sync(self) -> int:
        before = self.rig.cycle()
        self.network.send_message(0x80, b"")
        target = 0 if before is None else before + 1
        assert self.rig.wait_cycle(target, timeout=WAIT)
        return target

    def start(self) -> None:
        self.network.send_message(0x000, b"\x01\x00")
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline and not all(n.state == 0x05 for n in self.rig.nodes.values()):
            time.sleep(0.002)
        assert all(n.state == 0x05 for n in self.rig.nodes.values())

    def timers_done(self, delay: float = 0.0) -> None:
        """Every timer of the channel due up to ``delay`` seconds from now has run."""
        ran = threading.Event()
        self.rig.node(1).link.scheduler.call_at(time.monotonic() + delay, ran.set)
        assert ran.wait(WAIT + delay)

    def close(self) -> None:
        self.network.disconnect()
        self.rig.stop()
        self._notifier.stop()
        self.monitor.shutdown()


@pytest.fixture
def harness():
    made = []

    def make(scene_kwargs=None, source=None):
        scene = make_scene(f"test-fastpath-{uuid.uuid4().hex[:10]}", **(scene_kwargs or {}))
        h = Harness(scene, source)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


def int8(u: int) -> bytes:
    return struct.pack("<b", u)


def real32(x: float) -> bytes:
    return struct.pack("<f", x)


# --------------------------------------------------------------------------- OD values and TPDOs

# per cycle, per node (N = 0.5, ζ = 1.5, full scale = EDS default): X, expected u, status
CASES = [
    ([2.0, 1.99, 7.25], [1, -1, 1], [0, 0, 0]),
    ([-3.5, 1e-3, 2.0], [-1, -1, 1], [0, 0, 0]),
    ([math.nan, math.inf, -math.inf], [-1, -1, -1], [0x01, 0x03, 0x05]),  # open circuit: not valid, ±overload
    ([2.0, 2.0, 2.0], [1, 1, 1], [0, 0, 0]),
]


def test_sampled_values_are_cia301_encodings_and_tpdo_payload(harness):
    h = harness(source=lambda c: np.array(CASES[c % len(CASES)][0]))
    h.start()
    for c, (xs, us, statuses) in enumerate(CASES):
        assert h.sync() == c
        for nid, (x, u, status) in enumerate(zip(xs, us, statuses), start=1):
            store = h.rig.node(nid).local.data_store
            assert store[0x2000][0] == int8(u)
            assert store[0x6130][1] == real32(x)
            assert store[0x6150][1] == bytes([status])
            assert h.remote[nid].sdo[0x2000].raw == u                       # canopen master, SDO
            assert h.remote[nid].sdo[0x6150][1].raw == status
            pv = h.remote[nid].sdo[0x6130][1].raw
            assert (math.isnan(pv) and math.isnan(x)) or pv == struct.unpack("<f", real32(x))[0]
    h.barrier()
    for nid in (1, 2, 3):
        assert h.of(0x180 + nid) == [int8(us[nid - 1]) for _, us, _ in CASES]


def test_raw_mode_tpdo2_payload_is_the_real32_reading(harness):
    xs = [2.0, -1.25, 3.0e-3, 123.456]
    h = harness(scene_kwargs={"mode": "raw", "n": 1}, source=lambda c: np.array([xs[c]]))
    h.start()
    for _ in xs:
        h.sync()
    h.barrier()
    assert h.of(0x281) == [real32(x) for x in xs]
    # raw mode: the reading is sent *instead of* the decision (TPDO1 invalid at start-up);
    # the node still decides locally and keeps u_i in 0x2000 (last X = 123.456: present)
    assert h.of(0x181) == []
    assert h.remote[1].sdo[0x2000].raw == 1


# --------------------------------------------------------------------------- cached parameters

def test_detector_parameters_follow_sdo_writes_and_nmt_resets(harness):
    h = harness(source=lambda c: np.array([2.0, 2.0, 2.0]))   # Y = 1.5 = ζ: present
    rn = h.remote[1]
    h.sync()
    assert rn.sdo[0x2000].raw == 1
    rn.sdo[0x2001][1].raw = 1.75         # ζ above Y
    h.sync()
    assert rn.sdo[0x2000].raw == -1
    rn.sdo[0x2001][2].raw = 0.25         # N: Y = 1.75 = ζ
    h.sync()
    assert rn.sdo[0x2000].raw == 1
    rn.sdo[0x2002][1].raw = 2.0          # full scale: |X| >= 2.0 is an open circuit
    h.sync()
    assert rn.sdo[0x2000].raw == -1 and rn.sdo[0x6150][1].raw == 0x03
    rn.sdo[0x2002][1].raw = 100.0
    rn.sdo[0x2002][2].raw = 2            # stuck after 2 identical samples (the source is constant)
    h.sync()
    assert rn.sdo[0x6150][1].raw == 0x01 and rn.sdo[0x2000].raw == -1
    # reset communication keeps the manufacturer area (0x2001/0x2002 as written)
    h.network.send_message(0x000, b"\x82\x01")
    h.barrier()
    h.sync()
    assert rn.sdo[0x2001][1].raw == pytest.approx(1.75)
    assert rn.sdo[0x6150][1].raw == 0x00   # fault state reset: one sample seen again
    h.sync()
    assert rn.sdo[0x6150][1].raw == 0x01   # stuck count 2 still in force
    # reset node restores the start-up values: ζ 1.5, N 0.5, stuck detector off -> present
    h.network.send_message(0x000, b"\x81\x01")
    h.barrier()
    for _ in range(3):
        h.sync()
    assert rn.sdo[0x2001][1].raw == pytest.approx(1.5)
    assert rn.sdo[0x2000].raw == 1 and rn.sdo[0x6150][1].raw == 0x00


# --------------------------------------------------------------------------- bursts

def test_burst_keeps_order_and_starts_inhibit_time_when_sent():
    lock = threading.RLock()
    scheduler = Scheduler(lock, name="test-burst")
    sent: list[tuple[int, bytes, float]] = []
    link = NodeLink(lambda can_id, data: sent.append((can_id, data, time.monotonic())), scheduler)
    try:
        rt = _TpdoRuntime()
        link.mark_sent(rt)                       # outside a burst: now
        assert rt.last_tx_time <= time.monotonic() and rt.last_tx_time > -math.inf
        link.hold()
        frames = [(0x081, b"\x00" * 8), (0x181, b"\x01"), (0x182, b"\xff"), (0x281, b"\0\0\0\0")]
        rt = _TpdoRuntime()
        for can_id, data in frames:
            link.send(can_id, data)
        link.mark_sent(rt)
        assert sent == [] and rt.last_tx_time == -math.inf   # held: nothing left yet
        link.release()
        assert [(i, d) for i, d, _ in sent] == frames       # production order
        assert rt.last_tx_time >= sent[-1][2]                # inhibit time from the real send
        link.release()                                       # idempotent
        link.send(0x183, b"\x01")
        assert sent[-1][:2] == (0x183, b"\x01")              # not held any more
    finally:
        scheduler.stop()


# --------------------------------------------------------------------------- deep copy

@pytest.mark.parametrize("fields", [
    dict(arbitration_id=0x181, data=b"\x01", is_extended_id=False),
    dict(arbitration_id=0x1ABCDEF, data=bytes(range(8)), is_extended_id=True, channel="can1",
         timestamp=12.5, is_rx=False),
    dict(arbitration_id=0x700, is_remote_frame=True, dlc=1, is_extended_id=False, channel=3),
    dict(arbitration_id=0x7FF, data=bytes(64), is_fd=True, bitrate_switch=True,
         error_state_indicator=True, is_extended_id=False),
])
def test_tx_frame_deepcopy_is_pythoncan_deepcopy(fields):
    frame = TxMessage(**fields)
    mine = copy.deepcopy(frame)
    theirs = copy.deepcopy(can.Message(**fields))
    assert type(mine) is can.Message
    for slot in can.Message.__slots__:
        if slot != "__weakref__":
            assert getattr(mine, slot) == getattr(theirs, slot), slot
    assert mine.data is not frame.data
    frame.data[:] = b""                                   # the copy owns its buffer
    assert mine.data == theirs.data


# --------------------------------------------------------------------------- readings ahead

def test_physics_readings_read_ahead_are_canonical(harness):
    h = harness(scene_kwargs={"sigma": 0.7, "sync_period_ms": 2.0})
    rig = h.rig
    read_ahead = 0
    for c in range(24):
        if c and c in rig._reading_cache:
            read_ahead += 1
        assert h.sync() == c
        x = physics.sample_readings(rig.scene, c)
        for i, t in enumerate(rig.scene.taxels):
            assert rig.node(t.node_id).local.data_store[0x6130][1] == real32(x[i])
        h.timers_done(delay=0.5 * 2.0e-3)  # the read-ahead timer of this SYNC has run: it woke
        deadline = time.monotonic() + WAIT  # the read-ahead thread - wait until that one is done
        while rig._prefetch_pending and time.monotonic() < deadline:
            time.sleep(0.001)
    assert read_ahead == 23                # every cycle after the first came from the cache


def test_injected_source_is_never_read_ahead(harness):
    calls = []

    def source(cycle):
        calls.append(cycle)
        return np.zeros(3)

    h = harness(scene_kwargs={"sync_period_ms": 2.0}, source=source)
    for c in range(5):
        h.sync()
        h.timers_done(delay=2.0e-3)
        assert calls == list(range(c + 1))


# --------------------------------------------------------------------------- virtual-bus bursts

def _fields(msg: can.Message) -> dict:
    return {slot: getattr(msg, slot) for slot in can.Message.__slots__
            if slot not in ("__weakref__", "timestamp")}


@pytest.mark.parametrize("own", [False, True])
def test_virtual_burst_delivers_what_virtual_send_delivers(own):
    from node_sim.channel import virtual_burst_sender

    frames = [(0x181, b"\x01"), (0x182, b"\xff"), (0x081, bytes(range(8))), (0x281, b"\0\0\x80\x3f"), (0x700, b"")]
    received = {}
    for path in ("send", "burst"):
        channel = f"test-burst-{uuid.uuid4().hex[:10]}"
        tx = can.Bus(interface="virtual", channel=channel, receive_own_messages=own)
        rx1 = can.Bus(interface="virtual", channel=channel)
        rx2 = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        try:
            before = time.time()
            if path == "send":
                for can_id, data in frames:
                    tx.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
            else:
                send_many = virtual_burst_sender(tx)
                assert send_many is not None
                send_many(frames)
            after = time.time()
            got = {name: [bus.recv(0) for _ in range(len(frames) + 1)] for name, bus in
                   (("tx", tx), ("rx1", rx1), ("rx2", rx2))}
        finally:
            for bus in (tx, rx1, rx2):
                bus.shutdown()
        for name, msgs in got.items():
            delivered = [m for m in msgs if m is not None]
            stamps = [m.timestamp for m in delivered]
            assert all(before <= t <= after for t in stamps) and stamps == sorted(stamps)
            assert all(m.channel == channel for m in delivered)
            received[path, name] = [{k: v for k, v in _fields(m).items() if k != "channel"} for m in delivered]
    for name in ("tx", "rx1", "rx2"):
        assert received["burst", name] == received["send", name], name
    assert len(received["burst", "rx1"]) == len(frames)
    assert len(received["burst", "tx"]) == (len(frames) if own else 0)


def test_virtual_burst_only_for_plain_virtual_buses():
    from can.interfaces.virtual import VirtualBus

    from node_sim.channel import virtual_burst_sender

    class Derived(VirtualBus):
        pass

    channel = f"test-burst-{uuid.uuid4().hex[:10]}"
    derived = Derived(channel=channel)
    plain = can.Bus(interface="virtual", channel=channel)
    try:
        assert virtual_burst_sender(derived) is None    # may override send: use it
        send_many = virtual_burst_sender(plain)
    finally:
        derived.shutdown()
        plain.shutdown()
    with pytest.raises(can.CanOperationError):            # closed bus: python-can's error
        send_many([(0x181, b"\x01")])
