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
