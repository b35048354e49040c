"""The common frames of a receive turn fed in one loop (fusion_center.service.common_frames)
against feeding every frame on its own (``EventStream._feed_locked``, the stream with
``common`` None): random turns of patch TPDOs - lost, late, repeated, stale, cut, altered,
stamped before their SYNC or after the window - mixed with SYNCs, heartbeats, boot-ups, EMCY,
SDO requests and answers (awaited or not), NMT commands, flagged and unknown frames, odd time
stamps and frames that raise, give the same closed cycles in the same order, the same
counters, SDO answers and assembler state."""

import sys
from pathlib import Path

import can
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_cycles_patch import frames, patch_scene  # noqa: E402
from test_packed_decisions import assert_same_closed, random_stream  # noqa: E402

from taxel_net.patches import devices  # noqa: E402
from fusion_center.service.cycle_records import (  # noqa: E402
    C_LATE, FLAG_ERROR, FLAG_EXTENDED, FLAG_FD, FLAG_REMOTE)
from fusion_center.service.cycles import CycleAssembler  # noqa: E402
from fusion_center.service.stream import EventStream  # noqa: E402

MS = 1000  # µs
T0_S = 1_700_000_000.0  # the streams' first time stamp, s


def message(t_us, can_id, data, flags=0):
    msg = can.Message(timestamp=T0_S + t_us * 1e-6, arbitration_id=can_id,
                      is_extended_id=bool(flags & FLAG_EXTENDED), is_remote_frame=bool(flags & FLAG_REMOTE),
                      is_error_frame=bool(flags & FLAG_ERROR), is_fd=bool(flags & FLAG_FD))
    msg.data = bytearray(data)  # a remote frame too (can.Message would empty it): only its flag refuses it
    return msg


def boot_events(scene):
    """Every device's boot-up, then NMT start all on every channel: (t, channel, cob, data, flags)."""
    events = [(0, d.channel, 0x700 + d.node_id, b"\x00", 0) for d in devices(scene)]
    return events + [(0, ch, 0x000, bytes([0x01, 0]), 0) for ch in range(len(scene.bus.channels))]


def mixed_stream(scene, rng, cycles, fd):
    """random_stream's patch TPDOs and SYNCs (test_packed_decisions), with every fourth or so
    event followed by another kind of frame (each kind in turn), and some TPDOs stamped off
    their place, tagged with a counter no SYNC carries, with a padding bit set or a flag
    toggled."""
    devs = devices(scene)
    node_flags = FLAG_FD if fd else 0
    out = []
    extras = 0
    for t, ch, cob, data, flags in random_stream(scene, rng, cycles, fd):
        r = rng.random()
        if cob != 0x80 and r < 0.04:
            t -= int(rng.integers(1, 3 * MS))  # stamped before its SYNC (or a stamp going back)
        elif cob != 0x80 and r < 0.06:
            t += int(rng.integers(1, 3 * MS))  # stamped late, past any window
        elif cob != 0x80 and r < 0.1 and data:
            data = bytes([0 if r < 0.08 else 65]) + data[1:]  # a tag no SYNC carries: bad_value
        elif cob != 0x80 and r < 0.12 and data:
            data = data[:-1] + bytes([data[-1] | 0x80])  # a padding bit or byte set (or a decision bit)
        elif cob != 0x80 and r < 0.14:
            flags ^= (FLAG_FD, FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR)[int(r * 1000) % 4]  # a flag
        out.append((t, ch, cob, data, flags))
        if rng.random() > 0.25:
            continue
        d = devs[int(rng.integers(len(devs)))]
        other = [
            (t, d.channel, 0x700 + d.node_id, bytes([int(rng.choice([0x05, 0x7F, 0x04, 0x00, 0x33]))]), 0),
            (t, d.channel, 0x080 + d.node_id, bytes(8), 0),                               # EMCY
            (t, d.channel, 0x600 + d.node_id, bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]), 0),  # SDO request
            (t, d.channel, 0x580 + d.node_id, bytes([0x4F, 0x00, 0x10, 0, 5, 0, 0, 0]), 0),  # SDO answer
            (t, d.channel, 0x000, bytes([int(rng.choice([0x01, 0x02, 0x80])), d.node_id]), 0),  # NMT to one node
            (t, d.channel, 0x000, bytes([0x01, 0]), 0),                                    # NMT start all
            (t, d.channel, 0x7E5, bytes(8), 0),                                            # LSS
            (t, d.channel, 0x181, bytes(3), FLAG_ERROR),
            (t, d.channel, 0x181, b"", FLAG_REMOTE),
            (t, d.channel, 0x181, bytes(3), FLAG_EXTENDED),
            (t, d.channel, d.tpdos[0].cob_id, bytes(d.tpdos[0].length), FLAG_FD ^ node_flags),  # the other format
            (t, d.channel, 0x17F, bytes(8), 0),                                            # no such node
            (t, 0, 0x80, bytes([int(rng.integers(1, 65))]), 0),                            # a stray SYNC
        ]
        out.append(other[extras % len(other)])  # each kind in turn
        extras += 1
    return sync_ahead(rng, out)


def sync_ahead(rng, events):
    """Half the SYNCs handled before the last few answers to the SYNC before them, as a busy
    host hands them over (the master feeds its SYNC when it sends it): each frame keeps its
    time stamp, so those answers are stamped inside the previous cycle's window."""
    out = []
    for event in events:
        if event[2] == 0x80 and out and rng.random() < 0.5:
            back = 0
            while back < int(rng.integers(1, 6)) and back < len(out) and out[-1 - back][2] != 0x80:
                back += 1
            out.insert(len(out) - back, event)
        else:
            out.append(event)
    return out


def turns(rng, events, odd_every: int = 50, longest: int = 15):
    """The events as receive turns ``(channel, [(t, cob, data, flags, odd)])``: runs of one
    channel cut at random lengths (up to ``longest``); ``odd`` marks every ``odd_every``-th
    frame: its time stamp one that quantise_timestamp maps to 0 (NaN, None), or its data one that
    makes the receive path raise."""
    out = []
    for k, (t, ch, cob, data, flags) in enumerate(events):
        odd = ("nan", "none", "no data")[k // odd_every % 3] if k % odd_every == odd_every - 1 else None
        if out and out[-1][0] == ch and len(out[-1][1]) < int(rng.integers(1, longest + 1)):
            out[-1][1].append((t, cob, data, flags, odd))
        else:
            out.append((ch, [(t, cob, data, flags, odd)]))
    return out


def messages(frames):
    out = []
    for t, cob, data, flags, odd in frames:
        msg = message(t, cob, data, flags)
        if odd == "nan":
            msg.timestamp = float("nan")
        elif odd == "none":
            msg.timestamp = None
        elif odd == "no data":
            msg.data = None  # len(None): counted as internal_error
        out.append(msg)
    return out


def feed(scene, turn_list, common: bool, closing_fails=frozenset()):
    """A fresh stream fed ``turn_list``; its closed cycles in on_closed order, the SDO answers
    per turn (indexes in the turn) and how many frames the common path fed (all, late, and
    while events were held)."""
    assembler = CycleAssembler(scene)
    closed = []

    def on_closed(cycle):
        if cycle.cycle in closing_fails:
            raise RuntimeError("on_closed fails")  # counted and logged, like any receive-path error
        closed.append(cycle)

    stream = EventStream(assembler, on_closed=on_closed)
    fed_common = {"all": 0, "late": 0, "held": 0}  # frames the common path fed: all, late, while events were held
    if common:
        assert stream.common is not None
        common_feed = stream.common.feed

        def counted(*args):
            late = assembler.counts[C_LATE]
            fed, last_us = common_feed(*args)
            fed_common["all"] += fed
            fed_common["late"] += assembler.counts[C_LATE] - late
            if assembler.held:
                fed_common["held"] += fed
            return fed, last_us

        stream.common.feed = counted
    else:
        stream.common = None
    answers = []
    for k, (ch, turn) in enumerate(turn_list):
        msgs = messages(turn)
        got = stream.receive_all(iter(msgs) if k % 5 == 0 else msgs, ch)  # any iterable
        answers.append([next(i for i, m in enumerate(msgs) if m is answer) for answer in got])
    return stream, closed, answers, fed_common


def assert_same_state(got: CycleAssembler, want: CycleAssembler):
    assert got.counters() == want.counters()
    for name in ("t0_us", "last_us", "pending", "is_open", "cycle", "sync_raw", "sync_counter", "late_since",
                 "bad_since", "bootups", "solicited", "duplicates", "held"):
        assert getattr(got, name) == getattr(want, name), name
    for name in ("last_heard", "state", "slot_got", "expected", "sdo_outstanding", "got1", "decisions"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    assert got.packed.cycle_bytes == want.packed.cycle_bytes and got.packed.held_bytes == want.packed.held_bytes
    np.testing.assert_array_equal(got.packed.heard, want.packed.heard)


SCENES = [  # (patch sizes, node channels, fd)
    ((10, 70), None, False),
    ((1, 7, 13, 192), (0, 1, 0, 1), False),
    ((64, 3, 130), (1, 0, 1), False),
    ((192, 100, 9), None, True),
]


@pytest.mark.parametrize("sizes, node_channels, fd", SCENES)
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("window_us", [0, 100, 4000])  # 100 µs: later frames miss it; 4 ms: most hit it
def test_a_turn_fed_in_one_loop_equals_its_frames_fed_one_by_one(sizes, node_channels, fd, seed, window_us):
    channels = ("c0", "c1") if node_channels else ("c0",)
    scene = patch_scene(sizes=sizes, fd=fd, window_us=window_us, channels=channels, node_channels=node_channels)
    rng = np.random.default_rng(seed)
    turn_list = turns(rng, boot_events(scene) + mixed_stream(scene, rng, 60, fd))
    fails = frozenset({7, 19})
    stream, closed, answers, fed_common = feed(scene, turn_list, common=True, closing_fails=fails)
    reference, want, want_answers, _ = feed(scene, turn_list, common=False, closing_fails=fails)
    assert len(want) >= 40
    assert_same_closed(closed, want)
    assert [c.closed_by for c in closed] == [c.closed_by for c in want]
    assert answers == want_answers
    assert (stream.fed, stream.first_us, stream.last_us) == (reference.fed, reference.first_us, reference.last_us)
    assert_same_state(stream.assembler, reference.assembler)
    # the streams reach what they are meant to: the common path, and every general case beside it
    counters = reference.assembler.counters()
    frames = sum(len(msgs) for _, msgs in turn_list)
    assert fed_common["all"] > frames // 4 and fed_common["late"] > 0
    assert counters["tpdo1"] > fed_common["all"] - fed_common["late"]  # the closing TPDOs are not common
    assert counters["late"] > fed_common["late"]  # nor repeats
    for name in ("late", "bad_dlc", "bad_value", "heartbeat", "emcy", "sdo", "nmt", "unknown_cob_id",
                 "error_frame", "remote_frame", "extended_id", "fd_frame", "internal_error"):
        assert counters[name] > 0, name
    assert any(want_answers) and reference.assembler.duplicates
    if window_us:
        assert any(c.closed_by == "window" for c in want)
    if window_us > 100:
        assert fed_common["held"] > 0  # answers to a cycle whose successor's SYNC is held


def test_the_common_path_feeds_a_turn_of_one_cycle_in_one_loop_and_leaves_its_last_frame():
    scene = patch_scene(sizes=(10, 70))
    closed = []
    stream = EventStream(CycleAssembler(scene), on_closed=closed.append)
    for t, ch, cob, data, flags in boot_events(scene):
        stream.receive(message(t, cob, data, flags), ch)
    stream.receive(message(10 * MS, 0x80, b"\x01"), 0)
    msgs = [message(10 * MS + 10 * k, cob, data) for k, (_, cob, data) in enumerate(frames(scene, np.ones(80), 1))]
    assert len(msgs) == 3
    assert stream.common.feed(msgs, 0, 0, stream.first_us) == (2, int(round(msgs[1].timestamp * 1e6)))
    assert stream.assembler.counters()["tpdo1"] == 2 and stream.assembler.is_open
    # the last frame completes the cycle: not common, fed by the general path
    assert stream.common.feed(msgs, 2, 0, stream.first_us) == (0, 0)
    stream.receive_all(msgs[2:], 0)
    assert [c.closed_by for c in closed] == ["complete"] and closed[0].decisions.tolist() == [1] * 80
    assert stream.assembler.events == len(boot_events(scene)) + 4  # every frame counted once


def test_without_packed_decisions_there_is_no_common_path():
    assert EventStream(CycleAssembler(patch_scene(sizes=(10, 70), mode="raw"))).common is None
    assert EventStream(CycleAssembler(patch_scene(sizes=(10, 70)))).common is not None


def _part_fields(part) -> dict:
    import dataclasses

    out = {}
    for name, value in dataclasses.asdict(part).items():
        if isinstance(value, np.ndarray):
            value = (value.dtype.str, value.tolist())
        elif isinstance(value, tuple):
            value = [(v.dtype.str, v.tolist()) if isinstance(v, np.ndarray) else v for v in value]
        out[name] = value
    return out


@pytest.mark.parametrize("sizes, node_channels, fd", SCENES)
@pytest.mark.parametrize("window_us", [0, 4000])
def test_an_assembler_process_feeds_its_turns_as_it_would_frame_by_frame(sizes, node_channels, fd, window_us):
    """`fusion-center assemble` takes the common path too: the parts it would send the fuser,
    its event count and its assembler's state are those of feeding every frame on its own, on
    the same random turns (late, stale, repeated, cut, flagged frames, other kinds; a frame
    whose data makes the feed raise is counted as an internal error and the turn goes on, as
    in the centre's stream - raised, it would end the reading of its bus)."""
    from fusion_center.service.assembler_process import AssemblerProcess

    channels = ("c0", "c1") if node_channels else ("c0",)
    scene = patch_scene(sizes=sizes, fd=fd, window_us=window_us, channels=channels, node_channels=node_channels)
    rng = np.random.default_rng(11)
    turn_list = turns(rng, boot_events(scene) + mixed_stream(scene, rng, 60, fd))
    runs = []
    for common in (True, False):
        proc = AssemblerProcess(scene, range(len(channels)), fuser=("127.0.0.1", 9), interface="virtual")
        fed_common = [0]
        if common:
            assert proc.common is not None
            feed_run = proc.common.feed

            def counted(*args, feed_run=feed_run, fed_common=fed_common):
                fed, last_us = feed_run(*args)
                fed_common[0] += fed
                return fed, last_us

            proc.common.feed = counted
        else:
            proc.common = None
        proc._send = lambda: None  # the parts stay in the outbox
        raised = []
        for k, (ch, turn) in enumerate(turn_list):
            try:
                proc.receive_all(messages(turn), ch)
            except Exception as exc:  # noqa: BLE001 - compared between the two runs
                raised.append((k, type(exc)))
        runs.append((proc, raised, fed_common[0]))
    (got, got_raised, fed), (want, want_raised, _) = runs
    assert got_raised == want_raised == []
    assert want.group.assembler.counters()["internal_error"] > 0  # the raising frames are in the turns
    assert len(want._outbox) >= 40 and fed > sum(len(t) for _, t in turn_list) // 4
    assert [_part_fields(p) for p in got._outbox] == [_part_fields(p) for p in want._outbox]
    assert got.events == want.events
    assert_same_state(got.group.assembler, want.group.assembler)
