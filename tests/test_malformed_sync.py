"""A malformed SYNC (wrong length, or a counter no SYNC carries) is counted and changes no
cycle (issue 21, item 1): CiA 301 SYNC is DLC 0 without a counter (0x1019 = 0) and DLC 1 with a
counter 1..0x1019 with one. Before the fix the assembler held any COB-ID 0x080 frame on channel
0 as "SYNC k+1" while k's synchronous window was open, and a second such frame released the
window - closing the cycle early, its remaining decisions counted late."""

import dataclasses

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from fusion_center.commands.demo import run_demo
from fusion_center.service import CycleAssembler, CyclePipeline, EventStream
from fusion_center.service.traces import trace_channel
from taxel_net.scene import BusSpec, FusionSpec, Scene, TaxelSpec, load_scene

MS = 1000
N = 4


def windowed_scene(sync_counter):
    taxels = tuple(TaxelSpec(node_id=10 + i, kind="R", zeta_mv=1.0) for i in range(N))
    bus = BusSpec(sync_counter=sync_counter, heartbeat_consumer_ms=0, transmission_type=1, mode="decision",
                  channels=("c0",), sync_window_us=8 * MS)
    return Scene(path="<test>", name="t", bus=bus, taxels=taxels, fusion=FusionSpec())


def malformed_payloads(overflow):
    """SYNC payloads that open no cycle in a scene with this 0x1019 (independent of the code:
    CiA 301's rule written out)."""
    if overflow:
        return [b"", b"\x01\x01", bytes(8), b"\x00", bytes([overflow + 1]), b"\xff"]
    return [b"\x01", b"\x00", b"\x00\x00", bytes(8)]


@st.composite
def streams(draw):
    """A clean stream of SYNC cycles (answers on time, answers handled after the next SYNC,
    lost answers) and the same stream with malformed SYNCs inserted anywhere."""
    overflow = draw(st.sampled_from([0, 4, 64]))
    events = [(0, 0x700 + 10 + i, b"\x00") for i in range(N)] + [(0, 0x000, b"\x01\x00")]
    counter = 0
    for k in range(1, draw(st.integers(2, 8)) + 1):
        t0 = k * 10 * MS
        counter = counter % overflow + 1 if overflow else 0
        sync = (t0, 0x080, bytes([counter]) if overflow else b"")
        answers = []
        for i in range(N):
            fate = draw(st.sampled_from(["on time", "on time", "after next sync", "lost"]))
            if fate == "lost":
                continue
            u = draw(st.sampled_from([1, -1]))
            data = bytes([(u & 0x03) | ((counter & 0x3F) << 2)]) if overflow else bytes([u & 0xFF])
            stamp = t0 + draw(st.integers(1, 7 * MS))
            answers.append((fate, (stamp, 0x180 + 10 + i, data)))
        events.append(sync)
        events += [e for fate, e in answers if fate == "on time"]
        events.append(("deferred", [e for fate, e in answers if fate == "after next sync"]))
    # deferred answers are handled after the next SYNC was fed (bus order, cycles.py docstring)
    clean = []
    pending = []
    for e in events:
        if isinstance(e[0], str):
            pending = e[1]
            continue
        clean.append(e)
        if e[1] == 0x080 and pending:
            clean += pending
            pending = []
    clean += pending
    clean.append((clean[-1][0] + 20 * MS, 0x000, b"\x80\x00"))  # NMT pre-operational all: ends the run
    junk = draw(st.lists(st.tuples(st.integers(0, len(clean)), st.sampled_from(malformed_payloads(overflow))),
                         min_size=1, max_size=12))
    dirty = list(clean)
    for position, payload in sorted(junk, reverse=True):
        stamp = dirty[position - 1][0] if position else 0
        dirty.insert(position, (stamp, 0x080, payload))
    return overflow, clean, dirty, len(junk)


def closed_cycles(scene, events):
    a = CycleAssembler(scene)
    out = []
    for t, can_id, data in events:
        out += a.feed_all(t, 0, can_id, data)
    return out, a.counters()


def view(c):
    """Everything a closed cycle says, but its count of malformed frames."""
    fields = dataclasses.asdict(c) if not hasattr(c, "__slots__") else {f: getattr(c, f) for f in c.__slots__}
    fields.pop("bad_frames")
    # arrays by dtype and bytes: NaN readings (nothing received) compare equal to themselves
    return {k: ((str(v.dtype), v.shape, v.tobytes()) if isinstance(v, np.ndarray) else v) for k, v in fields.items()}


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(streams())
def test_malformed_syncs_anywhere_change_no_cycle(case):
    overflow, clean, dirty, n_junk = case
    scene = windowed_scene(overflow)
    want, want_counts = closed_cycles(scene, clean)
    got, got_counts = closed_cycles(scene, dirty)
    assert [view(c) for c in got] == [view(c) for c in want]
    # every malformed SYNC is counted once, as a length or a value error, and nothing else moved
    bad = (got_counts.get("bad_dlc", 0) - want_counts.get("bad_dlc", 0)
           + got_counts.get("bad_value", 0) - want_counts.get("bad_value", 0))
    assert bad == n_junk
    assert sum(c.bad_frames for c in got) - sum(c.bad_frames for c in want) <= n_junk
    others = {k: v for k, v in got_counts.items() if k not in ("bad_dlc", "bad_value")}
    assert others == {k: v for k, v in want_counts.items() if k not in ("bad_dlc", "bad_value")}


@pytest.mark.parametrize("overflow,payload,counter", [(64, b"", "bad_dlc"), (64, b"\x00", "bad_value"),
                                                      (64, b"\x41", "bad_value"), (64, b"\x01\x02", "bad_dlc"),
                                                      (0, b"\x01", "bad_dlc")])
def test_two_malformed_syncs_inside_the_window_leave_the_cycle_open(overflow, payload, counter):
    scene = windowed_scene(overflow)
    a = CycleAssembler(scene)
    for i in range(N):
        a.feed(0, 0, 0x700 + 10 + i, b"\x00")
    a.feed(0, 0, 0x000, b"\x01\x00")
    a.feed(10 * MS, 0, 0x080, b"\x01" if overflow else b"")
    tag = (lambda u: bytes([(u & 3) | (1 << 2)])) if overflow else (lambda u: bytes([u & 0xFF]))
    a.feed(10 * MS + 100, 0, 0x180 + 10, tag(1))
    assert a.feed_all(10 * MS + 200, 0, 0x080, payload) == []
    assert a.feed_all(10 * MS + 300, 0, 0x080, payload) == []
    assert a.is_open and not a.held and a.counters()[counter] == 2
    for i in range(1, N - 1):
        assert a.feed_all(10 * MS + 400 + i, 0, 0x180 + 10 + i, tag(-1)) == []
    closed = a.feed_all(10 * MS + 500, 0, 0x180 + 10 + N - 1, tag(1))
    assert [c.closed_by for c in closed] == ["complete"]
    assert closed[0].decisions.tolist() == [1, -1, -1, 1] and closed[0].bad_frames == 2


@pytest.fixture(scope="module")
def matrix_trace(tmp_path_factory):
    scene = load_scene("matrix57")
    trace = tmp_path_factory.mktemp("sync") / "d.log"
    run_demo(scene, 60, trace=trace, keep_records=False)
    return scene, trace


@pytest.fixture(scope="module")
def clean_replay(matrix_trace):
    """The trace replayed without junk (the reference of every payload's case: the same trace
    through the same objects gives the same records; the tests read copies of them)."""
    scene, trace = matrix_trace
    return replay_with_junk(scene, trace, 30, None)


def replay_with_junk(scene, trace, junk_cycle, payload):
    """The issue's reproduction: the trace fed through the public service objects, two
    malformed SYNCs injected right after the first two TPDO1s of cycle ``junk_cycle``."""
    asm = CycleAssembler(scene)
    pipe = CyclePipeline(scene)
    records = []
    stream = EventStream(asm, on_closed=lambda c: records.append(pipe.evaluate(c)))
    syncs = done = 0
    for m in can.LogReader(str(trace)):
        stream.receive(m, trace_channel(m))
        syncs += m.arbitration_id == 0x080
        if payload is not None and done < 2 and syncs == junk_cycle + 1 and 0x181 <= m.arbitration_id <= 0x1FF:
            stream.receive(can.Message(timestamp=m.timestamp, arbitration_id=0x080, data=payload,
                                       is_extended_id=False), 0)
            done += 1
    return records, asm.counters()


@pytest.mark.parametrize("payload", [b"", b"\x00", b"\x01\x01"])
def test_malformed_syncs_in_a_recorded_matrix57_run_flip_nothing(matrix_trace, clean_replay, payload):
    scene, trace = matrix_trace
    assert scene.bus.sync_counter > 0 and scene.bus.sync_window  # the case of the finding
    clean, clean_counts = clean_replay
    dirty, dirty_counts = replay_with_junk(scene, trace, 30, payload)
    assert len(dirty) == len(clean)
    assert dirty[30]["closed_by"] == clean[30]["closed_by"] and dirty[30]["n_received"] == clean[30]["n_received"]
    for a, b in zip(clean, dirty):
        a, b = dict(a), dict(b)
        assert b.pop("bad_frames") - a.pop("bad_frames") in (0, 2)
        b.pop("latency_ms", None), a.pop("latency_ms", None)
        assert a == b
    assert dirty_counts["late"] == clean_counts["late"]
    assert dirty_counts.get("bad_dlc", 0) + dirty_counts.get("bad_value", 0) == \
        clean_counts.get("bad_dlc", 0) + clean_counts.get("bad_value", 0) + 2
