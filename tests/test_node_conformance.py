"""CiA 301 objects of the node twins as canopen's master sees them: 0x1019 (SYNC counter
overflow), EMCY pairing across NMT states.

canopen's ``Network`` + ``RemoteNode`` (same EDS) is the master on a python-can virtual bus; the
SYNCs are sent by the master with the counter byte it chooses. Waits are "eventually" bounds.
"""

from __future__ import annotations

import dataclasses
import math
import time
import uuid

import canopen
import numpy as np
import pytest

from node_sim import emcy as em
from node_sim.od import EDS_PATH
from node_sim.rig import Rig
from taxel_net.scene import BusSpec, Scene, TaxelSpec

WAIT = 5.0


def make_scene(channel: str, n: int = 2, **bus) -> Scene:
    taxels = tuple(TaxelSpec(node_id=i + 1, kind="R", zeta_mv=1.0, noise_mv=0.0, noise_sigma_mv=0.0,
                             x=10.0 * i, y=0.0) for i in range(n))
    bus.setdefault("heartbeat_producer_ms", 0)
    return Scene(path="<test>", name="test", taxels=taxels, bus=BusSpec(channels=(channel,), **bus))


def wait_until(pred, timeout=WAIT) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.005)
    return False


class Setup:
    def __init__(self, scene: Scene, source):
        self.rig = Rig(scene, reading_source=source).start()
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=scene.bus.channels[0])
        self.remote = {}
        for t in scene.taxels:
            rn = canopen.RemoteNode(t.node_id, str(EDS_PATH))
            rn.sdo.RESPONSE_TIMEOUT = 2.0
            self.network.add_node(rn)
            self.remote[t.node_id] = rn

    def sync(self, data: bytes, expect_cycle: int) -> None:
        self.network.send_message(0x80, data)
        assert self.rig.wait_cycle(expect_cycle, timeout=WAIT)

    def nmt(self, command: int, node_id: int = 0) -> None:
        self.network.send_message(0x000, bytes([command, node_id]))

    def close(self) -> None:
        self.network.disconnect()
        self.rig.stop()


@pytest.fixture
def factory():
    made = []

    def make(source=None, n=2, **bus):
        scene = make_scene(f"test-conf-{uuid.uuid4().hex[:10]}", n, **bus)
        s = Setup(scene, source or (lambda cycle: np.zeros(n)))
        made.append(s)
        return s

    yield make
    for s in made:
        s.close()


def _abort(fn) -> int:
    with pytest.raises(canopen.SdoAbortedError) as info:
        fn()
    return info.value.code


# ------------------------------------------------------------------------ 0x1019

def test_sync_counter_overflow_object(factory):
    s = factory(sync_counter=7)
    rn = s.remote[1]
    assert rn.sdo[0x1019].raw == 7                       # start-up value from the scene
    assert _abort(lambda: setattr(rn.sdo[0x1019], "raw", 1)) == 0x06090030
    assert _abort(lambda: setattr(rn.sdo[0x1019], "raw", 241)) == 0x06090031   # EDS HighLimit 240
    rn.sdo[0x1019].raw = 0
    rn.sdo[0x1019].raw = 240
    assert rn.sdo[0x1019].raw == 240
    s.nmt(0x82, 1)                                        # reset communication: start-up value back
    assert wait_until(lambda: s.rig.node(1).read(0x1019) == 7)


def test_master_overflow_written_over_sdo_is_honoured(factory):
    """Scene without counter (0x1019 = 0); the master configures overflow 10 on every node and
    sends SYNCs counting 1..10: a wrap is one cycle, a gap counts as lost SYNCs (no 240)."""
    s = factory()
    for rn in s.remote.values():
        assert rn.sdo[0x1019].raw == 0
        rn.sdo[0x1019].raw = 10
    cycle = 0
    for counter in list(range(1, 11)) + [1, 2]:
        s.sync(bytes([counter]), cycle)
        cycle += 1
    assert s.rig.cycle() == 11 and s.rig.lost_syncs() == 0
    s.sync(bytes([5]), 14)                                # 2 -> 5: two SYNCs lost
    assert s.rig.lost_syncs() == 2
    s.sync(bytes([1]), 20)                                # 5 -> (wrap at 10) -> 1: five lost
    assert s.rig.lost_syncs() == 7
    # back to 0: a SYNC with a counter byte is now a length error (ignored), one without counts
    for rn in s.remote.values():
        rn.sdo[0x1019].raw = 0
    s.network.send_message(0x80, b"\x02")
    s.sync(b"", 21)
    assert s.rig.lost_syncs() == 7


# ------------------------------------------------------------------------ EDS defaults

def _writable(od):
    for obj in od.values():
        for var in ([obj] if isinstance(obj, canopen.objectdictionary.ODVariable)
                    else [obj[s] for s in obj.subindices]):
            if var.writable and var.default is not None:
                yield var


def _sdo_var(rn, var):
    obj = rn.sdo[var.index]
    return obj if isinstance(rn.object_dictionary[var.index], canopen.objectdictionary.ODVariable) else obj[var.subindex]


def test_every_writable_default_of_the_eds_is_accepted(factory):
    """A tool that downloads the EDS defaults (CiA 306 DefaultValue) gets no abort: in index
    order, and for the TPDOs with the CiA 301 procedure (PDO invalid while its parameters
    and mapping change, then the default COB-ID)."""
    s = factory(n=1)
    rn = s.remote[1]
    tpdo = (0x1800, 0x1801, 0x1A00, 0x1A01)
    written = 0
    for var in _writable(rn.object_dictionary):
        if var.index in tpdo:
            continue
        _sdo_var(rn, var).raw = var.default
        written += 1
    assert written >= 10
    assert rn.sdo[0x2001][3].raw == 1 and rn.sdo[0x1019].raw == 0
    for comm, mapping in ((0x1800, 0x1A00), (0x1801, 0x1A01)):
        cob = rn.object_dictionary[comm][1].default
        rn.sdo[comm][1].raw = cob | 0x80000000
        for var in _writable(rn.object_dictionary):
            if var.index == comm and var.subindex != 1:
                _sdo_var(rn, var).raw = var.default
        rn.sdo[mapping][0].raw = 0
        for var in _writable(rn.object_dictionary):
            if var.index == mapping and var.subindex != 0:
                _sdo_var(rn, var).raw = var.default
        rn.sdo[mapping][0].raw = rn.object_dictionary[mapping][0].default
        rn.sdo[comm][1].raw = cob
        assert rn.sdo[comm][1].raw == cob
    assert rn.sdo[0x1800][1].raw == 0x40000181               # valid, no RTR (bit 30)
    assert rn.sdo[0x1801][1].raw == 0xC0000281               # not valid, no RTR


def test_limits_the_eds_cannot_carry_are_checked_by_the_node(factory):
    s = factory(n=1)
    rn = s.remote[1]
    assert _abort(lambda: setattr(rn.sdo[0x2002][1], "raw", 0.0)) == 0x06090032    # full scale > 0
    assert _abort(lambda: setattr(rn.sdo[0x2002][1], "raw", -5.0)) == 0x06090032
    assert _abort(lambda: setattr(rn.sdo[0x2001][1], "raw", -0.01)) == 0x06090032   # ζ >= 0
    rn.sdo[0x2002][1].raw = 0.5
    assert rn.sdo[0x2002][1].raw == 0.5


# ------------------------------------------------------------------------ EMCY pairing

def _emcy_codes(rn) -> list[int]:
    return [e.code for e in rn.emcy.log]


def test_emcy_of_a_fault_that_began_while_stopped_is_sent_on_resuming(factory):
    """Node 1 open circuit from cycle 1 on, while STOPPED: no EMCY then (CiA 301), the EMCY
    when it is started, the error reset when it clears. Node 2 faults and recovers while
    stopped: neither EMCY nor error reset (every error reset follows a reported error)."""
    def source(cycle):
        x1 = math.nan if 1 <= cycle < 4 else 0.0
        x2 = math.nan if cycle == 1 else 0.0
        return np.array([x1, x2])

    s = factory(source)
    rn1, rn2 = s.remote[1], s.remote[2]
    s.nmt(0x02)                                             # stop both
    assert wait_until(lambda: s.rig.node(1).state == 0x04 and s.rig.node(2).state == 0x04)
    s.sync(b"", 0)
    s.sync(b"", 1)                                          # both faulted, stopped
    s.sync(b"", 2)                                          # node 2 fine again
    assert s.rig.node(1).read(0x1001) == 0x21 and s.rig.node(2).read(0x1001) == 0
    s.nmt(0x80)                                             # pre-operational: may report
    assert wait_until(lambda: _emcy_codes(rn1) == [0x5000])
    assert [e.code for e in rn1.emcy.active] == [0x5000]
    s.sync(b"", 3)
    s.sync(b"", 4)                                          # node 1 fine again: error reset
    assert wait_until(lambda: _emcy_codes(rn1) == [0x5000, 0x0000])
    assert rn1.emcy.active == []
    assert rn2.sdo[0x1001].raw == 0                         # round trip after node 2's frames
    assert _emcy_codes(rn2) == []


def test_error_reset_of_a_fault_cleared_while_stopped(factory):
    def source(cycle):
        return np.array([math.nan if cycle == 1 else 0.0, 0.0])

    s = factory(source)
    rn1 = s.remote[1]
    s.sync(b"", 0)
    s.sync(b"", 1)                                          # pre-operational: EMCY sent
    assert wait_until(lambda: _emcy_codes(rn1) == [0x5000])
    s.nmt(0x02, 1)
    assert wait_until(lambda: s.rig.node(1).state == 0x04)
    s.sync(b"", 2)                                          # cleared while stopped: no frame
    assert s.rig.node(1).read(0x1001) == 0
    s.nmt(0x01, 1)                                          # started: the error reset owed
    assert wait_until(lambda: _emcy_codes(rn1) == [0x5000, 0x0000])
    assert rn1.emcy.active == []


# ------------------------------------------------------------------------ heartbeat consumer

MASTER_ID = 0x70   # the master's heartbeat: 0x770


def _consume_master(rn, time_ms: int = 100) -> None:
    rn.sdo[0x1016][1].raw = MASTER_ID << 16 | time_ms


def _emcy_trail(rn) -> str:
    """What the master heard of the node (for a failing wait's message)."""
    return "EMCYs heard: " + ", ".join(f"0x{e.code:04X}@{e.timestamp:.3f}" for e in rn.emcy.log)


def test_heartbeat_consumer_objects(factory):
    s = factory(n=1)
    rn = s.remote[1]
    assert rn.sdo[0x1016][0].raw == 2 and rn.sdo[0x1016][1].raw == 0 and rn.sdo[0x1029][1].raw == 0
    _consume_master(rn)
    assert rn.sdo[0x1016][1].raw == 0x00700064
    assert _abort(lambda: setattr(rn.sdo[0x1016][2], "raw", MASTER_ID << 16 | 50)) == 0x06040043  # same node twice
    rn.sdo[0x1016][2].raw = MASTER_ID << 16                 # time 0: entry off, accepted
    assert _abort(lambda: setattr(rn.sdo[0x1016][2], "raw", 0x01000000 | 5 << 16 | 50)) == 0x06090030
    assert _abort(lambda: setattr(rn.sdo[0x1029][1], "raw", 3)) == 0x06090031
    rn.sdo[0x1029][1].raw = 2
    s.nmt(0x82, 1)                                           # reset communication: defaults back
    assert wait_until(lambda: s.rig.node(1).read(0x1016, 1) == 0 and s.rig.node(1).read(0x1029, 1) == 0)


@pytest.mark.parametrize("behaviour, state_after", [(0, 0x7F), (1, 0x05), (2, 0x04)])
def test_master_heartbeat_loss_emcy_and_error_behaviour(factory, behaviour, state_after):
    """The master beats every 20 ms, the node consumes it with 300 ms. Monitoring starts at the
    first heartbeat after 0x1016 is configured (CiA 301): the beat is stopped only once the node
    times it - a CI run on a loaded host stopped it before any beat had reached the node (the
    write's reset of the consumer still pending), so no loss was ever detected (no EMCY heard)."""
    s = factory(n=2)
    rn1, rn2 = s.remote[1], s.remote[2]
    _consume_master(rn1, time_ms=300)                        # node 2 consumes nothing
    rn1.sdo[0x1029][1].raw = behaviour
    beat = s.network.send_periodic(0x700 + MASTER_ID, [0x05], 0.02)
    try:
        s.nmt(0x01)
        assert wait_until(lambda: s.rig.node(1).state == 0x05 and s.rig.node(2).state == 0x05), _emcy_trail(rn1)
        assert wait_until(lambda: MASTER_ID in s.rig.node(1).heartbeat_consumer.monitored)
    finally:
        beat.stop()
    # the master's heartbeat is gone: EMCY 0x8130, error register bits 0 + 4, state per 0x1029
    assert wait_until(lambda: [e.code for e in rn1.emcy.active] == [0x8130]), _emcy_trail(rn1)
    assert rn1.emcy.active[0].register == 0x11
    assert wait_until(lambda: s.rig.node(1).state == state_after), _emcy_trail(rn1)
    assert s.rig.node(1).read(0x1001) == 0x11, _emcy_trail(rn1)
    assert s.rig.node(1).read(0x1003, 1) == 0x8130
    assert s.rig.node(2).state == 0x05 and rn2.emcy.log == []
    # it is back: error reset EMCY, the register clears
    beat = s.network.send_periodic(0x700 + MASTER_ID, [0x05], 0.02)
    try:
        if state_after == 0x04:
            s.nmt(0x80, 1)                                   # stopped: no EMCY until it may report
        assert wait_until(lambda: [e.code for e in rn1.emcy.log] == [0x8130, 0x0000]), _emcy_trail(rn1)
        assert rn1.emcy.active == [] and s.rig.node(1).read(0x1001) == 0
    finally:
        beat.stop()


# ------------------------------------------------------------------------ identity 0x1018

def test_identity_distinct_per_node_and_stable_per_scene(factory):
    """0x1018: vendor-ID 0 (no CiA vendor-ID is assigned to this project: the EDS says so),
    product code 0x7A01 and revision 1.0 of the twin, serial distinct per node and the same in
    every run of the scene (what an identity check or LSS needs)."""
    from node_sim.rig import identity_serial

    s = factory(n=3)
    ids = {nid: tuple(rn.sdo[0x1018][sub].raw for sub in range(1, 5)) for nid, rn in s.remote.items()}
    assert {i[:3] for i in ids.values()} == {(0, 0x7A01, 0x00010000)}
    serials = [i[3] for i in ids.values()]
    assert len(set(serials)) == 3 and all(serials)
    scene = s.rig.scene
    assert serials == [identity_serial(scene, t) for t in scene.taxels]
    # a second rig of the same scene (another run) reports the same serials
    again = Rig(scene).start()
    try:
        assert [again.node(t.node_id).read(0x1018, 4) for t in scene.taxels] == serials
    finally:
        again.stop()
    # another scene (name) gives other serials
    other = dataclasses.replace(scene, name="another scene")
    assert {identity_serial(other, t) for t in other.taxels}.isdisjoint(serials)
