"""The SYNC-cycle assembler as a pure state machine: hand-built event streams, hand-worked
expectations (no bus, no clock)."""

import numpy as np
import pytest

from taxel_net.scene import BusSpec, FusionSpec, Scene, TaxelSpec
from fusion_center.service.cycle_records import COUNTER_NAMES, FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE
from fusion_center.service.cycles import CycleAssembler

MS = 1000  # µs


def scene(n=3, consumer_ms=300, sync_counter=0, tx_type=1, mode="decision", channels=("c0",)):
    taxels = tuple(TaxelSpec(node_id=10 + i, kind="R", zeta_mv=1.0) for i in range(n))
    bus = BusSpec(sync_counter=sync_counter, heartbeat_consumer_ms=consumer_ms, transmission_type=tx_type,
                  mode=mode, channels=channels)
    return Scene(path="<test>", name="t", bus=bus, taxels=taxels, fusion=FusionSpec())


def boot_all(a, sc, t=0):
    for tx in sc.taxels:
        assert a.feed(t, 0, 0x700 + tx.node_id, b"\x00") is None
    assert a.feed(t, 0, 0x000, bytes([0x01, 0])) is None  # NMT start all


def tpdo(node_id, u):
    return 0x180 + node_id, bytes([u & 0xFF])


def test_early_close_when_every_expected_node_reported():
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    assert a.feed(10 * MS, 0, 0x80, b"") is None  # cycle 0 opens
    assert a.feed(10 * MS + 100, 0, *tpdo(10, 1)) is None
    assert a.feed(10 * MS + 200, 0, *tpdo(11, -1)) is None
    closed = a.feed(10 * MS + 300, 0, *tpdo(12, 1))
    assert closed is not None
    assert closed.cycle == 0 and closed.closed_by == "complete"
    assert closed.decisions.tolist() == [1, -1, 1]
    assert closed.received.all() and not closed.missing.any()
    assert closed.sync_us == 10 * MS and closed.close_us == 10 * MS + 300


def test_duplicate_and_after_close_frames_are_late_and_never_mixed_in():
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")
    a.feed(10 * MS + 1, 0, *tpdo(10, 1))
    a.feed(10 * MS + 2, 0, *tpdo(10, -1))  # duplicate: late, value not used
    a.feed(10 * MS + 3, 0, *tpdo(11, 1))
    closed = a.feed(10 * MS + 4, 0, *tpdo(12, 1))
    assert closed.decisions.tolist() == [1, 1, 1]
    a.feed(10 * MS + 5, 0, *tpdo(12, -1))  # after the early close: late
    nxt = None
    a.feed(20 * MS, 0, 0x80, b"")
    for node_id in (10, 11):
        a.feed(20 * MS + 1, 0, *tpdo(node_id, -1))
    nxt = a.feed(20 * MS + 2, 0, *tpdo(12, -1))
    assert nxt.decisions.tolist() == [-1, -1, -1]
    assert a.counters()["late"] == 2
    assert closed.late_frames == 1  # the duplicate, before cycle 0 closed
    assert nxt.late_frames == 1     # the one after cycle 0's close, reported with cycle 1


def test_close_at_next_sync_marks_silent_node_and_adjusts_nothing_else():
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")
    a.feed(10 * MS + 1, 0, *tpdo(10, 1))
    a.feed(10 * MS + 2, 0, *tpdo(12, 1))
    closed = a.feed(20 * MS, 0, 0x80, b"")
    assert closed.closed_by == "sync"
    assert closed.received.tolist() == [True, False, True]
    assert closed.expected.tolist() == [True, True, True]
    assert closed.decisions.tolist() == [1, 0, 1]
    assert not closed.missing.any()  # silent for 10 ms only: not missing yet


def test_heartbeat_consumer_time_declares_missing_and_recovery():
    # node 11 last heard at t=0 (boot-up); consumer 300 ms: at a SYNC at 300 ms it is still
    # live (not > 300 ms), at 301 ms it is missing; a heartbeat brings it back.
    sc = scene(consumer_ms=300)
    a = CycleAssembler(sc)
    boot_all(a, sc)
    for t in (300 * MS, 301 * MS):
        for node_id in (10, 12):
            a.feed(t - 1, 0, 0x700 + node_id, b"\x05")
        a.feed(t, 0, 0x80, b"")
        closed_missing = a.missing.copy()
        if t == 300 * MS:
            assert closed_missing.tolist() == [False, False, False]
        else:
            assert closed_missing.tolist() == [False, True, False]
    # missing nodes are not waited for: the cycle closes as soon as 10 and 12 reported
    a.feed(301 * MS + 1, 0, *tpdo(10, 1))
    closed = a.feed(301 * MS + 2, 0, *tpdo(12, 1))
    assert closed is not None and closed.closed_by == "complete"
    assert closed.missing.tolist() == [False, True, False]
    # recovery: a heartbeat (operational) from node 11
    a.feed(305 * MS, 0, 0x700 + 11, b"\x05")
    a.feed(310 * MS, 0, 0x80, b"")
    assert a.missing.tolist() == [False, False, False]
    assert a.expected.tolist() == [True, True, True]


def test_never_heard_node_is_missing_and_cycles_without_expected_nodes_close_at_sync():
    sc = scene()
    a = CycleAssembler(sc)
    a.feed(0, 0, 0x80, b"")
    assert a.missing.all()
    # a TPDO from a never-heard node while a cycle is open is accepted (the node is back)
    assert a.feed(1, 0, *tpdo(10, 1)) is None
    closed = a.feed(10 * MS, 0, 0x80, b"")
    assert closed.closed_by == "sync" and closed.decisions.tolist() == [1, 0, 0]
    assert a.missing.tolist() == [False, True, True]


def test_nmt_broadcast_stop_closes_the_open_cycle_and_start_does_not():
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")
    assert a.feed(10 * MS + 1, 0, 0x000, bytes([0x01, 0])) is None
    closed = a.feed(10 * MS + 2, 0, 0x000, bytes([0x80, 0]))
    assert closed.closed_by == "nmt" and closed.cycle == 0
    # pre-operational nodes are not expected in the next cycle
    a.feed(20 * MS, 0, 0x80, b"")
    assert not a.expected.any()


def test_pre_operational_node_is_not_waited_for():
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(1, 0, 0x000, bytes([0x80, 11]))  # node 11 to pre-operational
    a.feed(10 * MS, 0, 0x80, b"")
    assert a.expected.tolist() == [True, False, True]
    a.feed(10 * MS + 1, 0, *tpdo(10, 1))
    assert a.feed(10 * MS + 2, 0, *tpdo(12, 1)).closed_by == "complete"


@pytest.mark.parametrize("data,counter", [(b"\x01", "bad_value"), (b"\x00", "bad_value"), (b"", "bad_dlc"),
                                          (b"\x01\x01", "bad_dlc")])
def test_tpdo_domain_checks(data, counter):
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")
    if data == b"\x01":
        data = b"\x02"  # 2 is no decision
    a.feed(10 * MS + 1, 0, 0x180 + 10, data)
    assert a.counters()[counter] == 1
    assert a.decisions[0] == 0


def test_sync_counter_validation_and_value():
    sc = scene(sync_counter=4)
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")          # no counter byte: wrong DLC
    a.feed(11 * MS, 0, 0x80, b"\x05")      # 5 > overflow 4
    a.feed(12 * MS, 0, 0x80, b"\x00")      # 0 is not a counter value
    assert a.cycle == -1
    assert a.counters()["bad_dlc"] == 1 and a.counters()["bad_value"] == 2
    a.feed(13 * MS, 0, 0x80, b"\x04")
    closed = a.feed(14 * MS, 0, 0x80, b"\x01")
    assert closed.sync_counter == 4 and a.sync_counter == 1


def test_emcy_decoded_and_reported_once():
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")
    # error code 0x5010 little endian, error register 0x81, manufacturer bytes
    a.feed(10 * MS + 5, 0, 0x80 + 11, bytes([0x10, 0x50, 0x81, 1, 2, 3, 4, 5]))
    a.feed(10 * MS + 6, 0, 0x80 + 11, bytes([0x10, 0x50, 0x81]))  # short EMCY: bad_dlc
    closed = a.feed(20 * MS, 0, 0x80, b"")
    assert len(closed.emcy) == 1
    e = closed.emcy[0].as_record()
    assert e == {"node": 11, "code": "0x5010", "register": "0x81", "manufacturer": "0102030405", "t": 0.010005}
    assert closed.bad_frames == 1
    later = a.feed(30 * MS, 0, 0x80, b"")
    assert later.emcy == ()


def test_flags_unknown_ids_and_counter_sum():
    sc = scene()
    a = CycleAssembler(sc)
    events = [
        (0, 0, 0x123, b"", FLAG_ERROR),
        (0, 0, 0x18A, b"\x01", FLAG_REMOTE),
        (0, 0, 0x18A, b"\x01", FLAG_EXTENDED),
        (0, 0, 0x180 + 99, b"\x01", 0),   # node 99 is not in the scene
        (0, 5, 0x80, b"", 0),             # channel the scene does not have
        (0, 0, 0x100, bytes(6), 0),       # TIME
        (0, 0, 0x580 + 10, bytes([0x80] + [0] * 7), 0),  # SDO abort
        (0, 0, 0x600 + 10, bytes(8), 0),  # SDO request
    ]
    for e in events:
        a.feed(*e)
    c = a.counters()
    assert (c["error_frame"], c["remote_frame"], c["extended_id"], c["unknown_cob_id"]) == (1, 1, 1, 2)
    assert (c["time"], c["sdo_abort"], c["sdo"]) == (1, 1, 1)
    assert sum(c.values()) == len(events) == a.events
    assert set(c) == set(COUNTER_NAMES)


def test_timestamps_are_relative_to_first_event_and_clamped_monotonic():
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc, t=5_000_000)
    a.feed(5_010_000, 0, 0x80, b"")
    a.feed(5_009_000, 0, *tpdo(10, 1))  # earlier than the SYNC: clamped to it
    assert a.last_heard[0] == 10_000


def test_second_channel_sync_is_counted_but_opens_no_cycle():
    taxels = (TaxelSpec(node_id=1, kind="R", channel=0), TaxelSpec(node_id=1, kind="R", channel=1))
    sc = Scene(path="<t>", name="t", bus=BusSpec(channels=("a", "b")), taxels=taxels)
    a = CycleAssembler(sc)
    a.feed(0, 0, 0x701, b"\x05")
    a.feed(0, 1, 0x701, b"\x05")
    a.feed(10, 0, 0x80, b"")
    a.feed(11, 1, 0x80, b"")
    assert a.cycle == 0 and a.counters()["sync"] == 2
    a.feed(12, 1, 0x181, b"\x01")
    closed = a.feed(13, 0, 0x181, b"\xff")
    assert closed.closed_by == "complete" and closed.decisions.tolist() == [-1, 1]
    assert a.labels == [1, "1:1"]


def test_hold_mode_keeps_last_values_for_non_every_sync_transmission():
    sc = scene(tx_type=2)
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")
    for node_id in (10, 11, 12):
        assert a.feed(10 * MS + 1, 0, *tpdo(node_id, 1)) is None  # no early close
    closed = a.feed(20 * MS, 0, 0x80, b"")
    assert closed.closed_by == "sync"
    closed = a.feed(30 * MS, 0, 0x80, b"")
    assert closed.decisions.tolist() == [0, 0, 0] and closed.held_decisions.tolist() == [1, 1, 1]
    assert np.array_equal(closed.received, [False] * 3)


def tagged(node_id, u, counter):
    """TPDO1 mapping 0x2003: u_i in bits 0-1 (0b01 = +1, 0b11 = -1), counter mod 64 in bits 2-7
    (written out here, not taken from node_sim, so the two sides are checked against the spec)."""
    return 0x180 + node_id, bytes([(counter % 64) << 2 | (0b01 if u > 0 else 0b11)])


def test_tagged_decision_counts_only_in_the_cycle_of_its_sync():
    sc = scene(sync_counter=240)
    assert sc.bus.cycle_tag
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, bytes([70]))                  # cycle 0, counter 70 (tag 6)
    a.feed(10 * MS + 100, 0, *tagged(10, 1, 70))
    a.feed(10 * MS + 200, 0, *tagged(11, -1, 70))
    # node 12 answers cycle 0 only after the next SYNC went out, stamped later than it: by time
    # alone it looks like an answer to cycle 1; its tag says cycle 0 - late, never counted in 1
    closed0 = a.feed(20 * MS, 0, 0x80, bytes([71]))
    assert closed0.decisions.tolist() == [1, -1, 0] and closed0.closed_by == "sync"  # no 0x1007 here
    a.feed(20 * MS + 100, 0, *tagged(12, 1, 70))
    assert a.counters()["late"] == 1 and not a.got1[2]
    a.feed(20 * MS + 200, 0, *tagged(12, -1, 71))          # its own answer to cycle 1: counted
    a.feed(20 * MS + 300, 0, *tagged(10, 1, 71 + 64))      # the tag is the counter modulo 64
    closed1 = a.feed(20 * MS + 400, 0, *tagged(11, 1, 71))
    assert closed1.cycle == 1 and closed1.closed_by == "complete"
    assert closed1.decisions.tolist() == [1, 1, -1]
    assert a.counters()["tpdo1"] == 5


def test_tagged_decision_codes_outside_the_two_values_are_bad():
    sc = scene(sync_counter=4)
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"\x01")
    a.feed(10 * MS + 1, 0, 0x180 + 10, bytes([1 << 2 | 0b00]))
    a.feed(10 * MS + 2, 0, 0x180 + 10, bytes([1 << 2 | 0b10]))
    a.feed(10 * MS + 3, 0, 0x180 + 10, b"\x01\x00")         # DLC 2
    assert a.counters()["bad_value"] == 2 and a.counters()["bad_dlc"] == 1
    assert a.decisions.tolist() == [0, 0, 0]


def test_untagged_scenes_keep_the_integer8_decision():
    sc = scene(sync_counter=0)
    assert not sc.bus.cycle_tag and not scene(sync_counter=4, mode="raw").bus.cycle_tag
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")
    a.feed(10 * MS + 1, 0, 0x180 + 10, bytes([1 << 2 | 0b01]))  # a tagged byte: not INTEGER8 +-1
    assert a.counters()["bad_value"] == 1


def test_two_decisions_tagged_with_one_sync_flag_a_duplicate_node_id():
    sc = scene(sync_counter=64)
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, bytes([5]))
    a.feed(10 * MS + 1, 0, *tagged(10, 1, 5))
    a.feed(10 * MS + 2, 0, *tagged(10, -1, 5))   # a second device answering for node 10
    a.feed(10 * MS + 3, 0, *tagged(11, 1, 4))    # a late answer to the previous SYNC: no evidence
    a.feed(10 * MS + 4, 0, *tagged(11, 1, 5))
    closed = a.feed(10 * MS + 5, 0, *tagged(12, 1, 5))
    assert closed.duplicates == (0,) and a.duplicates == {0}
    assert closed.decisions.tolist() == [1, 1, 1]  # the first answer counts, the second is late
    assert a.counters()["late"] == 2


def test_without_the_tag_a_second_pdo_is_only_late():
    sc = scene(sync_counter=0)
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(10 * MS, 0, 0x80, b"")
    a.feed(10 * MS + 1, 0, *tpdo(10, 1))
    a.feed(10 * MS + 2, 0, *tpdo(10, -1))   # could be a late answer to an earlier SYNC: not evidence
    assert not a.duplicates and a.counters()["late"] == 1


def windowed(sync_counter=64, n=3):
    sc = scene(n=n, sync_counter=sync_counter)
    return __import__("dataclasses").replace(sc, bus=__import__("dataclasses").replace(sc.bus, sync_window_us=8 * MS))


def test_an_answer_on_the_bus_before_the_next_sync_counts_however_late_it_is_handled():
    """Bus order: the master's SYNC 2 is fed when sent; node 12's answer to SYNC 1, on the bus
    at 3 ms, reaches the assembler only after it. It counts in cycle 0, then SYNC 2 opens cycle 1."""
    sc = windowed()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(0, 0, 0x80, b"\x01")
    a.feed(1 * MS, 0, *tagged(10, 1, 1))
    a.feed(2 * MS, 0, *tagged(11, -1, 1))
    assert a.feed_all(10 * MS, 0, 0x80, b"\x02") == []            # held: cycle 0's window is open
    assert a.counters()["held"] == 1 and a.events == sum(a.counts) + 1
    closed = a.feed_all(3 * MS, 0, *tagged(12, 1, 1))            # stamped 3 ms, handled after SYNC 2
    assert [c.cycle for c in closed] == [0] and closed[0].closed_by == "complete"
    assert closed[0].decisions.tolist() == [1, -1, 1]
    assert a.cycle == 1 and a.is_open and a.sync_counter == 2 and not a.held  # SYNC 2 fed after it
    assert "held" not in a.counters() and a.events == sum(a.counts)


def test_the_first_node_frame_after_the_window_closes_the_cycle_and_feeds_what_was_held():
    sc = windowed(sync_counter=0)  # untagged: by time stamps alone
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(0, 0, 0x80, b"")
    a.feed(1 * MS, 0, *tpdo(10, 1))
    a.feed(10 * MS, 0, 0x80, b"")                                  # held
    a.feed(10 * MS + 1, 0, 0x600 + 10, bytes(8))                  # an SDO request: held too
    a.feed(7 * MS, 0, 0x700 + 11, b"\x05")                         # in the window: fed at once
    closed = a.feed_all(10 * MS + 200, 0, *tpdo(11, -1))           # after the window: cycle 0 ends
    assert [c.closed_by for c in closed] == ["window"] and closed[0].close_us == 8 * MS
    assert closed[0].decisions.tolist() == [1, 0, 0]
    assert a.cycle == 1 and a.decisions.tolist() == [0, -1, 0]    # node 11's answer is cycle 1's
    assert a.counters()["sdo"] == 1 and a.counters()["heartbeat"] == 1


def test_with_no_node_frame_a_second_sync_or_the_end_of_run_releases_the_hold():
    sc = windowed()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(0, 0, 0x80, b"\x01")
    assert a.feed_all(10 * MS, 0, 0x80, b"\x02") == []
    closed = a.feed_all(20 * MS, 0, 0x80, b"\x03")                  # nodes all dead: SYNC 3 releases
    assert [(c.cycle, c.closed_by) for c in closed] == [(0, "window")]
    assert a.cycle == 1 and a.held                                 # SYNC 3 held behind cycle 1
    closed = a.feed_all(25 * MS, 0, 0x000, bytes([0x80, 0]))       # NMT pre-operational all
    assert [(c.cycle, c.closed_by) for c in closed] == [(1, "window"), (2, "nmt")]
    assert not a.held and sum(a.counts) == a.events


def test_lss_frames_are_counted_as_lss_not_as_malformed():
    sc = scene()
    a = CycleAssembler(sc)
    a.feed(0, 0, 0x7E5, bytes([0x04, 0x01, 0, 0, 0, 0, 0, 0]))   # switch state global: configuration
    a.feed(1, 0, 0x7E4, bytes([0x11, 0, 0, 0, 0, 0, 0, 0]))       # a slave's answer
    a.feed(2, 0, 0x7E5, bytes([0x04, 0x01]))                       # LSS is always 8 bytes
    assert a.counters()["lss"] == 2 and a.counters()["bad_dlc"] == 1 and a.counters()["unknown_cob_id"] == 0


def test_the_masters_heartbeat_is_counted_as_such_and_changes_no_node():
    """0x700 + [master] node_id (default 127): the master's own heartbeat, counted
    master_heartbeat (never unknown_cob_id, never a node's heartbeat); wrong length / state bad."""
    sc = scene()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    states = a.state.copy()
    heard = a.last_heard.copy()
    a.feed(1 * MS, 0, 0x77F, b"\x05")
    a.feed(2 * MS, 0, 0x77F, b"\x05\x00")                          # heartbeats are 1 byte
    a.feed(3 * MS, 0, 0x77F, b"\x06")                               # no NMT state 6
    c = a.counters()
    assert (c["master_heartbeat"], c["bad_dlc"], c["bad_value"], c["heartbeat"], c["unknown_cob_id"]) == (1, 1, 1, 0, 0)
    assert (a.state == states).all() and (a.last_heard == heard).all()
    assert sum(a.counts) == a.events == len(sc.taxels) + 1 + 3
    # another node-ID for the master; with its heartbeat off, 0x77F belongs to nobody
    import dataclasses
    from taxel_net.scene import MasterSpec
    b = CycleAssembler(dataclasses.replace(sc, master=MasterSpec(node_id=5)))
    b.feed(0, 0, 0x705, b"\x05")
    b.feed(1, 0, 0x77F, b"\x05")
    assert (b.counters()["master_heartbeat"], b.counters()["unknown_cob_id"]) == (1, 1)
    off = CycleAssembler(dataclasses.replace(sc, master=MasterSpec(heartbeat_ms=0)))
    off.feed(0, 0, 0x77F, b"\x05")
    assert (off.counters()["master_heartbeat"], off.counters()["unknown_cob_id"]) == (0, 1)


def test_a_taxel_with_the_masters_node_id_keeps_its_heartbeat():
    """A scene built in code (the loader refuses it) with a taxel at node-ID 127: 0x77F is the taxel's."""
    sc = Scene(path="<test>", name="t", bus=BusSpec(), taxels=(TaxelSpec(node_id=127, kind="R"),), fusion=FusionSpec())
    a = CycleAssembler(sc)
    a.feed(0, 0, 0x77F, b"\x7F")
    assert a.counters()["heartbeat"] == 1 and a.counters()["master_heartbeat"] == 0 and a.state[0] == 0x7F


def test_the_masters_heartbeat_is_held_like_its_sync_while_a_window_is_open():
    """Bus order: the master's heartbeat sent after SYNC 2 while cycle 0's window is open waits
    behind SYNC 2; a node's answer to SYNC 1 handled after both still counts in cycle 0."""
    sc = windowed()
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(0, 0, 0x80, b"\x01")
    a.feed(1 * MS, 0, *tagged(10, 1, 1))
    a.feed(2 * MS, 0, *tagged(11, -1, 1))
    a.feed(3 * MS, 0, 0x77F, b"\x05")                              # no hold yet: fed at once
    assert a.counters()["master_heartbeat"] == 1
    assert a.feed_all(10 * MS, 0, 0x80, b"\x02") == []             # SYNC 2 held
    assert a.feed_all(10 * MS + 5, 0, 0x77F, b"\x05") == []        # the heartbeat after it: held
    assert a.counters()["held"] == 2 and a.counters()["master_heartbeat"] == 1
    closed = a.feed_all(4 * MS, 0, *tagged(12, 1, 1))
    assert [(c.cycle, c.closed_by) for c in closed] == [(0, "complete")]
    assert closed[0].decisions.tolist() == [1, -1, 1]
    assert a.cycle == 1 and not a.held and a.counters()["master_heartbeat"] == 2
    assert sum(a.counts) == a.events


def test_a_tagged_decision_stamped_before_its_sync_is_an_old_one_and_late():
    """The tag repeats every 64 SYNCs: a decision held up behind a backlog of 64 periods carries
    the open cycle's tag. No answer is sent before its SYNC, so one stamped before it is the old
    one: late, never counted (a skin4096 run 640 ms behind counted old contacts)."""
    sc = scene(sync_counter=64)
    a = CycleAssembler(sc)
    boot_all(a, sc)
    a.feed(640 * MS, 0, 0x80, bytes([5]))                     # counter 5 again, 64 SYNCs after the first
    a.feed(640 * MS + 100, 0, *tagged(10, 1, 5))
    a.feed(640 * MS + 200, 0, *tagged(11, 1, 5))
    # node 12's answer to the SYNC with counter 5 of 640 ms earlier, reaching the assembler now
    a.feed_all(0 * MS + 300, 0, *tagged(12, 1, 5))
    assert a.counters()["late"] == 1 and not a.got1[2]
    a.feed(640 * MS + 400, 0, *tagged(12, -1, 5))            # its answer to this SYNC: counted
    closed = a.feed(650 * MS, 0, 0x80, bytes([6]))
    assert closed.cycle == 0 and closed.decisions.tolist() == [1, 1, -1] and a.counters()["tpdo1"] == 3
