"""The common frames of a receive turn on one-taxel scenes fed in one loop
(fusion_center.service.node_frames) against feeding every frame on its own
(``EventStream._feed_locked``, the stream with ``common`` None): random turns of TPDO1s (tagged
and not) and TPDO2s - lost, late, repeated, stale, cut, altered, stamped before their SYNC or
after the window, NaN readings - mixed with SYNCs, heartbeats, EMCY, SDO, NMT, flagged and
unknown frames, odd time stamps and frames that raise, give the same closed cycles in the same
order, the same counters and the same assembler state."""

import dataclasses
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_common_frames import feed, message, turns  # noqa: E402

from fusion_center.service.cycle_records import FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE  # noqa: E402
from fusion_center.service.cycles import CycleAssembler  # noqa: E402
from fusion_center.service.node_frames import NodeFrames  # noqa: E402
from fusion_center.service.stream import EventStream  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402

MS = 1000  # µs
CLOSED_ARRAYS = ("decisions", "readings", "received", "expected", "missing", "held_decisions", "held_readings",
                 "states")
CLOSED_FIELDS = ("cycle", "sync_us", "close_us", "sync_counter", "closed_by", "late_frames", "bad_frames",
                 "duplicates", "emcy_dropped")


def one_taxel_scene(name: str, window_us: int):
    scene = load_scene(name)
    return dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, sync_window_us=window_us))


def answer(scene, node_id: int, counter: int | None, u: int, reading: float):
    """The node's primary TPDO of a cycle: (cob, data)."""
    if scene.bus.mode == "raw":
        return 0x280 + node_id, struct.pack("<f", reading)
    if scene.bus.cycle_tag:
        return 0x180 + node_id, bytes([((counter & 63) << 2) | (0b01 if u > 0 else 0b11)])
    return 0x180 + node_id, bytes([1 if u > 0 else 0xFF])


def random_stream(scene, rng, cycles):
    """(t, channel, cob, data, flags): boot-ups and NMT start, then per cycle a SYNC and the nodes'
    answers - some dropped, repeated, delayed into the next cycle, stamped before the SYNC or late,
    cut, with a bad value or a stale tag, NaN readings, a flag - shuffled, with other frames
    between them."""
    ids = [t.node_id for t in scene.taxels]
    events = [(0, 0, 0x700 + i, b"\x00", 0) for i in ids] + [(0, 0, 0x000, bytes([0x01, 0]), 0)]
    t = 10 * MS
    period = int(scene.bus.sync_period_ms * MS)
    delayed = []
    for cycle in range(cycles):
        counter = cycle % scene.bus.sync_counter + 1 if scene.bus.sync_counter else None
        events.append((t, 0, 0x80, b"" if counter is None else bytes([counter]), 0))
        batch = []
        clean = rng.random() < 0.5  # every answer in time, once, well formed: the cycle completes
        for i in ids:
            r = 1.0 if clean else rng.random()
            if r < 0.06:
                continue  # lost
            cob, data = answer(scene, i, counter, 1 if rng.random() < 0.4 else -1, float(rng.normal(50, 30)))
            stamp = t + int(rng.integers(50, 1400 if clean else 3 * MS))
            if r < 0.09:
                stamp = t - int(rng.integers(1, 2 * MS))  # stamped before its SYNC
            elif r < 0.11:
                stamp = t + int(rng.integers(8 * MS, 9 * MS))  # past any window
            elif r < 0.13:
                data = data[:-1]  # cut
            elif r < 0.15:
                data = bytes([0x02]) if len(data) == 1 else struct.pack("<f", float("nan"))  # bad value
            elif r < 0.17 and scene.bus.cycle_tag:
                data = bytes([((counter + 5) & 63) << 2 | 0b01])  # a stale tag
            elif r < 0.18:
                batch.append((stamp, 0, cob, data, (FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE)[int(r * 1e4) % 3]))
                continue
            batch.append((stamp, 0, cob, data, 0))
            if not clean and rng.random() < 0.05:
                batch.append((stamp + 10, 0, cob, data, 0))  # repeated
            if not clean and rng.random() < 0.05:
                delayed.append((stamp + period, 0, cob, data, 0))  # an answer that comes a cycle late
        batch += [d for d in delayed if d[0] < t + period]
        delayed = [d for d in delayed if d[0] >= t + period]
        for _ in range(int(rng.integers(0, 4))):  # other frames of the bus
            i = int(rng.choice(ids))
            stamp = t + int(rng.integers(0, period))
            options = [
                (stamp, 0, 0x700 + i, bytes([int(rng.choice([0x05, 0x7F, 0x04, 0x33]))]), 0),
                (stamp, 0, 0x080 + i, bytes(8), 0),
                (stamp, 0, 0x600 + i, bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]), 0),
                (stamp, 0, 0x580 + i, bytes([0x4F, 0x00, 0x10, 0, 5, 0, 0, 0]), 0),
                (stamp, 0, 0x000, bytes([0x80, i]), 0),
                (stamp, 0, 0x000, bytes([0x01, 0]), 0),
                (stamp, 0, 0x17F, bytes(8), 0),
                (stamp, 0, (0x180 if scene.bus.mode == "raw" else 0x280) + i, bytes(4), 0),  # the other TPDO
            ]
            batch.append(options[int(rng.integers(len(options)))])
        order = rng.permutation(len(batch)) if rng.random() < 0.3 else np.argsort([b[0] for b in batch])
        events += [tuple(batch[k]) for k in order]
        t += period
    events.append((t, 0, 0x000, bytes([0x80, 0]), 0))  # the end of a run: NMT broadcast
    return [(int(e[0]), int(e[1]), int(e[2]), bytes(e[3]), int(e[4])) for e in events]


def assert_same_closed(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want):
        for name in CLOSED_FIELDS:
            assert getattr(g, name) == getattr(w, name), name
        for name in CLOSED_ARRAYS:
            np.testing.assert_array_equal(getattr(g, name), getattr(w, name), err_msg=name)
        assert g.emcy == w.emcy and g.drive == w.drive


def assert_same_state(got: CycleAssembler, want: CycleAssembler):
    assert got.counters() == want.counters()
    for name in ("t0_us", "last_us", "pending", "is_open", "cycle", "sync_raw", "sync_counter", "late_since",
                 "bad_since", "bootups", "solicited", "duplicates", "held", "got2_any"):
        assert getattr(got, name) == getattr(want, name), name
    for name in ("last_heard", "state", "expected", "sdo_outstanding", "got1", "got2", "decisions",
                 "held_decisions", "readings", "held_readings"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


@pytest.mark.parametrize("name", ["grasp_lift", "matrix57", "grasp_lift_raw", "matrix57_raw"])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("window_us", [0, 1500, 8000])
def test_a_turn_fed_in_one_loop_equals_its_frames_fed_one_by_one(name, seed, window_us):
    scene = one_taxel_scene(name, window_us)
    rng = np.random.default_rng(seed)
    # every 300th frame odd (a cycle of 50-odd answers can still complete), runs up to 39 frames
    turn_list = turns(rng, random_stream(scene, rng, 40), odd_every=300, longest=39)
    fails = frozenset({7, 19})
    stream, closed, answers, fed_common = feed(scene, turn_list, common=True, closing_fails=fails)
    reference, want, want_answers, _ = feed(scene, turn_list, common=False, closing_fails=fails)
    assert len(want) >= 30
    assert_same_closed(closed, want)
    assert answers == want_answers
    assert (stream.fed, stream.first_us, stream.last_us) == (reference.fed, reference.first_us, reference.last_us)
    assert_same_state(stream.assembler, reference.assembler)
    # the streams reach what they are meant to: the common path, and every general case beside it
    counters = reference.assembler.counters()
    frames = sum(len(msgs) for _, msgs in turn_list)
    assert fed_common["all"] > frames // 4 and fed_common["late"] > 0
    # the closing answers are not common
    assert counters["tpdo1"] + counters["tpdo2"] > fed_common["all"] - fed_common["late"]
    for counter in ("late", "bad_dlc", "bad_value", "heartbeat", "emcy", "sdo", "nmt", "unknown_cob_id",
                    "internal_error"):
        assert counters[counter] > 0, counter
    assert counters["error_frame"] + counters["remote_frame"] + counters["extended_id"] > 0
    if scene.bus.cycle_tag:
        assert reference.assembler.duplicates  # a repeat tagged with its cycle: left to the general path
    if window_us:
        assert any(c.closed_by == "window" for c in want)
    assert any(c.closed_by == "complete" for c in want)


def test_the_common_path_leaves_the_cycles_last_answer_and_the_centres_own_frames():
    scene = one_taxel_scene("grasp_lift", 0)
    closed = []
    stream = EventStream(CycleAssembler(scene), on_closed=closed.append)
    assert isinstance(stream.common, NodeFrames)
    ids = [t.node_id for t in scene.taxels]
    for i in ids:
        stream.receive(message(0, 0x700 + i, b"\x00"), 0)
    stream.receive(message(0, 0x000, bytes([0x01, 0])), 0)
    stream.receive(message(10 * MS, 0x80, b""), 0)
    msgs = [message(10 * MS + 10 * k, 0x180 + i, b"\x01") for k, i in enumerate(ids)]
    first = stream.first_us
    assert stream.common.feed(msgs, 0, 0, first) == (len(ids) - 1, int(round(msgs[-2].timestamp * 1e6)))
    assert stream.common.feed(msgs, len(ids) - 1, 0, first) == (0, 0)  # it completes the cycle
    stream.receive_all(msgs[-1:], 0)
    assert [c.closed_by for c in closed] == ["complete"] and closed[0].decisions.tolist() == [1] * len(ids)
    own = message(20 * MS, 0x181, b"\x01")
    own.is_rx = False
    assert stream.common.feed([own], 0, 0, first) == (0, 0)
    # patch scenes keep CommonFrames (or none), never this path
    assert NodeFrames.for_assembler(CycleAssembler(load_scene("skin4096"))) is None
