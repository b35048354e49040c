"""Raw readings beyond the range of a patch node's packed INTEGER8 / INTEGER16 counts: the node
sends the limit code, which the centre cannot tell from a genuine reading, so the node signals it
as CiA 301 / CiA 404 devices do (AI status 0x2033, EMCY 0x3000 on the rising edge and its error
reset 0x0000, inhibit time 0x1015) and the centre counts it and flags the records.

The twins' side is checked with canopen's master (its EMCY consumer and SDO client on the patch
EDS), the centre's with a FusionService running the twins; the expected TPDO of a taxel comes
from the scene's layout (taxel_net.patches.devices), the limits from the INTEGER ranges.
"""

from __future__ import annotations

import dataclasses
import math
import itertools
import time
import uuid

import canopen
import numpy as np
import pytest

from node_sim.patch import load_patch_od
from node_sim.rig import Rig
from taxel_net import patches as P

from test_node_conformance import wait_until  # noqa: E402 - bounded polling, WAIT = 5 s
from test_node_patch import write_scene

WAIT = 5.0
_names = itertools.count()
LSB = {"int8": 0.05, "int16": 0.01}   # mV a count: both ranges (6.35 / 327.67 mV) below full scale (1000 mV)
TOP = {"int8": 127, "int16": 32767}


def raw_scene(tmp_path, raw_format: str, n: int = 10, channel: str | None = None, sync_counter: int = 0):
    scene = write_scene(tmp_path, sizes=((0, 1, n),), mode="raw", raw_format=raw_format, sync_counter=sync_counter)
    name = channel or f"overrange{next(_names)}-{uuid.uuid4().hex[:6]}"
    return dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, channels=(name,), sync_window_us=0,
                                                              raw_lsb_mv=LSB[raw_format]))


class Twin:
    """One raw patch node twin (node-ID 1) with readings set by the test, canopen's master."""

    def __init__(self, scene):
        self.scene = scene
        self.x = np.zeros(scene.n)
        self.rig = Rig(scene, channel=scene.bus.channels[0], reading_source=lambda cycle: self.x.copy()).start()
        self.net = canopen.Network()
        self.net.connect(interface="virtual", channel=scene.bus.channels[0])
        self.node = self.net.add_node(canopen.RemoteNode(1, load_patch_od(1)))
        self.node.sdo.RESPONSE_TIMEOUT = 2.0
        self.cycle = 0
        self.net.send_message(0x000, bytes((0x01, 0)))          # NMT start
        assert wait_until(lambda: self.rig.node(1).state == 0x05)

    def sync(self) -> None:
        self.net.send_message(0x080, b"")
        assert self.rig.wait_cycle(self.cycle, timeout=WAIT)
        self.cycle += 1

    def emcys(self):
        return list(self.node.emcy.log)

    def close(self):
        self.net.disconnect()
        self.rig.stop()


@pytest.fixture
def twin(tmp_path):
    made = []

    def make(raw_format):
        t = Twin(raw_scene(tmp_path, raw_format))
        made.append(t)
        return t

    yield make
    for t in made:
        t.close()


def tpdo_of(scene, k: int) -> int:
    """The TPDO (1 = 0x1800) carrying taxel k of node 1, from the scene's layout."""
    (device,) = P.devices(scene)
    return next(t.number + 1 for t in device.tpdos if t.first <= k < t.first + t.count)


@pytest.mark.parametrize("raw_format", ["int8", "int16"])
def test_the_over_range_emcy_on_the_rising_edge_and_its_error_reset(twin, raw_format):
    t = twin(raw_format)
    limit = TOP[raw_format] * LSB[raw_format]              # the largest reading the counts carry, mV
    t.x[:] = 0.5 * limit
    t.x[2] = -0.9 * limit
    t.sync()
    t.sync()
    assert wait_until(lambda: t.rig.node(1).last_cycle == 1)
    assert t.emcys() == []                                  # in range: silence

    t.x[7] = 1.5 * limit                                    # sent as the largest code
    t.x[9] = -2.0 * limit                                   # sent as the most negative code + 1
    t.sync()
    assert wait_until(lambda: len(t.emcys()) == 1), "no EMCY for readings over range"
    (e,) = t.emcys()
    assert e.code == 0x3000 and e.register == 0x05         # voltage; error register bits 0 and 2
    # manufacturer field: over-range id 3, first taxel over range, its TPDO, its AI status, count
    assert bytes(e.data) == bytes((3, 7, tpdo_of(t.scene, 7), 0x02, 2))
    status = [t.node.sdo[P.PATCH_AI_STATUS][k + 1].raw for k in range(t.scene.n)]
    assert status == [0x02 if k == 7 else 0x04 if k == 9 else 0 for k in range(t.scene.n)]
    assert t.node.sdo[0x1001].raw == 0x05
    assert t.node.sdo[0x1003][1].raw == 0x3000 | 3 << 16
    # the limit codes on the bus, as before: only the signal above tells them from readings
    index = P.PATCH_READINGS_I8 if raw_format == "int8" else P.PATCH_READINGS_I16
    assert t.node.sdo[index][8].raw == TOP[raw_format]
    assert t.node.sdo[index][10].raw == -TOP[raw_format]

    t.x[7] = 3.0 * limit                                    # still over range: no new EMCY
    t.sync()
    t.sync()
    assert wait_until(lambda: t.rig.node(1).last_cycle == 4)
    time.sleep(0.05)
    assert len(t.emcys()) == 1

    t.x[7] = t.x[9] = 0.0                                   # back in range: the error reset
    t.sync()
    assert wait_until(lambda: len(t.emcys()) == 2)
    reset = t.emcys()[1]
    assert reset.code == 0x0000 and reset.register == 0x00 and bytes(reset.data) == bytes((3, 0, 0, 0, 0))
    assert [e.code for e in t.node.emcy.active] == []
    assert t.node.sdo[0x1001].raw == 0
    assert [t.node.sdo[P.PATCH_AI_STATUS][k + 1].raw for k in range(t.scene.n)] == [0] * t.scene.n


def test_the_emcy_inhibit_time_spaces_the_error_reset(twin):
    t = twin("int8")
    assert 0x1015 in t.node.object_dictionary, "the patch EDS has no EMCY inhibit time"
    assert t.node.sdo[0x1015].raw == 0                      # EDS default: no inhibit time
    t.node.sdo[0x1015].raw = 3000                           # 300 ms in 100 us units
    t.x[4] = 10.0                                           # > 127 * 0.05 mV
    t.sync()
    assert wait_until(lambda: len(t.emcys()) == 1)
    t.x[4] = 0.0
    t.sync()                                                # the reset is due now, inhibited
    assert wait_until(lambda: len(t.emcys()) == 2, timeout=WAIT + 0.3)
    first, second = t.emcys()
    assert (first.code, second.code) == (0x3000, 0x0000)
    assert second.timestamp - first.timestamp >= 0.3 - 0.005   # not before the inhibit time (a lower bound)


@pytest.mark.parametrize("pause", ["stopped", "0x1014 invalid"])
def test_an_emcy_queued_behind_the_inhibit_time_is_sent_after_a_pause(twin, pause):
    # the error reset is queued behind the inhibit time, then the node may not send (NMT stop, or
    # its EMCY COB-ID made not valid) while that time passes: it is kept and sent when the node may
    # again (CANopenNode's EMCY FIFO), not lost - the master must not be left seeing the error
    t = twin("int8")
    t.node.sdo[0x1015].raw = 3000                           # 300 ms
    t.x[4] = 10.0
    t.sync()
    assert wait_until(lambda: len(t.emcys()) == 1)
    t.x[4] = 0.0
    t.sync()                                                # the error reset: queued
    cob = t.node.sdo[0x1014].raw
    if pause == "stopped":
        t.net.send_message(0x000, bytes((0x02, 1)))         # NMT stop node 1
        assert wait_until(lambda: t.rig.node(1).state == 0x04)
    else:
        t.node.sdo[0x1014].raw = cob | 0x80000000
    time.sleep(0.45)                                        # the inhibit time is up during the pause
    assert [e.code for e in t.emcys()] == [0x3000]
    if pause == "stopped":
        t.net.send_message(0x000, bytes((0x01, 1)))         # NMT start
    else:
        t.node.sdo[0x1014].raw = cob
    assert wait_until(lambda: len(t.emcys()) == 2), "the queued error reset was lost"
    assert [(e.code, e.register) for e in t.emcys()] == [(0x3000, 0x05), (0x0000, 0x00)]
    assert t.node.sdo[0x1001].raw == 0


def test_unmapping_the_readings_while_over_range_sends_the_error_reset(twin):
    # no TPDO carries a reading any more: none is over range on the bus, so the error ends
    t = twin("int8")
    t.x[4] = 10.0
    t.sync()
    assert wait_until(lambda: len(t.emcys()) == 1)
    (device,) = P.devices(t.scene)
    t.net.send_message(0x000, bytes((0x80, 1)))             # pre-operational
    assert wait_until(lambda: t.rig.node(1).state == 0x7F)
    for tp in device.tpdos:                                 # every readings TPDO not valid (0x180x:1 bit 31)
        t.node.sdo[0x1800 + tp.number][1].raw |= 0x80000000
    t.net.send_message(0x000, bytes((0x01, 1)))             # operational
    assert wait_until(lambda: t.rig.node(1).state == 0x05)
    t.sync()                                                # still 10 mV: the reading is just not sent
    assert wait_until(lambda: len(t.emcys()) == 2), "no error reset: 0x1001 = %#x" % t.node.sdo[0x1001].raw
    reset = t.emcys()[1]
    assert (reset.code, reset.register, bytes(reset.data)) == (0x0000, 0x00, bytes((3, 0, 0, 0, 0)))
    assert t.node.sdo[0x1001].raw == 0


def test_the_ai_status_refers_to_the_mapped_readings_in_pre_operational(tmp_path):
    # 10 mV at 0.05 mV a count: 200 counts, beyond INTEGER8, within INTEGER16. The raw scene's
    # TPDOs map 0x2030 (INTEGER8): 0x2033 says "positive overload" from the boot on, before any
    # OPERATIONAL SYNC; with those TPDOs not valid (no readings mapped) it refers to INTEGER16
    scene = raw_scene(tmp_path, "int8")
    x = np.zeros(scene.n)
    x[4] = 10.0
    rig = Rig(scene, channel=scene.bus.channels[0], reading_source=lambda c: x.copy()).start()
    net = canopen.Network()
    net.connect(interface="virtual", channel=scene.bus.channels[0])
    node = net.add_node(canopen.RemoteNode(1, load_patch_od(1)))
    node.sdo.RESPONSE_TIMEOUT = 2.0
    try:
        assert rig.node(1).state == 0x7F
        net.send_message(0x080, b"")                        # a SYNC in PRE-OPERATIONAL: sampled, no TPDO
        assert rig.wait_cycle(0, timeout=WAIT)
        (device,) = P.devices(scene)
        assert node.sdo[0x1A00 + tpdo_of(scene, 4) - 1][1].raw >> 16 == P.PATCH_READINGS_I8   # no tag: readings only
        assert node.sdo[P.PATCH_READINGS_I8][5].raw == 127
        assert node.sdo[P.PATCH_AI_STATUS][5].raw == 0x02
        for tp in device.tpdos:
            node.sdo[0x1800 + tp.number][1].raw |= 0x80000000
        assert wait_until(lambda: node.sdo[P.PATCH_AI_STATUS][5].raw == 0)
        assert node.sdo[P.PATCH_READINGS_I16][5].raw == 200
    finally:
        net.disconnect()
        rig.stop()


# ------------------------------------------------------------------------------ the centre
OVER = range(6, 10)     # cycles whose readings are over range (taxel 3: sent as the largest code)
EXACT = range(12, 15)   # cycles whose taxel 3 reads exactly the largest code's value: the same counts


def readings(n: int, cycle: int) -> np.ndarray:
    x = np.full(n, 1.0)                                     # below zeta (2.5 mV): absent
    if cycle in OVER:
        x[3] = 50.0                                         # clipped to 127 counts = 6.35 mV
    elif cycle in EXACT:
        x[3] = 127 * LSB["int8"]                            # a genuine 6.35 mV: 127 counts too
    return x


def test_the_centre_counts_the_over_range_emcys_and_flags_the_clipped_cycles(tmp_path):
    from fusion_center.commands.run import execute, format_summary
    from fusion_center.service import FusionService

    # 30 taxels: the scene's object covers some (its centralised tests need a footprint); a SYNC
    # counter: every frame tagged with its SYNC, so a loaded host cannot count one cycle's
    # readings in the next (untagged, a frame stamped after the next SYNC would be)
    scene = raw_scene(tmp_path, "int8", n=30, channel=f"centre-or-{uuid.uuid4().hex[:8]}", sync_counter=16)
    scene = dataclasses.replace(scene, cycles=20)
    channels = list(scene.bus.channels)
    service = FusionService(scene, interface="virtual", channels=channels, truth=False)
    rig = Rig(scene, interface="virtual", channel=channels, reading_source=lambda c: readings(scene.n, c))
    with service:
        try:
            summary = execute(service, 18, live=False, boot_timeout=5.0, on_start=rig.start)
        finally:
            rig.stop()
    records = {r["cycle"]: r for r in service.records}
    assert sorted(records) == list(range(18))
    # the EMCY leaves before the frames of its SYNC, after the centre opened that SYNC's cycle:
    # every cycle whose readings all arrived is flagged exactly when they were clipped (a cycle
    # a loaded host closed before its frames came has no readings to flag - they are late - and
    # the EMCY counts in the next window)
    whole = [c for c, r in records.items() if r["n_received"] == scene.n]
    flags = {c: records[c]["over_range_nodes"] for c in whole}
    trail = {c: (r["closed_by"], r["n_received"], r["late_frames"], [(e["code"], e["t"]) for e in r["emcy"]], r["t"])
             for c, r in records.items()}
    assert flags == {c: [1] if c in OVER else [] for c in whole}, trail
    assert [e["code"] for r in records.values() for e in r["emcy"]] == ["0x3000", "0x0000"]   # one edge each way
    # a clipped cycle's readings on the wire equal a genuine limit reading's: only the flag differs
    clipped = records[next(c for c in OVER if c in whole)]
    exact = records[next(c for c in EXACT if c in whole)]
    assert clipped["present_nodes"] == exact["present_nodes"] == ["1/3"]
    assert clipped["rules"] == exact["rules"]
    assert clipped["over_range_nodes"] == [1] and exact["over_range_nodes"] == []
    flagged = sum(1 for r in records.values() if r["over_range_nodes"])
    assert flagged >= len([c for c in OVER if c in whole])
    assert summary["over_range"] == {"cycles": flagged, "emcy": {"1": 1}}
    assert any(line.startswith("over_range:") and f"{flagged} cycles flagged" in line and "node 1 1" in line
               for line in format_summary(summary))


def test_a_decision_scene_has_no_over_range_field(tmp_path):
    from fusion_center.service.pipeline import CyclePipeline

    scene = write_scene(tmp_path, sizes=((0, 1, 10),), mode="decision", sync_counter=0)
    assert CyclePipeline(scene, truth=False).over_range is None


# ------------------------------------------------------------------------------ the parts
def test_the_ai_status_of_readings_at_and_beyond_the_integer_ranges():
    # int8 at 0.1 mV: counts -127..127 carry -12.7..12.7 mV (to half a count: 12.74 is 127);
    # a reading whose nearest count is beyond: the limit code and an overload bit
    x = [12.7, 12.74, 12.76, 1e6, -12.7, -12.74, -12.76, math.inf, -math.inf, math.nan, 0.0]
    counts, status = P.counts_and_status(P.ENC_INT8, x, 0.1)
    assert counts.tolist() == [127, 127, 127, 127, -127, -127, -127, 127, -127, -128, 0]
    assert status.tolist() == [0, 0, 2, 2, 0, 0, 4, 2, 4, 1, 0]
    counts, status = P.counts_and_status(P.ENC_INT16, [3276.74, 3276.76, -3276.76], 0.1)
    assert counts.tolist() == [32767, 32767, -32767] and status.tolist() == [0, 2, 4]


def _closed(cycle, emcy=(), missing=False, state=0x05, bootups=()):
    """A closed cycle of one raw patch node (node-ID 1): ``emcy`` its EMCYs as (code, register)
    or (code, register, t_us); ``bootups`` ((device 0, t_us),) when it sent a boot-up."""
    from fusion_center.service.cycle_records import ClosedCycle, DeviceCycle, EmcyEvent

    n = 3
    devices = DeviceCycle(expected=np.array([True]), missing=np.array([missing]),
                          states=np.array([state], dtype=np.int16), complete=np.array([True]))
    return ClosedCycle(cycle=cycle, sync_us=0, close_us=0, sync_counter=None, closed_by="complete",
                       decisions=np.zeros(n, np.int8), readings=np.zeros(n), received=np.ones(n, bool),
                       expected=np.ones(n, bool), missing=np.zeros(n, bool), held_decisions=np.zeros(n, np.int8),
                       held_readings=np.zeros(n), late_frames=0, bad_frames=0,
                       emcy=tuple(EmcyEvent(1, 0, e[0], e[1], "", e[2] if len(e) > 2 else 0) for e in emcy),
                       devices=devices, bootups=tuple(bootups))


def test_the_centre_follows_a_nodes_over_range_from_its_emcys_and_forgets_it_on_a_reset_not_a_loss():
    from fusion_center.service.over_range import OverRangeTracker

    t = OverRangeTracker([1])
    assert t.update(_closed(0)) == []
    assert t.update(_closed(1, [(0x3000, 0x05)])) == [1]
    assert t.update(_closed(2)) == [1]                                  # until the node says otherwise
    assert t.update(_closed(3, [(0x5000, 0x25)])) == [1]                # another error, bit 2 still set
    assert t.update(_closed(4, [(0x0000, 0x21)])) == []                 # a reset with bit 2 clear
    assert t.update(_closed(5, [(0x3000, 0x05), (0x0000, 0x00), (0x3000, 0x05)])) == [1]   # in bus order
    assert t.update(_closed(6, state=-2)) == []                         # NMT reset sent: afresh
    assert t.update(_closed(7, [(0x3000, 0x05)])) == [1]
    # lost (heartbeat consumer time expired): a node heard again without a boot-up resumes with
    # its error state as it was, and sends no second 0x3000 while still over range
    assert t.update(_closed(8, missing=True)) == [1]
    assert t.update(_closed(9)) == [1]
    assert t.update(_closed(10, [(0x0000, 0x01)])) == []                # its error reset, once back in range
    assert t.update(_closed(11, [(0x3000, 0x05)], missing=True)) == [1]
    assert t.update(_closed(12, state=-2)) == []                        # NMT reset: afresh, missing or not
    assert dict(t.emcy) == {1: 5}                                       # cycles 1, 5 (two), 7, 11


def test_a_node_that_restarts_by_itself_starts_its_over_range_afresh_at_its_boot_up():
    """A boot-up the centre did not ask for (a watchdog, a power cycle) - no NMT reset sent, so
    no RESETTING state - clears the node's flag: back in range, it would never send the error
    reset of an EMCY it no longer remembers. Its EMCYs of the same cycle count in bus time."""
    from fusion_center.service.over_range import OverRangeTracker

    t = OverRangeTracker([1])
    assert t.update(_closed(0, [(0x3000, 0x05)])) == [1]
    assert t.update(_closed(1, state=0x7F)) == [1]                       # pre-operational alone says nothing
    assert t.update(_closed(2, bootups=((0, 500),), state=0x7F)) == []   # its boot-up: afresh
    assert t.update(_closed(3, state=0x05)) == []
    assert t.update(_closed(4, [(0x3000, 0x05, 900)], bootups=((0, 500),))) == [1]  # over range after it
    assert t.update(_closed(5, [(0x0000, 0x00, 1100), (0x3000, 0x05, 1200)], bootups=((0, 1500),))) == []
    assert t.emcy == {1: 3}                                              # every 0x3000 heard, applied or not


def test_a_boot_up_clears_the_flag_whatever_its_stamp_two_assembler_processes_both_stamping_it_0():
    """Each assembler process stamps t_us from its own first frame, so a node whose boot-up is a
    process's first frame has t_us 0 in every process (the run's start, then the group's host and
    nodes power-cycled: a new process). Stamps of different processes are not comparable: the
    second boot-up, stamped 0 again and before the EMCY 0x3000 the first process stamped 5 s, is a
    genuine restart and clears the flag (back in range the node would never send the error reset
    of an EMCY it no longer remembers). A duplicate or replayed part never reaches the tracker with
    its events: the cycle merger carries a late part's events only when its cycle is newer than its
    group's last part (tests/test_assemblers.py)."""
    from fusion_center.service.over_range import OverRangeTracker

    t = OverRangeTracker([1])
    assert t.update(_closed(0, bootups=((0, 0),))) == []                  # process 1's first frame
    assert t.update(_closed(1, [(0x3000, 0x05, 5_000_000)])) == [1]
    assert t.update(_closed(2, bootups=((0, 0),), state=0x7F)) == []     # process 2's first frame: afresh
    assert t.update(_closed(3)) == [] and t.update(_closed(4)) == []
    assert t.update(_closed(5, [(0x3000, 0x05, 0)], bootups=((0, 0),))) == []   # at its stamp: before it
    assert t.update(_closed(6, [(0x3000, 0x05, 7)])) == [1]               # after it: flagged again
    assert t.emcy == {1: 3}


def _booted_raw_node():
    """A raw patch node of 3 INTEGER8 readings (node-ID 1), booted and started: the centre's
    cycle assembler, its pipeline and the node's TPDO (hand-fed frames, no bus)."""
    from fusion_center.service.cycles import CycleAssembler
    from fusion_center.service.pipeline import CyclePipeline
    from taxel_net.patches import devices
    from test_cycles_patch import boot, patch_scene

    sc = patch_scene(sizes=(3,), mode="raw", raw_format="int8", lsb=0.1)
    a, pipeline = CycleAssembler(sc), CyclePipeline(sc, truth=False)
    boot(a, sc)
    (tpdo,) = devices(sc)[0].tpdos
    return a, pipeline, tpdo


def test_a_boot_up_between_syncs_reaches_the_closed_cycle_and_clears_the_record_flag():
    """The chain a live run and a replay take: the boot-up frame -> the closed cycle's
    ``bootups`` -> ``over_range_nodes`` of the record (the pipeline as the centre runs it)."""
    from test_cycles_patch import MS, sync

    a, pipeline, tpdo = _booted_raw_node()
    records = []
    for k in range(4):
        sync(a, (k + 1) * 10 * MS, k + 1)
        if k == 0:  # the rising edge: EMCY 0x3000, error register bits 0 and 2, before the TPDO
            assert a.feed(10 * MS + 1, 0, 0x081, bytes([0x00, 0x30, 0x05, 0, 0, 0, 0, 0])) is None
        if k == 2:  # a boot-up the centre did not ask for, then NMT start by another master
            assert a.feed(30 * MS + 1, 0, 0x701, b"\x00") is None
            assert a.feed(30 * MS + 2, 0, 0x000, bytes([0x01, 1])) is None
        closed = a.feed((k + 1) * 10 * MS + 5, 0, tpdo.cob_id, bytes([k + 1, 127, 3, 4]))
        assert closed is not None and closed.closed_by == "complete", k
        assert closed.bootups == {0: ((0, 0),), 2: ((0, 30 * MS + 1),)}.get(k, ()), k  # 0: the first boot
        records.append(pipeline.evaluate(closed))
    assert [r["over_range_nodes"] for r in records] == [[1], [1], [], []]


def test_an_emcy_before_a_boot_up_of_the_same_stamp_is_not_applied():
    """Bus order is the truth (cycles.py: a frame stamped before the previous one is taken at
    the previous one's time): the node's EMCY 0x3000, then its own boot-up, both at 20.003 ms
    after the clamp - the node restarted after its EMCY, its flag starts afresh."""
    from test_cycles_patch import MS, sync

    a, pipeline, tpdo = _booted_raw_node()
    over = []
    for k in range(3):
        sync(a, (k + 1) * 10 * MS, k + 1)
        if k == 1:
            assert a.feed(20 * MS + 3, 0, 0x081, bytes([0x00, 0x30, 0x05, 0, 0, 0, 0, 0])) is None
            assert a.feed(20 * MS + 2, 0, 0x701, b"\x00") is None     # its boot-up, next on the bus
            assert a.feed(20 * MS + 4, 0, 0x000, bytes([0x01, 1])) is None
        closed = a.feed((k + 1) * 10 * MS + 5, 0, tpdo.cob_id, bytes([k + 1, 1, 3, 4]))
        assert closed is not None and closed.closed_by == "complete", k
        over.append(pipeline.evaluate(closed)["over_range_nodes"])
    assert over == [[], [], []]
