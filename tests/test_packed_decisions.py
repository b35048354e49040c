"""Packed decisions unpacked at the close (fusion_center.service.packed_decisions) against the
unpacking of every frame as it comes (the assembler with ``packed`` off): random streams of
patch TPDOs - frames missing, late, repeated, stale, with bad lengths or padding, in any order,
over several cycles - give the same closed cycles, field by field, and the same counters."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_cycles_patch import boot, frames, patch_scene  # noqa: E402

from fusion_center.service.cycle_records import FLAG_FD  # noqa: E402
from fusion_center.service.cycles import CycleAssembler  # noqa: E402
from fusion_center.service.packed_decisions import PackedDecisions  # noqa: E402

MS = 1000  # µs

CLOSED_ARRAYS = ("decisions", "readings", "received", "expected", "missing", "held_decisions", "held_readings")
CLOSED_FIELDS = ("cycle", "sync_us", "close_us", "sync_counter", "closed_by", "late_frames", "bad_frames",
                 "duplicates")


def per_frame(scene) -> CycleAssembler:
    """The reference: every packed frame unpacked as it comes (SlotDecoder.decode)."""
    a = CycleAssembler(scene)
    a.packed = None
    a.packed_places = [None] * len(a.packed_places)
    return a


def assert_same_closed(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want):
        for name in CLOSED_FIELDS:
            assert getattr(g, name) == getattr(w, name), name
        for name in CLOSED_ARRAYS:
            np.testing.assert_array_equal(getattr(g, name), getattr(w, name), err_msg=name)
        np.testing.assert_array_equal(g.devices.complete, w.devices.complete)


def random_stream(scene, rng, cycles, fd):
    """(t, channel, cob, data, flags) events: a SYNC per cycle, then that cycle's frames with
    some dropped, repeated, delayed into the next cycle, re-tagged stale, cut short or with a
    padding bit set, shuffled within the cycle."""
    flags = FLAG_FD if fd else 0
    events, t = [], 10 * MS
    delayed = []
    for cycle in range(cycles):
        counter = cycle % 64 + 1
        events.append((t, 0, 0x80, bytes([counter]), 0))
        u = np.where(rng.random(scene.n) < 0.3, 1, -1)
        batch = [(ch, cob, data) for ch, cob, data in frames(scene, u, tag=counter)]
        batch += delayed
        delayed = []
        out = []
        for ch, cob, data in batch:
            r = rng.random()
            if r < 0.08:
                continue                                    # lost
            if r < 0.14:
                delayed.append((ch, cob, data))             # comes in the next cycle (its tag stale there)
                continue
            if r < 0.18:
                out.append((ch, cob, data))                 # twice
            elif r < 0.21:
                data = data[:-1]                            # bad length
            elif r < 0.24 and len(data) > 1:
                data = data[:1] + bytes([data[1] ^ 0x80]) + data[2:]   # another decision byte
            elif r < 0.26:
                data = bytes([(data[0] + 7) % 64 + 1]) + data[1:]      # a tag no SYNC carried now
            out.append((ch, cob, data))
        rng.shuffle(out)
        for k, (ch, cob, data) in enumerate(out):
            events.append((t + 50 + 10 * k, ch, cob, data, flags))
        t += 10 * MS
    return events


@pytest.mark.parametrize("sizes, fd", [((10, 70), False), ((1, 7, 13, 192), False), ((64, 3), False),
                                       ((192, 100, 9), True)])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("window_us", [0, 100])   # 100 µs: a synchronous window the later frames miss
def test_unpacked_at_the_close_equals_unpacked_per_frame(sizes, fd, seed, window_us):
    scene = patch_scene(sizes=sizes, fd=fd, window_us=window_us)
    packed, reference = CycleAssembler(scene), per_frame(scene)
    assert packed.packed is not None and packed.packed.usable
    boot(packed, scene)
    boot(reference, scene)
    got, want = [], []
    for t, ch, cob, data, flags in random_stream(scene, np.random.default_rng(seed), 40, fd):
        got += packed.feed_all(t, ch, cob, data, flags)
        want += reference.feed_all(t, ch, cob, data, flags)
    assert len(want) >= 30   # the stream closes cycles (by SYNC or complete)
    assert_same_closed(got, want)
    assert packed.counters() == reference.counters()
    assert reference.counters()["late"] > 0 and reference.malformed() > 0  # the stream has both
    if window_us:
        assert any(c.closed_by == "window" for c in want)


def test_a_slot_never_heard_keeps_its_held_decisions_and_a_late_frame_updates_them():
    scene = patch_scene(sizes=(10, 70))
    a = CycleAssembler(scene)
    boot(a, scene)
    u = np.where(np.arange(80) % 2 == 0, 1, -1)
    fs = frames(scene, u, tag=1)
    assert a.feed_all(10 * MS, 0, 0x80, b"\x01") == []
    a.feed_all(10 * MS + 10, *fs[0])                       # device 1's only TPDO (taxels 0-9)
    closed = a.feed_all(20 * MS, 0, 0x80, b"\x02")[0]
    assert closed.decisions[:10].tolist() == u[:10].tolist() and (closed.decisions[10:] == 0).all()
    assert closed.held_decisions[:10].tolist() == u[:10].tolist() and (closed.held_decisions[10:] == 0).all()
    late = frames(scene, -u, tag=1)[1]                      # device 2's first TPDO, of the cycle before
    a.feed_all(20 * MS + 10, *late)
    closed = a.feed_all(30 * MS, 0, 0x80, b"\x03")[0]
    assert (closed.decisions == 0).all() and not closed.received.any()   # nothing counted in cycle 1
    assert closed.held_decisions[10:66].tolist() == (-u[10:66]).tolist()  # but heard
    assert (closed.held_decisions[66:] == 0).all() and closed.held_decisions[:10].tolist() == u[:10].tolist()


def test_the_places_cover_every_taxel_of_every_packed_slot_once():
    scene = patch_scene(sizes=(1, 7, 13, 192, 64))
    a = CycleAssembler(scene)
    packed = PackedDecisions(a.layout, scene.n)
    assert sorted(packed.bit_taxel.tolist()) == list(range(scene.n))
    widths = [stop - first for first, stop, _, _ in packed.places]
    assert sum(widths) == len(packed.cycle_bytes) == sum(-(-t.count // 8) for d in a.devices for t in d.tpdos)


def test_slots_of_readings_are_not_packed():
    scene = patch_scene(sizes=(10, 70), mode="raw")
    a = CycleAssembler(scene)
    assert a.packed is not None and a.packed.places == [None] * len(a.layout.slot_tpdo)
    assert len(a.packed.bit_taxel) == 0
