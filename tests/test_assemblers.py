"""Cycle assemblers in other processes, one fuser (issue 14, "Beyond one host"): two
``fusion-center assemble`` processes (one per scene channel) feed the fuser over Zenoh on a
loopback endpoint, multicast scouting off (the messages of assembler_wire, the link of
assembler_link; tests/test_assembler_wire.py) while the fuser is the CANopen master on
udp_multicast; the merge itself (parts out of order, a missing part) as a unit."""

from __future__ import annotations

import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fusion_center.service.assemblers import (
    CycleMerger,
    GroupAssembler,
    group_layout,
)
from fusion_center.service.zenoh_config import endpoint
from fusion_center.cli import main as cli_main
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from test_node_shards import _scene_file  # noqa: E402 - the two-channel patch scene (2 x 40 taxels)
from process_helpers import wait_line, wait_ready  # noqa: E402 - bounded waits for a process's lines

GROUPS = ["239.74.163.21", "239.74.163.22"]
ASSEMBLE = "fusion-center assemble"  # the program whose ready line the tests wait for (a bounded wait)
RECONNECT_S = 120.0  # an assembler's reconnect after its fuser broke the link: seconds on a loaded host


def _parts(scene, k, counter, *, decisions=(1, -1), bootups=((), ()), emcy=((), ())):
    """Parts of both groups for cycle k, built through GroupAssembler.part from a ClosedCycle;
    ``bootups``: each group's closed cycle's (sub-scene device, t_us) pairs; ``emcy``: each
    group's (code, register, t_us) EMCYs of its first node."""
    from fusion_center.service.cycle_records import ClosedCycle, DeviceCycle, EmcyEvent

    out = {}
    for g, value, booted, emcys in zip((0, 1), decisions, bootups, emcy):
        ga = GroupAssembler(scene, [g])
        n, nd = ga.layout.sub.n, len(ga.layout.devices)
        closed = ClosedCycle(
            cycle=k, sync_us=0, close_us=1000, sync_counter=counter, closed_by="complete",
            decisions=np.full(n, value, dtype=np.int8), readings=np.full(n, np.nan),
            received=np.ones(n, dtype=bool), expected=np.ones(n, dtype=bool), missing=np.zeros(n, dtype=bool),
            held_decisions=np.full(n, value, dtype=np.int8), held_readings=np.full(n, np.nan),
            late_frames=0, bad_frames=0, states=np.full(n, 5, dtype=np.int16),
            emcy=tuple(EmcyEvent(ga.assembler.labels[0], 0, code, register, "0000000000", t_us)
                       for code, register, t_us in emcys),
            devices=DeviceCycle(np.ones(nd, dtype=bool), np.zeros(nd, dtype=bool), np.full(nd, 5, dtype=np.int16),
                                np.ones(nd, dtype=bool)), bootups=tuple(booted))
        out[ga.layout.name] = ga.part(closed)
    return out


def test_group_layout_maps_taxels_devices_and_cob_ids(tmp_path):
    from taxel_net.patches import devices

    scene = load_scene(_scene_file(tmp_path))
    lay = group_layout(scene, [1])
    assert lay.name == "1" and lay.sub.n == 40 and list(lay.taxels) == list(range(40, 80))
    full = devices(scene)
    assert [full[d].channel for d in lay.devices] == [1, 1]
    # same node-IDs and TPDO COB-IDs as the full scene's channel 1
    assert [(d.node_id, [t.cob_id for t in d.tpdos]) for d in devices(lay.sub)] == \
        [(full[d].node_id, [t.cob_id for t in full[d].tpdos]) for d in lay.devices]


def test_merge_out_of_order_and_a_missing_part(tmp_path):
    scene = load_scene(_scene_file(tmp_path))
    merger = CycleMerger(scene, part_deadline_s=0.5)
    for g in (0, 1):
        assert merger.add_group(group_layout(scene, [g])) is None
    assert merger.add_group(group_layout(scene, [0, 1])) is not None  # overlap refused
    t = 100.0
    for k in range(3):
        assert merger.opened(k + 1, 1000 * k, t) == k
    p0, p1, p2 = (_parts(scene, k, k + 1) for k in range(3))
    # out of order across groups (each group's own parts come in order over its connection):
    # group 1's cycles 0 and 1 before anything of group 0; nothing is emitted before cycle 0 is whole
    merger.add_part("1", p0["1"])
    merger.add_part("1", p1["1"])
    assert merger.emit(t) == []
    merger.add_part("0", p0["0"])
    merger.add_part("0", p1["0"])
    out = merger.emit(t)
    assert [c.cycle for c in out] == [0, 1]
    assert all(c.closed_by == "complete" and c.received.all() for c in out)
    assert (out[0].decisions[:40] == 1).all() and (out[0].decisions[40:] == -1).all()  # no mix-up of groups
    assert out[0].devices.complete.all()
    # cycle 2: group 1's part never comes -> degraded at the deadline, its taxels silent
    merger.add_part("0", p2["0"])
    assert merger.emit(t + 0.1) == []
    merger.opened(4, 3000, t + 0.1)  # cycle 3
    p3 = _parts(scene, 3, 4)
    merger.add_part("0", p3["0"])
    merger.add_part("1", p3["1"])  # a later part of group 1: its part of 2 is not coming
    out = merger.emit(t + 0.1)
    assert [c.cycle for c in out] == [2, 3]
    assert out[0].closed_by == "part_missing" and merger.info[2] == {"parts_missing": ["1"]}
    assert out[0].received[:40].all() and not out[0].received[40:].any()
    assert out[0].expected[40:].all() and not out[0].devices.complete[2:].any()
    assert out[1].closed_by == "complete"
    # a part for an evaluated cycle is counted, never mixed in; a deadline alone degrades too
    merger.add_part("1", p2["1"])
    merger.opened(5, 4000, t + 0.2)
    merger.add_part("0", _parts(scene, 4, 5)["0"])
    assert merger.emit(t + 0.3) == []
    out = merger.emit(t + 0.8)
    assert [c.cycle for c in out] == [4] and merger.info[4] == {"parts_missing": ["1"]}
    s = merger.stats
    assert (s.complete, s.degraded, s.parts_missing, s.late_parts) == (3, 2, 2, 1)


def test_a_groups_boot_ups_reach_the_merged_cycle_as_scene_devices(tmp_path):
    """A node's own boot-up (the over-range tracker forgets its flag on it) crosses the link:
    the group's device index becomes the scene's, the merge keeps every group's."""
    scene = load_scene(_scene_file(tmp_path))
    merger = CycleMerger(scene, part_deadline_s=0.5)
    for g in (0, 1):
        merger.add_group(group_layout(scene, [g]))
    merger.opened(1, 0, 100.0)
    parts = _parts(scene, 0, 1, bootups=(((0, 700),), ((1, 500),)))
    lay1 = group_layout(scene, [1])
    assert parts["1"].bootups == ((int(lay1.devices[1]), 500),) and parts["0"].bootups == ((0, 700),)
    for name, part in parts.items():
        merger.add_part(name, part)
    (closed,) = merger.emit(100.0)
    assert closed.bootups == ((0, 700), (int(lay1.devices[1]), 500)) and int(lay1.devices[1]) == 3


def test_a_late_parts_boot_up_reaches_the_next_cycle_and_clears_the_over_range_flag(tmp_path):
    """A boot-up is an event, not cycle data: group 1's part of cycle 1 comes after the merge
    closed that cycle (part_missing) - the part is counted late, never mixed in, but its boot-up
    goes into the next cycle closed with its t_us, so the node that restarted by itself is not
    flagged over range for good; an over-range EMCY after the boot-up flags it again."""
    from fusion_center.service.over_range import OverRangeTracker
    from fusion_center.service.pipeline import node_labels

    scene = load_scene(_scene_file(tmp_path))
    merger = CycleMerger(scene, part_deadline_s=0.5)
    for g in (0, 1):
        merger.add_group(group_layout(scene, [g]))
    device = int(group_layout(scene, [1]).devices[0])  # group 1's first node, as the scene's device
    label = node_labels(scene)[device]
    tracker = OverRangeTracker(node_labels(scene))
    t = 100.0
    for k in range(2):
        merger.opened(k + 1, 10_000 * k, t)
    parts = [_parts(scene, 0, 1, emcy=((), ((0x3000, 0x05, 500),))),   # group 1's node over range
             _parts(scene, 1, 2, bootups=((), ((0, 15_000),))),        # ... then it restarts by itself
             _parts(scene, 2, 3), _parts(scene, 3, 4),
             _parts(scene, 4, 5, emcy=((), ((0x3000, 0x05, 45_000),)))]
    for name in ("0", "1"):
        merger.add_part(name, parts[0][name])
    merger.add_part("0", parts[1]["0"])
    closed = merger.emit(t) + merger.emit(t + 1.0)  # cycle 1: group 1's part missing at the deadline
    merger.add_part("1", parts[1]["1"])              # ... and then it comes: late
    for k in (2, 3, 4):
        merger.opened(k + 1, 10_000 * k, t + 1.0)
        for name in ("0", "1"):
            merger.add_part(name, parts[k][name])
        closed += merger.emit(t + 1.0)
    assert [c.cycle for c in closed] == [0, 1, 2, 3, 4] and closed[1].closed_by == "part_missing"
    over = [tracker.update(c) for c in closed]
    assert over == [[label], [label], [], [], [label]]
    assert [c.bootups for c in closed] == [(), (), ((device, 15_000),), (), ()]  # once, its t_us kept
    assert merger.stats.late_parts == 1 and merger.stats.late_bootups == 1
    assert merger.emit(t + 2.0, final=True) == []
    from fusion_center.commands.run import format_summary
    from test_assembler_wire import _summary_stub

    line, = [line for line in format_summary({**_summary_stub(), "assemblers": merger.stats.as_dict()})
             if line.startswith("assemblers:")]
    assert "late parts 1 (1 boot-ups carried on), unmatched 0;" in line, line


def test_a_late_boot_up_merged_with_a_later_one_of_the_same_node_keeps_the_later(tmp_path):
    """Carried on, a late part's boot-up meets the next cycle's own boot-up of the same node: the
    later one counts (an EMCY between them came before the restart: counted, not applied)."""
    from fusion_center.service.over_range import OverRangeTracker
    from fusion_center.service.pipeline import node_labels

    scene = load_scene(_scene_file(tmp_path))
    merger = CycleMerger(scene, part_deadline_s=0.5)
    for g in (0, 1):
        merger.add_group(group_layout(scene, [g]))
    device = int(group_layout(scene, [1]).devices[0])
    tracker = OverRangeTracker(node_labels(scene))
    for k in range(2):
        merger.opened(k + 1, 10_000 * k, 100.0)
    p0, p1 = _parts(scene, 0, 1), _parts(scene, 1, 2, bootups=((), ((0, 12_000),)))
    p2 = _parts(scene, 2, 3, bootups=((), ((0, 25_000),)), emcy=((), ((0x3000, 0x05, 21_000),)))
    for name in ("0", "1"):
        merger.add_part(name, p0[name])
    merger.add_part("0", p1["0"])
    closed = merger.emit(100.0) + merger.emit(101.0)
    merger.add_part("1", p1["1"])  # late
    merger.opened(3, 20_000, 101.0)
    for name in ("0", "1"):
        merger.add_part(name, p2[name])
    closed += merger.emit(101.0)
    assert closed[2].bootups == ((device, 25_000),)
    assert [tracker.update(c) for c in closed] == [[], [], []] and sum(tracker.emcy.values()) == 1


def _two_group_merger(scene):
    from fusion_center.service.over_range import OverRangeTracker
    from fusion_center.service.pipeline import node_labels

    merger = CycleMerger(scene, part_deadline_s=0.5)
    for g in (0, 1):
        merger.add_group(group_layout(scene, [g]))
    device = int(group_layout(scene, [1]).devices[0])  # group 1's first node, as the scene's device
    return merger, OverRangeTracker(node_labels(scene)), device, node_labels(scene)[device]


def test_a_late_parts_emcy_goes_on_with_its_boot_up_so_a_node_over_range_after_its_restart_stays_flagged(tmp_path):
    """Group 1's parts of cycles 1 and 2 both come late: the first holds its node's boot-up,
    the second its EMCY 0x3000 after that restart. The node sends 0x3000 on the rising edge only,
    so the EMCY must go on with the boot-up (into the next cycle closed, bus order): the node
    stays flagged while clipped. Before, the boot-up cleared the flag and the EMCY was lost."""
    scene = load_scene(_scene_file(tmp_path))
    merger, tracker, device, label = _two_group_merger(scene)
    t = 100.0
    parts = [_parts(scene, 0, 1, emcy=((), ((0x3000, 0x05, 500),))),      # over range
             _parts(scene, 1, 2, bootups=((), ((0, 15_000),))),           # restarts by itself ...
             _parts(scene, 2, 3, emcy=((), ((0x3000, 0x05, 21_000),))),   # ... over range again after its start
             _parts(scene, 3, 4), _parts(scene, 4, 5)]
    for k in range(3):
        merger.opened(k + 1, 10_000 * k, t)
    for name in ("0", "1"):
        merger.add_part(name, parts[0][name])
    merger.add_part("0", parts[1]["0"])
    merger.add_part("0", parts[2]["0"])
    closed = merger.emit(t) + merger.emit(t + 1.0)  # cycles 1 and 2: group 1's parts missing (deadline)
    merger.add_part("1", parts[1]["1"])              # late: the boot-up
    merger.add_part("1", parts[2]["1"])              # late: the EMCY after it
    for k in (3, 4):
        merger.opened(k + 1, 10_000 * k, t + 1.0)
        for name in ("0", "1"):
            merger.add_part(name, parts[k][name])
        closed += merger.emit(t + 1.0)
    assert [c.closed_by for c in closed] == ["complete", "part_missing", "part_missing", "complete", "complete"]
    assert [tracker.update(c) for c in closed] == [[label]] * 5
    assert closed[3].bootups == ((device, 15_000),) and [e.t_us for e in closed[3].emcy] == [21_000]
    assert closed[4].emcy == () and closed[3].emcy_dropped == 0
    assert (merger.stats.late_parts, merger.stats.late_bootups, merger.stats.late_emcy) == (2, 1, 1)
    assert tracker.emcy[label] == 2
    from fusion_center.commands.run import format_summary
    from test_assembler_wire import _summary_stub

    line, = [line for line in format_summary({**_summary_stub(), "assemblers": merger.stats.as_dict()})
             if line.startswith("assemblers:")]
    assert "late parts 2 (1 boot-ups, 1 EMCYs carried on), unmatched 0;" in line, line


def test_late_parts_carry_at_most_emcy_per_cycle_emcys_the_rest_counted_dropped(tmp_path):
    """Carried EMCYs are bounded as a cycle's own (EMCY_PER_CYCLE, the earliest kept): the rest,
    and a late part's own emcy_dropped, are counted in the next cycle's emcy_dropped."""
    from fusion_center.service.cycle_records import EMCY_PER_CYCLE

    scene = load_scene(_scene_file(tmp_path))
    merger, _, _, _ = _two_group_merger(scene)
    many = tuple((0x8130, 0x11, 10_000 + i) for i in range(EMCY_PER_CYCLE - 2))
    more = tuple((0x8130, 0x11, 20_000 + i) for i in range(5))
    parts = [_parts(scene, 0, 1), _parts(scene, 1, 2, emcy=((), many)), _parts(scene, 2, 3, emcy=((), more)),
             _parts(scene, 3, 4, emcy=((), ((0x3000, 0x05, 31_000),)))]
    parts[2]["1"].emcy_dropped = 7
    for k in range(3):
        merger.opened(k + 1, 10_000 * k, 100.0)
    for name in ("0", "1"):
        merger.add_part(name, parts[0][name])
    merger.add_part("0", parts[1]["0"])
    merger.add_part("0", parts[2]["0"])
    closed = merger.emit(100.0) + merger.emit(101.0)
    merger.add_part("1", parts[1]["1"])
    merger.add_part("1", parts[2]["1"])
    merger.opened(4, 30_000, 101.0)
    for name in ("0", "1"):
        merger.add_part(name, parts[3][name])
    closed += merger.emit(101.0)
    last = closed[-1]
    assert len(last.emcy) == EMCY_PER_CYCLE
    assert [e.t_us for e in last.emcy] == [t for _, _, t in many] + [20_000, 20_001]
    # 3 of the second late part not carried + its own 7 + the cycle's own EMCY (the latest) beyond the bound
    assert last.emcy_dropped == 3 + 7 + 1
    assert merger.stats.late_emcy == EMCY_PER_CYCLE


def test_carried_emcys_are_kept_first_over_the_bound_whatever_the_groups_stamps(tmp_path):
    """Each assembler process stamps t_us from its own first frame: stamps of different groups are
    not comparable. Group 1's late part carries 10 EMCYs stamped 9 s into its process, the next
    cycle's own part of group 0 (a process started lately) 10 stamped 1 ms: over EMCY_PER_CYCLE,
    the carried EMCYs (bus order: before every EMCY of the cycle's parts) are kept whole and the
    cycle's own cut, and ``late_emcy`` counts what landed in the record. Before, the merge sorted
    by t_us across groups: 4 carried EMCYs dropped, yet all 10 counted as carried on."""
    from fusion_center.service.cycle_records import EMCY_PER_CYCLE

    scene = load_scene(_scene_file(tmp_path))
    merger, *_ = _two_group_merger(scene)
    late = tuple((0x8130, 0x11, 9_000_000 + i) for i in range(10))
    own = tuple((0x8130, 0x11, 1_000 + i) for i in range(10))
    parts = [_parts(scene, 0, 1), _parts(scene, 1, 2, emcy=((), late)), _parts(scene, 2, 3, emcy=(own, ()))]
    for k in range(2):
        merger.opened(k + 1, 10_000 * k, 100.0)
    for name in ("0", "1"):
        merger.add_part(name, parts[0][name])
    merger.add_part("0", parts[1]["0"])
    closed = merger.emit(100.0) + merger.emit(101.0)   # cycle 1 closes without group 1
    merger.add_part("1", parts[1]["1"])                 # late: its 10 EMCYs go on
    merger.opened(3, 20_000, 101.0)
    for name in ("0", "1"):
        merger.add_part(name, parts[2][name])
    closed += merger.emit(101.0)
    last = closed[-1]
    assert [e.t_us for e in last.emcy] == [t for _, _, t in late] + [t for _, _, t in own[:EMCY_PER_CYCLE - 10]]
    assert last.emcy_dropped == 10 - (EMCY_PER_CYCLE - 10)
    assert merger.stats.late_emcy == 10


def test_a_duplicate_part_after_its_cycle_closed_does_not_reapply_its_boot_up(tmp_path):
    """The same part again (a duplicate, a replayed signed message) after its cycle closed: counted
    late, its boot-up NOT carried on - it would clear the over-range flag an EMCY 0x3000 after that
    boot-up set. Only a late part newer than the group's last part carries its events."""
    scene = load_scene(_scene_file(tmp_path))
    merger, tracker, device, label = _two_group_merger(scene)
    parts = [_parts(scene, 0, 1, bootups=((), ((0, 500),))),              # the node restarts ...
             _parts(scene, 1, 2, emcy=((), ((0x3000, 0x05, 12_000),))),  # ... and is over range after it
             _parts(scene, 2, 3), _parts(scene, 3, 4)]
    closed = []
    for k in range(4):
        merger.opened(k + 1, 10_000 * k, 100.0)
        for name in ("0", "1"):
            merger.add_part(name, parts[k][name])
        if k == 2:
            merger.add_part("1", parts[0]["1"])  # the cycle-0 part again
            merger.add_part("1", parts[1]["1"])  # the cycle-1 part again (its EMCY not doubled either)
        closed += merger.emit(100.0)
    assert [c.bootups for c in closed] == [((device, 500),), (), (), ()]
    assert [len(c.emcy) for c in closed] == [0, 1, 0, 0]
    assert [tracker.update(c) for c in closed] == [[], [label], [label], [label]]
    assert (merger.stats.late_parts, merger.stats.late_bootups, merger.stats.late_emcy) == (2, 0, 0)


class _Publisher:
    def __init__(self, fail: bool = False):
        self.fail, self.sent = fail, []

    def put(self, data, attachment=None):
        if self.fail:
            raise RuntimeError("session closed")
        self.sent.append(data)


def test_an_assembler_keeps_the_boot_ups_of_a_part_it_could_not_send_for_the_next_part(tmp_path):
    """Disconnected (no link) or a failed put: the part is counted not sent, its boot-ups go
    with the next part that is sent (the latest per device), as the fuser decodes it."""
    from fusion_center.service.assembler_link import mac_key
    from fusion_center.service.assembler_process import AssemblerProcess, _Link
    from fusion_center.service.assembler_wire import PartCodec

    scene = load_scene(_scene_file(tmp_path))
    process = AssemblerProcess(scene, [1], fuser=("127.0.0.1", 9), interface="virtual", authkey=b"k" * 32)
    layout = process.layout
    d0, d1 = (int(d) for d in layout.devices)
    parts = [_parts(scene, k, k + 1, bootups=((), booted))["1"]
             for k, booted in enumerate((((0, 1_000),), ((1, 12_000),), ((0, 21_000),), (), ()))]
    process._outbox.append(parts[0])
    process._send()                                  # no link: not sent
    link = _Link(process, "test", mac_key(b"k" * 32))
    link.publisher = _Publisher(fail=True)
    process.link = link
    process._outbox.append(parts[1])
    process._send()                                  # the put fails: not sent (the link given up)
    assert process.parts_unsent == 2 and process.link is None
    link.publisher = _Publisher()
    process.link = link
    process._outbox.extend(parts[2:])
    process._send()
    codec = PartCodec(scene, layout)
    sent = [codec.decode(data) for data in link.publisher.sent]
    assert [p.bootups for p in sent] == [((d0, 21_000), (d1, 12_000)), (), ()]
    assert process.parts_sent == 3 and process.parts_unsent == 2


def test_an_assembler_sends_the_emcys_of_parts_it_could_not_send_with_its_next_part(tmp_path):
    """A part with a node's boot-up and the next with its EMCY 0x3000 after it, both not sent
    (disconnected): the next part sent carries both, the EMCYs ahead of its own in bus order, at
    most EMCY_PER_CYCLE (the rest and the parts' own emcy_dropped counted), so the fuser keeps the
    node flagged. Before, the boot-up went on and the EMCY was lost: the node was unflagged."""
    from fusion_center.service.assembler_link import mac_key
    from fusion_center.service.assembler_process import AssemblerProcess, _Link
    from fusion_center.service.assembler_wire import PartCodec
    from fusion_center.service.cycle_records import EMCY_PER_CYCLE

    scene = load_scene(_scene_file(tmp_path))
    process = AssemblerProcess(scene, [1], fuser=("127.0.0.1", 9), interface="virtual", authkey=b"k" * 32)
    layout = process.layout
    d0 = int(layout.devices[0])
    filler = tuple((0x8130, 0x11, 30_000 + i) for i in range(EMCY_PER_CYCLE))
    parts = [_parts(scene, 0, 1, bootups=((), ((0, 1_000),)))["1"],
             _parts(scene, 1, 2, emcy=((), ((0x3000, 0x05, 12_000),)))["1"],
             _parts(scene, 2, 3)["1"],
             _parts(scene, 3, 4, emcy=((), filler[:EMCY_PER_CYCLE - 1]))["1"],
             _parts(scene, 4, 5, emcy=((), filler[EMCY_PER_CYCLE - 1:] + ((0x3000, 0x05, 41_000),)))["1"],
             _parts(scene, 5, 6, emcy=((), ((0x0000, 0x00, 51_000),)))["1"]]
    parts[4].emcy_dropped = 2
    process._outbox.extend(parts[:2])
    process._send()                                   # disconnected: neither sent
    link = _Link(process, "test", mac_key(b"k" * 32))
    link.publisher = _Publisher()
    process.link = link
    process._outbox.append(parts[2])
    process._send()
    codec = PartCodec(scene, layout)
    sent = codec.decode(link.publisher.sent[0])
    assert sent.bootups == ((d0, 1_000),) and [(e.code, e.t_us) for e in sent.emcy] == [(0x3000, 12_000)]
    assert sent.emcy_dropped == 0
    # over many parts not sent the kept EMCYs stay bounded: 15 + 2 (the 16th kept) and the part's own
    process.link = None
    process._outbox.extend(parts[3:5])
    process._send()
    assert len(process._unsent_emcy) == EMCY_PER_CYCLE and process._unsent_emcy_dropped == 1 + 2
    process.link = link
    process._outbox.append(parts[5])
    process._send()
    sent = codec.decode(link.publisher.sent[1])
    assert [e.t_us for e in sent.emcy] == [t for _, _, t in filler]  # the earliest kept: the wire's bound
    assert sent.emcy_dropped == 1 + 2 + 1                             # the over-range one, 2 of its part, the reset
    assert process.parts_sent == 2 and process.parts_unsent == 4


def test_counter_maps_a_part_to_its_sync_and_numbers_jump_over_lost_syncs(tmp_path):
    scene = load_scene(_scene_file(tmp_path))
    merger = CycleMerger(scene, part_deadline_s=0.5)
    merger.add_group(group_layout(scene, [0]))
    for k in range(70):  # counter wraps at 64
        merger.opened(k % 64 + 1, k, 0.0)
    part = _parts(scene, 0, (66 % 64) + 1)["0"]
    with merger.lock:
        assert merger.cycle_of(part) == 66
    ga = GroupAssembler(scene, [0])
    from fusion_center.service.cycle_records import ClosedCycle

    def closed(c, counter):
        n = 40
        return ClosedCycle(cycle=c, sync_us=0, close_us=0, sync_counter=counter, closed_by="sync",
                           decisions=np.zeros(n, dtype=np.int8), readings=np.full(n, np.nan),
                           received=np.zeros(n, dtype=bool), expected=np.zeros(n, dtype=bool),
                           missing=np.zeros(n, dtype=bool), held_decisions=np.zeros(n, dtype=np.int8),
                           held_readings=np.full(n, np.nan), late_frames=0, bad_frames=0, emcy=())
    assert [ga.number(closed(c, cnt)) for c, cnt in ((0, 1), (1, 2), (2, 5), (3, 64), (4, 2))] == [0, 1, 4, 63, 65]


def test_bad_values_exit_2_naming_the_flag(tmp_path, capsys):
    path = _scene_file(tmp_path)
    with pytest.raises(UsageError, match="--fuser 'tcp/nohost'"):
        endpoint("nohost", "--fuser")
    assert endpoint("127.0.0.1:7447", "--fuser") == "tcp/127.0.0.1:7447"
    assert endpoint("tls/[::1]:7447", "--fuser") == "tls/[::1]:7447"
    cases = [
        (["assemble", "--scene", str(path), "-i", "virtual", "--serve", "0", "--fuser", "127.0.0.1:0"], "--fuser"),
        (["assemble", "--scene", str(path), "-i", "virtual", "--serve", "2", "--fuser", "127.0.0.1:47000"],
         "--serve '2'"),
        (["assemble", "--scene", str(path), "-i", "virtual", "--serve", "x", "--fuser", "127.0.0.1:47000"],
         "--serve 'x'"),
        (["assemble", "--scene", str(path), "-i", "virtual", "--serve", "0", "--fuser", "10.1.2.3:47000"],
         "FUSION_CENTER_AUTHKEY"),
        (["assemble", "--scene", str(path), "-i", "virtual", "--serve", "0", "--fuser", "tls/10.1.2.3:47000"],
         "FUSION_CENTER_AUTHKEY"),
        (["assemble", "--scene", str(path), "-i", "virtual", "--serve", "0", "--fuser", "127.0.0.1:47000",
          "--zenoh-config", str(tmp_path / "nosuch.json5")], "nosuch.json5"),
        (["run", "--scene", str(path), "-i", "virtual", "--assemblers", "127.0.0.1:99999"], "--assemblers"),
        (["run", "--scene", str(path), "-i", "virtual", "--assemblers", "udp/127.0.0.1:x"], "--assemblers"),
        (["assemble", "--scene", str(path), "-i", "virtual", "--serve", "0", "--fuser", "127.0.0.1:47000",
          "--reconnect-timeout", "0"], "--reconnect-timeout 0.0"),
    ]
    for argv, needle in cases:
        assert cli_main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and needle in err, err


def _udp_rig(tmp_path):
    """The two-group scene's twins on udp_multicast (skip where multicast does not work):
    (scene, its file, rig, bus kwargs, bus port, a fuser port); bench/ importable (check_records)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from test_service_multiprocess import multicast_port

    from node_sim.rig import Rig

    port = multicast_port()
    path = _scene_file(tmp_path)
    scene = load_scene(path)
    bus = {"port": port, "hop_limit": 0}
    rig = Rig(scene, interface="udp_multicast", channel=GROUPS, bus_kwargs=bus)
    return scene, path, rig, bus, port, random.randint(40000, 60000)


def _fuser(scene, bus, fuser_port, assembler_wait_s=20.0):
    """The fuser of the scene's channels on udp_multicast, listening on ``fuser_port``."""
    from fusion_center.service.assemblers import AssembledFusionService

    return AssembledFusionService(scene, listen=("127.0.0.1", fuser_port), interface="udp_multicast",
                                  channels=GROUPS, bus_kwargs=bus, assembler_wait_s=assembler_wait_s)


def test_two_assembler_processes_and_a_fuser_on_udp_multicast(tmp_path):
    scene, path, rig, bus, port, fuser_port = _udp_rig(tmp_path)
    from skin_scale import check_records
    service = _fuser(scene, bus, fuser_port)
    procs = []
    t0 = time.monotonic()
    try:
        rig.start()
        service.open()
        for serve in ("0", "1"):
            procs.append(subprocess.Popen(
                [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())",
                 "assemble", "--scene", str(path), "-i", "udp_multicast", "-c", ",".join(GROUPS),
                 "--bus-kwargs", f"port={port}", "hop_limit=0", "--serve", serve,
                 "--fuser", f"127.0.0.1:{fuser_port}"],
                cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        for proc, group in zip(procs, GROUPS):
            line = wait_ready(proc, name=ASSEMBLE)
            assert group in line and "40 taxels" in line, line
        service.boot(5.0)
        assert not service.summary().missing_at_boot
        service.run(60)
    finally:
        service.close()
        rig.stop()
        outs = [_finish(proc, timeout=10) for proc in procs]  # the fuser's bye ends them (else killed)
    elapsed = time.monotonic() - t0
    records = service.records
    figures = check_records(scene, records)
    stats = service.merger.stats
    print(figures, stats.as_dict(), f"{elapsed:.1f} s", service.summary().latency_percentile(50),
          service.summary().latency_percentile(99))
    for r in records:
        if r["closed_by"] != "complete":
            print({k: r.get(k) for k in ("cycle", "closed_by", "n_received", "silent_nodes", "missing_nodes",
                                         "parts_missing", "closed_after_ms", "nodes_by_state", "late_frames")})
    assert [rc for rc, _, _ in outs] == [0, 0], outs
    assert all("60 cycles sent" in out for _, out, _ in outs), outs
    assert [r["cycle"] for r in records] == list(range(60))
    assert figures["misattributed"] == 0
    # every process sent a part of every cycle, each matched to its SYNC
    assert stats.by_group == {"0": 60, "1": 60} and stats.unmatched_parts == 0
    assert stats.complete + stats.degraded == 60
    # 60/60 complete on an idle host (and at load 6.6 on the 2 cores); how many cycles are in
    # time depends on the host (a run beside the full suite lost a few: degraded, flagged, never
    # misattributed), so only what holds on any host is asserted: some cycle merged complete, and
    # every complete one holds both groups' 80 taxels
    complete = [r for r in records if r["closed_by"] == "complete"]
    assert len(complete) > 0, figures
    # complete: every group's part, and every taxel of every node expected in that cycle (a node
    # still pre-operational at the start is not expected: it is listed in nodes_by_state)
    from fusion_center.service.pipeline import node_labels
    from taxel_net.patches import devices

    size = {label: len(d.taxels) for label, d in zip(node_labels(scene), devices(scene))}

    def heard(r):
        return 80 - sum(size[label] for labels in r["nodes_by_state"].values() for label in labels)

    wrong = [{k: r.get(k) for k in ("cycle", "n_received", "parts_missing", "nodes_by_state")}
             for r in complete if r["parts_missing"] != [] or r["n_received"] != heard(r)]
    assert not wrong, wrong


# ---------------------------------------------------------------------------- reconnects

def _assemble(path, serve, fuser_port, port=None, *extra, interface="udp_multicast", channels=None):
    """A `fusion-center assemble` process (stdout/stderr piped)."""
    channels = channels if channels is not None else GROUPS
    bus = ["--bus-kwargs", f"port={port}", "hop_limit=0"] if port is not None else []
    return subprocess.Popen(
        [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())",
         "assemble", "--scene", str(path), "-i", interface, "-c", ",".join(channels), *bus, "--serve", serve,
         "--fuser", f"127.0.0.1:{fuser_port}", *extra],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(proc, timeout=30):
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, out, err


def test_merger_takes_a_group_back_and_refuses_a_second_claim(tmp_path):
    scene = load_scene(_scene_file(tmp_path))
    merger = CycleMerger(scene, part_deadline_s=0.5)
    for g in (0, 1):
        assert merger.add_group(group_layout(scene, [g])) is None
    t = 100.0
    merger.opened(1, 0, t)
    p = _parts(scene, 0, 1)
    merger.add_part("0", p["0"])
    merger.add_part("1", p["1"])
    merger.remove_group("1")  # group 1's connection broke
    why = merger.add_group(group_layout(scene, [0]))  # a second assembler for the connected group 0
    assert why is not None and "already served" in why and "group 0" in why
    for k in (1, 2):
        merger.opened(k + 1, 1000 * k, t)
        merger.add_part("0", _parts(scene, k, k + 1)["0"])
    out = merger.emit(t)  # group 1 gone: its cycles are decided at once, degraded naming it
    assert [(c.cycle, c.closed_by) for c in out] == [(0, "complete"), (1, "part_missing"), (2, "part_missing")]
    assert merger.info[1] == merger.info[2] == {"parts_missing": ["1"]}
    assert merger.add_group(group_layout(scene, [1])) is None  # back: the same group
    assert merger.stats.reconnects == {"1": 1}
    assert merger.add_group(group_layout(scene, [1])) is not None  # ... and now connected: a second claim
    merger.opened(4, 3000, t)
    merger.add_part("0", _parts(scene, 3, 4)["0"])
    assert merger.emit(t) == []  # waits for group 1 again
    merger.add_part("1", _parts(scene, 3, 4)["1"])
    out = merger.emit(t)
    assert [(c.cycle, c.closed_by) for c in out] == [(3, "complete")]
    assert (out[0].decisions[:40] == 1).all() and (out[0].decisions[40:] == -1).all()
    assert merger.stats.as_dict()["reconnects"] == {"1": 1}
    from fusion_center.commands.run import _reconnects  # the summary line's field

    assert _reconnects(merger.stats.as_dict()) == "1 (1 1)" and _reconnects({"reconnects": {}}) == "0"
    merger.remove_group("0")
    merger.remove_group("1")
    why = merger.add_group(group_layout(scene, [0, 1]))  # another grouping of this run's channels
    assert why is not None and "--serve 0" in why


def zenoh_peer(*, connect: int | None = None, listen: int | None = None):
    """A Zenoh peer session on loopback, multicast scouting off: connected to the port
    ``connect`` or listening on ``listen`` (nowhere else)."""
    import json

    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{listen}"] if listen else []))
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{connect}"] if connect else []))
    return zenoh.open(config)


class StandInFuser:
    """A stand-in fuser on loopback ``port`` (a Zenoh session of this process): its hello
    queryable answers each hello with the next of :attr:`answers` (signed with ``key``; none
    queued: no answer); ``("new run", message)`` declares a new liveliness token first."""

    def __init__(self, scene, key: bytes, port: int, *, sign: bool = True):
        import queue

        from fusion_center.service import assembler_link as link

        self.link = link
        self.session = zenoh_peer(listen=port)
        self.prefix = link.prefix(scene.name)
        self.mac_key = link.mac_key(key)
        self.sign = sign
        self.answers = queue.Queue()
        self.hellos = []  # (link id, hello payload)
        self.run = link.new_id()
        self.token = self.session.liveliness().declare_token(link.fuser_key(self.prefix, self.run))
        self.queryable = self.session.declare_queryable(link.hello_key(self.prefix), self._on_hello)

    def _on_hello(self, query):
        import queue

        link = self.link
        ident = link.split_id(query.attachment.to_bytes())
        self.hellos.append((ident[0], query.payload.to_bytes()))
        try:
            answer = self.answers.get_nowait()
        except queue.Empty:
            return
        if isinstance(answer, tuple):
            self.run = link.new_id()
            self.token = self.session.liveliness().declare_token(link.fuser_key(self.prefix, self.run))
            answer = answer[1]
        key = link.hello_key(self.prefix)
        tag = link.mac(self.mac_key, key, answer, ident[1] + self.run.encode()) if self.sign else bytes(32)
        query.reply(key, answer, attachment=self.run.encode() + tag)

    def tell(self, link_id: str, message: bytes, *, signed: bool = True) -> int:
        """A message to the assembler of ``link_id`` as the fuser sends it (a query): the
        number of answers (1 once it took it)."""
        key = self.link.to_link_key(self.prefix, link_id)
        tag = self.link.mac(self.mac_key, key, message) if signed else bytes(32)
        return sum(reply.ok is not None for reply in self.session.get(key, payload=message, attachment=tag,
                                                                       timeout=10))

    def crash(self) -> None:
        """Gone without a bye, as the assemblers see it (its liveliness token gone)."""
        self.token.undeclare()

    def close(self) -> None:
        self.session.close()


def test_assembler_reconnects_retries_a_refusal_and_gives_up_after_reconnect_timeout(tmp_path):
    """A stand-in fuser: it goes away without bye, refuses the first try to come back, takes the
    second; then it is gone for good: exit 1, one line."""
    from fusion_center.service.assembler_parts import remove_key_file, write_key_file
    from fusion_center.service.assembler_wire import decode_hello, encode_refused, encode_welcome

    path = _scene_file(tmp_path)
    scene = load_scene(path)
    port = random.randint(40000, 60000)
    key, key_path = write_key_file(port)  # as `run --assemblers` on loopback: this run's key
    fuser = StandInFuser(scene, key, port)
    fuser.answers.put(encode_welcome("1"))
    proc = _assemble(path, "1", port, None, "--reconnect-timeout", "1", interface="virtual",
                     channels=["rc-a", "rc-b"])
    try:
        wait_ready(proc, name=ASSEMBLE)
        fuser.answers.put(encode_refused("scene channel(s) [1] are already served by another assembler"))
        fuser.answers.put(("new run", encode_welcome("1")))
        fuser.crash()  # no bye: the link broke
        lines = wait_line(proc, proc.stderr, "reconnected to the fuser", RECONNECT_S,
                          f"{ASSEMBLE} did not say it reconnected")
        hellos = [decode_hello(payload) for _, payload in fuser.hellos]
        assert [h["channels"] for h in hellos] == [[1], [1], [1]]
        assert len({h["pid"] for h in hellos}) == 1  # the same process came back
        assert len({link_id for link_id, _ in fuser.hellos}) == 3  # a new link each time
    finally:
        fuser.close()  # nobody there any more
        remove_key_file(key_path, key)
    rc, out, err = _finish(proc, timeout=120)
    err = "".join(lines) + err
    assert rc == 1, (rc, out, err)
    assert "1 reconnects" in out, out
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"fusion-center assemble: the fuser tcp/127.0.0.1:{port} went away and was not back "
                           "within 1 s (last try: "), err
    assert "reconnected to the fuser" in err and "broke: reconnecting" in err, err


def test_assemblers_come_back_during_a_run_and_a_second_claim_is_refused(tmp_path):
    """The fuser breaks group 1's connection: the same process reconnects; group 0's process is
    killed and a new one started: it is taken back; a second `--serve 1` while group 1 is
    connected is refused (exit 2). Parts merge again after each comeback, never misattributed."""
    scene, path, rig, bus, port, fuser_port = _udp_rig(tmp_path)
    from skin_scale import check_records
    service = _fuser(scene, bus, fuser_port)
    procs = {}
    at = {}  # event -> the cycle whose before_sync hook saw it
    reconnects = service.merger.stats.reconnects

    def wait_for(condition):  # holds the SYNCs until it holds (a safety limit, not a timing claim)
        end = time.monotonic() + 120
        while not condition() and time.monotonic() < end:
            time.sleep(0.01)

    def hook(k):  # runs before SYNC k goes out
        if k == 10:
            at["drop"] = k
            assert service.drop_assembler("1")
        if "drop" in at and "back1" not in at:
            if k == 40:
                wait_for(lambda: reconnects.get("1"))
            if reconnects.get("1"):
                at["back1"] = k
                procs["dup"] = _assemble(path, "1", fuser_port, port)  # group 1 is connected: refused
        if k == 70:
            at["kill"] = k
            procs["0"].kill()
        if "kill" in at and "gone0" not in at:
            if k == 100:
                wait_for(lambda: "0" in service.merger.gone)
            if "0" in service.merger.gone:
                at["gone0"] = k  # SYNC k goes out while no assembler serves group 0
        elif "gone0" in at and "restart" not in at:
            at["restart"] = k
            procs["0 again"] = _assemble(path, "0", fuser_port, port)
        if "restart" in at and "back0" not in at:
            if k == 140:
                wait_for(lambda: reconnects.get("0"))
            if reconnects.get("0"):
                at["back0"] = k

    cycles = 180
    try:
        rig.start()
        service.open()
        for serve in ("0", "1"):
            procs[serve] = _assemble(path, serve, fuser_port, port)
        for serve in ("0", "1"):
            wait_ready(procs[serve], name=ASSEMBLE)
        service.boot(5.0)
        service.run(cycles, before_sync=hook, timeout_s=600)
    finally:
        service.close()
        rig.stop()
        outs = {name: _finish(proc) for name, proc in procs.items()}
    records = service.records
    stats = service.merger.stats
    figures = check_records(scene, records)
    print(at, figures, stats.as_dict())
    for name, (rc, out, err) in outs.items():
        print(name, rc, out.strip().splitlines()[-1:], err.strip().splitlines()[-3:])
    assert set(at) == {"drop", "back1", "kill", "gone0", "restart", "back0"}, at
    assert [r["cycle"] for r in records] == list(range(cycles))
    assert figures["misattributed"] == 0
    assert stats.reconnects == {"1": 1, "0": 1} and stats.unmatched_parts == 0
    # the processes: group 1's came back by itself, group 0's second one was taken back, the
    # second claim of group 1 was refused with one line
    rc, out, err = outs["1"]
    assert rc == 0 and "1 reconnects" in out and "reconnected to the fuser" in err, (rc, out, err)
    assert outs["0"][0] == -9
    rc, out, err = outs["0 again"]
    assert rc == 0 and "ready" in out, (rc, out, err)
    rc, out, err = outs["dup"]
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "refused" in err and "already served" in err, err
    by_cycle = {r["cycle"]: r for r in records}
    # no part of group 0 for the SYNC sent while no process served it: degraded, naming it
    assert "0" in by_cycle[at["gone0"]]["parts_missing"], by_cycle[at["gone0"]]
    assert by_cycle[at["gone0"]]["closed_by"] == "part_missing"
    # every cycle group 1's assembler closed while disconnected (not sent) is degraded naming it
    unsent = int(out_1.split(" not sent")[0].rsplit(", ", 1)[-1]) if (out_1 := outs["1"][1]) else 0
    assert sum("1" in r["parts_missing"] for r in records) >= unsent
    # the parts merge again after each comeback: complete records, holding both groups' taxels
    for since in (at["back1"], at["back0"]):
        assert any(r["closed_by"] == "complete" for r in records[since + 1:]), since
    assert all(r["parts_missing"] == [] and r["n_received"] > 0 for r in records if r["closed_by"] == "complete")


def test_a_fuser_killed_and_started_again_gets_its_assemblers_back(tmp_path):
    """`fusion-center run --assemblers` killed (SIGKILL: no bye) mid-run: the assemblers keep
    going and reconnect to the next fuser on the same address, whose run merges their parts."""
    scene, path, rig, bus, port, fuser_port = _udp_rig(tmp_path)
    from skin_scale import check_records
    jsonl = tmp_path / "first.jsonl"
    procs = []
    service = first = None
    try:
        rig.start()
        first = subprocess.Popen(
            [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())",
             "run", "--scene", str(path), "-i", "udp_multicast", "-c", ",".join(GROUPS), "--bus-kwargs",
             f"port={port}", "hop_limit=0", "--assemblers", f"127.0.0.1:{fuser_port}", "--cycles", "100000",
             "--no-live", "--json-lines", str(jsonl)],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs = [_assemble(path, serve, fuser_port, port) for serve in ("0", "1")]
        for proc in procs:
            wait_ready(proc, name=ASSEMBLE)
        end = time.monotonic() + 120  # a safety limit: the first fuser writes records
        while time.monotonic() < end and first.poll() is None and \
                (not jsonl.exists() or jsonl.read_text().count("\n") < 10):
            time.sleep(0.05)
        assert first.poll() is None, first.communicate()
        first.kill()  # no bye
        first.communicate()
        service = _fuser(scene, bus, fuser_port, assembler_wait_s=60.0)
        service.open()
        service.boot(5.0)
        service.run(40, timeout_s=600)
    finally:
        if service is not None:
            service.close()
        rig.stop()
        if first is not None and first.poll() is None:  # the test failed before killing it
            first.kill()
            first.communicate()
        outs = [_finish(proc) for proc in procs]
    records = service.records
    figures = check_records(scene, records)
    print(figures, service.merger.stats.as_dict(), [(rc, out.strip().splitlines()[-1:]) for rc, out, _ in outs])
    for rc, out, err in outs:  # the second fuser's bye ends them
        assert rc == 0 and "1 reconnects" in out and "reconnected to the fuser" in err, (rc, out, err)
    assert service.merger.stats.reconnects == {}  # new to this fuser: a first connection, not a reconnect
    assert [r["cycle"] for r in records] == list(range(40)) and figures["misattributed"] == 0
    assert any(r["closed_by"] == "complete" for r in records)
    assert all(r["parts_missing"] == [] for r in records if r["closed_by"] == "complete")


def test_without_a_sync_counter_only_an_assembler_that_heard_the_reset_comes_back(tmp_path):
    from fusion_center.service.assembler_wire import decode_hello, encode_hello
    from fusion_center.service.assemblers import AssembledFusionService, scene_fingerprint

    path = _scene_file(tmp_path)
    path.write_text(path.read_text().replace("sync_counter = 64", "sync_counter = 0"))
    scene = load_scene(path)
    service = AssembledFusionService(scene, listen=("127.0.0.1", 47999), interface="virtual",
                                     channels=["nc-a", "nc-b"])
    hello = decode_hello(encode_hello(scene_fingerprint(scene), [1], "host", 1, False))
    assert service._check_hello(hello) is None  # before the run's SYNCs: numbered from the reset to come
    service.merger.opened(None, 0, 0.0)
    why = service._check_hello(hello)  # a process started mid-run numbers from its own first SYNC
    assert why is not None and "no SYNC counter" in why
    assert service._check_hello({**hello, "numbered_from_reset": True}) is None  # the same process, back
    ga = GroupAssembler(scene, [1])
    assert not ga.heard_reset
    ga.feed(0, 0, 0x000, bytes([0x82, 0]))  # the master's broadcast reset communication
    assert ga.heard_reset


def test_the_link_sessions_are_loopback_unless_configured(tmp_path, monkeypatch):
    """The fuser's link session listens on --assemblers only, an assembler's nowhere (it connects
    to --fuser), multicast scouting off in both; a user's Zenoh file may open them up (its own
    scouting setting is kept), and a file Zenoh cannot read is one line naming it."""
    import json

    from fusion_center.service.assembler_link import assembler_config, fuser_config

    monkeypatch.delenv("FUSION_CENTER_ZENOH_CONFIG", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "nothing-here"))
    config, _ = fuser_config("tcp/127.0.0.1:47400", None)
    assert json.loads(config.get_json("listen/endpoints")) == ["tcp/127.0.0.1:47400"]
    assert json.loads(config.get_json("connect/endpoints")) == []
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    config, _ = assembler_config("tcp/127.0.0.1:47400", None)
    assert json.loads(config.get_json("listen/endpoints")) == []
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:47400"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    user = tmp_path / "zenoh.json5"
    user.write_text('{ scouting: { multicast: { enabled: true } }, connect: { endpoints: ["tcp/127.0.0.1:7999"] } }')
    config, _ = assembler_config("tcp/127.0.0.1:47400", str(user))
    assert json.loads(config.get_json("scouting/multicast/enabled")) is True
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:47400", "tcp/127.0.0.1:7999"]
    user.write_text("{ listen: { endpoints: 5 } }")
    with pytest.raises(UsageError) as info:
        fuser_config("tcp/127.0.0.1:47400", str(user))
    assert str(user) in str(info.value) and "\n" not in str(info.value)


def test_a_one_taxel_node_scenes_merged_cycle_with_two_boot_ups_keeps_no_device_view(tmp_path):
    """A one-taxel-node scene (no patch nodes: a merged cycle's ``devices`` is None) whose part
    brings two nodes' boot-ups: the merge keeps both and ``devices`` stays None - the boot-ups'
    merge named its loop variable like the merge's device view and left a node index there
    (the fuser's pipeline then failed the cycle: "'int' object has no attribute 'missing'",
    tests/test_grip_assemblers.py's first record)."""
    from fusion_center.service.cycle_records import ClosedCycle

    scene = load_scene(ROOT / "tests" / "data" / "grasp_light.toml")
    ga = GroupAssembler(scene, [0])
    n = ga.layout.sub.n
    closed = ClosedCycle(
        cycle=0, sync_us=0, close_us=1000, sync_counter=1, closed_by="complete",
        decisions=np.ones(n, dtype=np.int8), readings=np.full(n, np.nan), received=np.ones(n, dtype=bool),
        expected=np.ones(n, dtype=bool), missing=np.zeros(n, dtype=bool), held_decisions=np.ones(n, dtype=np.int8),
        held_readings=np.full(n, np.nan), late_frames=0, bad_frames=0, states=np.full(n, 5, dtype=np.int16),
        emcy=(), bootups=((0, 100), (1, 200)))
    merger = CycleMerger(scene, part_deadline_s=0.5)
    merger.add_group(group_layout(scene, [0]))
    merger.opened(1, 0, 100.0)
    merger.add_part(ga.layout.name, ga.part(closed))
    (merged,) = merger.emit(100.0)
    assert merged.devices is None and merged.bootups == ((0, 100), (1, 200)), merged.devices
