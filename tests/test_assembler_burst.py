"""The assembler link under a burst (issue 24, the link's performance): Zenoh hands the parts of
every link to one callback thread of the fuser's, one after the other. A cycle evaluated in
that thread held the other group's parts behind it (skin4096 on a loaded host: the part
callback took 10 ms at p90, 29 ms at p99, parts came after their deadline and cycles were
degraded). The fuser's merge thread evaluates; the callback only checks, decodes and merges.
No wall-clock limit: the waits are safety limits, the deadline is out of reach."""

from __future__ import annotations

import random
import sys
import threading
import time
from pathlib import Path

from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from test_assembler_wire import _service, _wait  # noqa: E402
from test_assemblers import _parts  # noqa: E402
from test_node_shards import _scene_file  # noqa: E402 - the two-channel patch scene (2 x 40 taxels)

CYCLES = 48  # within the scene's SYNC counter (64): every part maps to its SYNC


def test_parts_merge_while_a_cycle_is_evaluated_and_none_is_lost_in_a_burst(tmp_path, monkeypatch):
    """Cycle 0's evaluation is held; meanwhile both assemblers send the parts of cycles 1..47
    back to back (far above any SYNC rate): every part is received and merged while the
    evaluation waits (on main the callback thread was the one evaluating: none arrived), and
    once it goes on, every cycle is a complete record, in SYNC order, none late or missing."""
    from fusion_center.service.assembler_process import AssemblerProcess

    monkeypatch.setenv("FUSION_CENTER_AUTHKEY", "burst-test-key")
    scene = load_scene(_scene_file(tmp_path))
    port = random.randint(40000, 60000)
    service = _service(scene, port, part_deadline_s=3600.0)  # only the parts decide a cycle
    evaluating, release = threading.Event(), threading.Event()
    evaluate_command = service.pipeline.evaluate_command  # a cycle's evaluation begins there

    def held(closed):
        evaluating.set()
        release.wait(120)  # a safety limit: the test releases it
        return evaluate_command(closed)

    service.pipeline.evaluate_command = held
    processes = []
    try:
        service.open()
        for g in (0, 1):
            process = AssemblerProcess(scene, [g], fuser=("127.0.0.1", port), interface="virtual",
                                       reconnect_timeout_s=10)
            processes.append(process)
            process.open()
            process.connect(30)
        _wait(lambda: service.merger.covered() == {0, 1}, "both groups welcomed")
        for k in range(CYCLES):
            service.merger.opened(k + 1, k * 40_000, time.monotonic())  # SYNC k, counter k + 1
        parts = [_parts(scene, k, k + 1) for k in range(CYCLES)]

        def send(k):
            for process in processes:
                process._outbox.append(parts[k][process.layout.name])
                process._send()

        send(0)
        assert evaluating.wait(60), "cycle 0 was not evaluated"
        for k in range(1, CYCLES):
            send(k)
        assert all(p.parts_sent == CYCLES and p.parts_unsent == 0 for p in processes)
        _wait(lambda: service.merger.stats.parts == 2 * CYCLES,
              f"every part merged while cycle 0 is evaluated (got {service.merger.stats.parts})", limit_s=60)
        assert len(service.records) == 0 and not release.is_set()
        release.set()
        _wait(lambda: len(service.records) == CYCLES, f"{CYCLES} records (got {len(service.records)})", limit_s=60)
        stats = service.merger.stats
        assert [r["cycle"] for r in service.records] == list(range(CYCLES))
        missing = [(r["cycle"], r["parts_missing"]) for r in service.records if r["parts_missing"]]
        assert missing == []
        assert (stats.complete, stats.degraded, stats.late_parts, stats.unmatched_parts, stats.duplicate_parts) == \
            (CYCLES, 0, 0, 0, 0)
        assert stats.by_group == {"0": CYCLES, "1": CYCLES} and stats.refused == {}
    finally:
        release.set()
        for process in processes:
            process.close()
        service.close()


def test_an_assemblers_buses_are_read_by_one_thread_a_receive_turn_at_a_time(tmp_path, monkeypatch):
    """The assembler process reads its group's buses as the centre and node-sim read theirs
    (taxel_net.receiver): one receive thread for every bus, the frames a bus holds handed on in
    one call. On main each bus had a python-can Notifier thread handing on one frame per call:
    the threads took turns on the interpreter lock frame by frame (a part's Zenoh put releases
    it), and skin4096's two assemblers took 6.7 ms of CPU a cycle (one thread: 4.1 ms,
    docs/robotics.md). Every frame still reaches the assembler once, in its bus's order."""
    import can

    from fusion_center.service.assembler_process import AssemblerProcess

    monkeypatch.setenv("FUSION_CENTER_AUTHKEY", "turn-test-key")
    scene = load_scene(_scene_file(tmp_path))
    port = random.randint(40000, 60000)
    names = [f"turn-{port}-a", f"turn-{port}-b"]
    process = AssemblerProcess(scene, [0, 1], fuser=("127.0.0.1", port), interface="virtual", channel_names=names)
    calls: list[tuple[int, int, list[bytes]]] = []  # (thread, channel, the frames' payloads)
    held, go = threading.Event(), threading.Event()
    receive_all = process.receive_all

    def recording(msgs, channel):
        msgs = list(msgs)
        calls.append((threading.get_ident(), channel, [bytes(m.data) for m in msgs]))
        if not held.is_set():  # the first call waits while the rest of the frames are queued
            held.set()
            go.wait(30)  # a safety limit: the test releases it
        receive_all(msgs, channel)

    monkeypatch.setattr(process, "receive_all", recording)
    senders = [can.Bus(interface="virtual", channel=name) for name in names]
    frames = 40
    try:
        process.open()
        # heartbeats of a node the group does not have: fed, counted, they close no cycle
        senders[0].send(can.Message(arbitration_id=0x77F, data=[0x7F, 0], is_extended_id=False))
        assert held.wait(30), "the first frame was not handed on"
        for k in range(frames):
            for channel, bus in enumerate(senders):
                bus.send(can.Message(arbitration_id=0x77F, data=[0x7F, 1 + k + 100 * channel], is_extended_id=False))
        go.set()
        _wait(lambda: sum(len(c[2]) for c in calls) == 1 + 2 * frames, "every frame handed on")
        got = {0: [], 1: []}
        for _, channel, payloads in calls:
            got[channel].extend(p[1] for p in payloads)
        assert got == {0: [0] + [1 + k for k in range(frames)], 1: [101 + k for k in range(frames)]}
        assert len({thread for thread, _, _ in calls}) == 1  # one receive thread for both buses
        # the frames queued meanwhile came a turn of a bus in one call (main: one frame a call)
        assert max(len(payloads) for _, _, payloads in calls[1:]) == frames
        assert process.events == 1 + 2 * frames
    finally:
        go.set()
        process.close()
        for bus in senders:
            bus.shutdown()
