"""The rig: start-up configuration from the scene, one network per channel, SYNC cycle
numbering (and lost-SYNC detection with a counter), default physics readings."""

from __future__ import annotations

import struct
import threading
import time
import uuid
from pathlib import Path

import can
import canopen
import numpy as np
import pytest

from taxel_net.errors import ParameterError
from taxel_net.scene import TAXEL_KINDS, BusSpec, Scene, TaxelSpec, load_scene
from node_sim.od import EDS_PATH
from node_sim.rig import Rig

ROOT = Path(__file__).resolve().parent.parent
WAIT = 5.0
MARKER_ID = 0x1ABCDEF  # extended ID: ignored by the node twins


def uid(prefix="rig"):
    return f"test-{prefix}-{uuid.uuid4().hex[:10]}"


class Recorder:
    def __init__(self, channel):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        self.frames: list[can.Message] = []
        self.lock = threading.Lock()
        self.notifier = can.Notifier(self.bus, [self.on], timeout=0.05)

    def on(self, m):
        with self.lock:
            self.frames.append(m)

    def of(self, can_id):
        with self.lock:
            return [m for m in self.frames if m.arbitration_id == can_id]

    def wait_count(self, can_id, n, timeout=WAIT):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if len(self.of(can_id)) >= n:
                return self.of(can_id)
            time.sleep(0.005)
        raise AssertionError(f"0x{can_id:03X}: {len(self.of(can_id))} < {n}")

    def send(self, can_id, data=b""):
        self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def barrier(self):
        """Return once every frame sent before the call is recorded (virtual bus queues are FIFO)."""
        n = len(self.of(MARKER_ID))
        self.bus.send(can.Message(arbitration_id=MARKER_ID, is_extended_id=True))
        self.wait_count(MARKER_ID, n + 1)

    def close(self):
        self.notifier.stop()
        self.bus.shutdown()


def sync_and_wait(rec: Recorder, rig: Rig, channel: int = 0, data: bytes = b"", expect_cycle=None):
    before = rig.cycle(channel)
    rec.send(0x80, data)
    target = expect_cycle if expect_cycle is not None else (0 if before is None else before + 1)
    assert rig.wait_cycle(target, channel, timeout=WAIT)


def test_startup_configuration_written_from_scene():
    ch = uid()
    taxels = (TaxelSpec(node_id=3, kind="TBS", x=1.0, y=2.0, zeta_mv=0.75, noise_mv=0.25, slope=0.307,
                        intercept=-0.0163, noise_sigma_mv=0.1),
              TaxelSpec(node_id=8, kind="IR", zeta_mv=2.0))
    bus = BusSpec(channels=(ch,), heartbeat_producer_ms=250, mode="raw", transmission_type=255,
                  inhibit_time_100us=30, event_timer_ms=500)
    scene = Scene(path="<t>", name="cfg", taxels=taxels, bus=bus)
    net = canopen.Network()
    with Rig(scene, reading_source=lambda c: np.zeros(2)) as rig:
        net.connect(interface="virtual", channel=ch)
        try:
            rn = canopen.RemoteNode(3, str(EDS_PATH))
            rn.sdo.RESPONSE_TIMEOUT = 2.0
            net.add_node(rn)
            assert rn.sdo[0x2001][1].raw == pytest.approx(0.75)
            assert rn.sdo[0x2001][2].raw == pytest.approx(0.25)
            assert rn.sdo[0x2001][3].raw == TAXEL_KINDS["TBS"] == 5
            assert (rn.sdo[0x2001][4].raw, rn.sdo[0x2001][5].raw) == (1.0, 2.0)
            assert rn.sdo[0x6126][1].raw == pytest.approx(0.307, rel=1e-6)
            assert rn.sdo[0x6127][1].raw == pytest.approx(-0.0163, rel=1e-6)
            assert rn.sdo[0x1017].raw == 250
            for comm in (0x1800, 0x1801):
                assert rn.sdo[comm][2].raw == 255
                assert rn.sdo[comm][3].raw == 30
                assert rn.sdo[comm][5].raw == 500
            assert rn.sdo[0x1801][1].raw == 0x40000283   # raw mode: TPDO2 valid (bit 30: no RTR) ...
            assert rn.sdo[0x1800][1].raw == 0xC0000183   # ... instead of TPDO1
            assert rn.sdo[0x2002][2].raw == 20           # noisy taxel: stuck detector on (EDS default)
        finally:
            net.disconnect()
        n8 = rig.node(8)
        assert n8.read(0x2001, 3) == 6 and n8.read(0x2002, 2) == 0   # noiseless: stuck detector off
        assert n8.read(0x2001, 4) == 0.0                             # no geometry: EDS default
        assert set(rig.nodes) == {(0, 3), (0, 8)}


def test_decision_mode_leaves_tpdo2_disabled():
    ch = uid()
    scene = Scene(path="<t>", name="d", taxels=(TaxelSpec(node_id=1, kind="R"),), bus=BusSpec(channels=(ch,)))
    with Rig(scene, reading_source=lambda c: np.zeros(1)) as rig:
        assert rig.node(1).read(0x1801, 1) == 0xC0000281
        assert rig.node(1).read(0x1800, 1) == 0x40000181


def test_more_than_127_taxels_use_one_network_per_channel():
    a, b = uid("a"), uid("b")
    taxels = tuple(TaxelSpec(node_id=i, kind="C", channel=0) for i in range(1, 128)) + \
        tuple(TaxelSpec(node_id=i, kind="P", channel=1) for i in (1, 2, 3))
    scene = Scene(path="<t>", name="big", taxels=taxels, bus=BusSpec(channels=(a, b), heartbeat_producer_ms=0))
    seen = []

    def source(cycle):
        seen.append(cycle)
        x = np.zeros(len(taxels))
        x[127:] = 5.0            # channel b's taxels (scene indices 127..129) see contact
        return x

    rec_a, rec_b = Recorder(a), Recorder(b)
    try:
        with Rig(scene, reading_source=source) as rig:
            assert len(rig.buses) == 2 and len(rig.nodes) == 130
            rec_a.wait_count(0x701, 1)
            rec_b.wait_count(0x703, 1)
            rec_a.wait_count(0x77F, 1)                          # node 127 on network a (its boot-up
            assert rec_b.of(0x704) == []                        # may reach the recorder after node 1's)
            rec_b.send(0x000, bytes([0x01, 0]))                 # start network b only
            deadline = time.monotonic() + WAIT
            while rig.node(3, 1).state != 0x05 and time.monotonic() < deadline:
                time.sleep(0.005)
            sync_and_wait(rec_b, rig, channel=1)
            frames = rec_b.wait_count(0x181, 1)
            assert struct.unpack("<b", bytes(frames[0].data))[0] == 1      # 5.0 - 0 >= ζ = 1.0
            assert rig.cycle(0) is None and rig.cycle(1) == 0
            rec_a.barrier()
            assert rec_a.of(0x181) == []                        # network a is still pre-operational
            assert rig.node(1, 0).state == 0x7F
    finally:
        rec_a.close()
        rec_b.close()


def test_sync_counter_gap_counts_lost_syncs():
    ch = uid()
    scene = Scene(path="<t>", name="c", taxels=(TaxelSpec(node_id=1, kind="R", zeta_mv=1.0),),
                  bus=BusSpec(channels=(ch,), sync_counter=4, heartbeat_producer_ms=0))
    requested = []

    def source(cycle):
        requested.append(cycle)
        return np.array([float(cycle)])    # X = cycle: present from cycle 1 on (X - 0 >= 1)

    rec = Recorder(ch)
    try:
        with Rig(scene, reading_source=source) as rig:
            rec.send(0x000, bytes([0x01, 1]))
            deadline = time.monotonic() + WAIT
            while rig.node(1).state != 0x05 and time.monotonic() < deadline:
                time.sleep(0.005)
            for counter, cycle in ((1, 0), (2, 1), (4, 3), (1, 4), (3, 6)):
                sync_and_wait(rec, rig, data=bytes([counter]), expect_cycle=cycle)
            assert requested == [0, 1, 3, 4, 6]
            assert rig.lost_syncs() == 2
            frames = rec.wait_count(0x181, 5)
            # TPDO1 maps the tagged decision 0x2003 (a SYNC counter is configured): u_i in
            # bits 0-1 (0b11 = -1, 0b01 = +1), the SYNC's counter modulo 64 in bits 2-7
            assert [(f.data[0] & 3, f.data[0] >> 2) for f in frames] == [
                (0b11, 1), (0b01, 2), (0b01, 4), (0b01, 1), (0b01, 3)]
    finally:
        rec.close()


def test_default_readings_come_from_scene_physics():
    scene = load_scene(ROOT / "scenes" / "matrix57.toml")
    ch = uid("m57")
    from dataclasses import replace

    from node_sim import physics

    # untagged INTEGER8 u_i; no synchronous window: a SYNC handled late on a loaded host is still answered
    scene = replace(scene, bus=replace(scene.bus, channels=(ch,), heartbeat_producer_ms=0, sync_counter=0,
                                       sync_window_us=0))
    rec = Recorder(ch)
    try:
        with Rig(scene, seed=11) as rig:
            assert rig.scene.seed == 11
            rec.send(0x000, bytes([0x01, 0]))
            deadline = time.monotonic() + WAIT
            while any(n.state != 0x05 for n in rig.nodes.values()) and time.monotonic() < deadline:
                time.sleep(0.005)
            cycles = 25                            # the object is present from cycle 20 on
            for _ in range(cycles):
                sync_and_wait(rec, rig)
            for i, t in enumerate(scene.taxels):
                frames = rec.wait_count(0x180 + t.node_id, cycles)
                got = [struct.unpack("<b", bytes(f.data))[0] for f in frames]
                x = [physics.sample_readings(rig.scene, c)[i] for c in range(cycles)]
                want = [1 if xi - t.noise_mv >= t.zeta_mv else -1 for xi in x]   # eqs 3-4 by hand
                assert got == want, t.node_id
            present = sum(struct.unpack("<b", bytes(f.data))[0] == 1
                          for t in scene.taxels for f in rec.of(0x180 + t.node_id)[20:])
            assert present > 0
    finally:
        rec.close()


def test_rig_parameter_errors():
    ch = uid()
    scene = Scene(path="<t>", name="e", taxels=(TaxelSpec(node_id=1, kind="R"),), bus=BusSpec(channels=(ch,)))
    with pytest.raises(ParameterError, match="channel"):
        Rig(scene, channel=["a", "b"])
    with pytest.raises(ParameterError, match="channels"):
        Rig(Scene(path="<t>", name="e", taxels=(TaxelSpec(node_id=1, kind="R", channel=1),),
                  bus=BusSpec(channels=(ch,))))
    with pytest.raises(ParameterError, match="cannot be opened"):
        Rig(scene, interface="udp_multicast", channel="no-such-group").start()
    with pytest.raises(ParameterError, match="eds"):
        Rig(scene, eds_path="/nonexistent.eds")
    with pytest.raises(ParameterError, match="taxels"):
        Rig(Scene(path="<t>", name="e", bus=BusSpec(channels=(ch,))))
    rig = Rig(scene, reading_source=lambda c: np.zeros(1)).start()
    rig.stop()
    rig.stop()   # idempotent
    with pytest.raises(ParameterError):
        rig.drop_node(1)


@pytest.mark.parametrize("which", ["taxel", "patch", "gripper"])
def test_a_missing_eds_is_named_in_the_error(tmp_path, which):
    """The one-line error names the missing file and no other (it named eds/taxel_node.eds
    whichever EDS was missing)."""
    from node_sim.gripper.host import DriveHost
    from node_sim.patch import load_patch_od

    missing = tmp_path / f"no_{which}.eds"
    with pytest.raises(ParameterError) as info:
        if which == "taxel":
            Rig(load_scene("matrix57"), eds_path=missing)
        elif which == "patch":
            load_patch_od(1, missing)
        else:
            DriveHost(5, "virtual", uid(), eds_path=missing).start()
    text = str(info.value)
    assert str(missing) in text and "taxel_node.eds" not in text and "\n" not in text
    assert ("patch node" in text) == (which == "patch")


def test_bus_filters_follow_the_sync_cob_id_and_keep_out_the_pdos():
    """The twins' bus lets through what they consume (python-can filters: in the kernel on
    socketcan, before a Message is made on udp_multicast): when an SDO moves 0x1005 to
    another COB-ID, SYNC there still drives the node; a reset restores 0x080."""
    ch = uid()
    scene = Scene(path="<t>", name="f", taxels=(TaxelSpec(node_id=1, kind="R", zeta_mv=1.0),),
                  bus=BusSpec(channels=(ch,), heartbeat_producer_ms=0))
    rec = Recorder(ch)
    try:
        with Rig(scene, reading_source=lambda cycle: np.array([5.0])) as rig:
            bus = rig._channels[0].bus
            accepted = {f["can_id"] for f in bus.filters if f["can_mask"] == 0x7FF}
            assert 0x080 in accepted and 0x181 not in accepted
            assert not bus._matches_filters(can.Message(arbitration_id=0x181, is_extended_id=False))
            assert bus._matches_filters(can.Message(arbitration_id=0x601, is_extended_id=False))
            # SDO expedited download 0x1005:0 := 0x0A0 (COB-ID SYNC), then start the node
            rec.send(0x601, bytes([0x23, 0x05, 0x10, 0x00, 0xA0, 0x00, 0x00, 0x00]))
            answer = rec.wait_count(0x581, 1)[0]
            assert answer.data[0] == 0x60, answer.data.hex()
            assert bus._matches_filters(can.Message(arbitration_id=0x0A0, is_extended_id=False))
            rec.send(0x000, bytes([0x01, 1]))
            deadline = time.monotonic() + WAIT
            while rig.node(1).state != 0x05 and time.monotonic() < deadline:
                time.sleep(0.005)
            rec.send(0x0A0)
            assert rig.wait_cycle(0, 0, timeout=WAIT)
            assert rec.wait_count(0x181, 1)
            rec.send(0x000, bytes([0x82, 0]))  # reset communication: 0x1005 back to 0x080
            rec.wait_count(0x701, 2)           # the boot-up after the reset
            assert bus._matches_filters(can.Message(arbitration_id=0x080, is_extended_id=False))
    finally:
        rec.close()


def test_the_set_up_is_out_of_the_cyclic_collector_while_the_rig_runs_and_given_back_after():
    """While the rig runs its set-up (ODs, EDS imports) is frozen: a full collection does not
    traverse it (a pause of tens of ms at skin scale). Once stopped it is given back: a stopped
    rig is collected, never kept for the life of the process."""
    import gc
    import weakref

    from taxel_net import gcfreeze

    assert gcfreeze.holders() == 0
    gc.unfreeze()
    ch = uid()
    scene = Scene(path="<t>", name="g", taxels=(TaxelSpec(node_id=1, kind="R", zeta_mv=1.0),),
                  bus=BusSpec(channels=(ch,), heartbeat_producer_ms=0))
    rig = Rig(scene, reading_source=lambda cycle: np.array([0.0]))
    with rig:
        node = rig.node(1)
        assert gcfreeze.holders() == 1 and gc.get_freeze_count() > 0
        assert all(o is not node for o in gc.get_objects(generation=2))
        del node
    assert gcfreeze.holders() == 0 and gc.get_freeze_count() == 0
    gone = weakref.ref(rig)
    del rig
    gc.collect()
    assert gone() is None


def test_the_freeze_is_given_back_by_its_last_holder():
    import gc

    from taxel_net import gcfreeze

    gc.unfreeze()
    gcfreeze.hold()
    gcfreeze.hold()
    gcfreeze.release()
    assert gcfreeze.holders() == 1 and gc.get_freeze_count() > 0
    gcfreeze.release()
    assert gcfreeze.holders() == 0 and gc.get_freeze_count() == 0
    gcfreeze.release()  # more releases than holds: nothing happens
    assert gcfreeze.holders() == 0
