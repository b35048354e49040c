"""Soak: does the fusion centre's memory stay flat over many cycles? (issue 10, bounded memory)

    .venv/bin/python bench/soak.py [--cycles 1000000] [--keep-records] [--trace]

The centre as ``fusion-center run`` builds it (``FusionService`` on a private virtual channel,
``keep_records=False``, decision log to a temporary file, optionally a candump trace), fed in
*virtual time*: every cycle a SYNC, the 57 TPDO1 frames of scenes/matrix57.toml, the
heartbeats every 10th cycle; the decision vectors are precomputed (contact in 80 of every 200
cycles, about one false alarm or miss per 9 cycles, so many distinct vectors pass through the
bounded caches); every 5000th cycle node 18 goes silent for 40 cycles (missing, degraded
cycles, a new received set) and sends an EMCY. The frames go through ``EventStream.receive``
exactly as the receive thread hands them over (no bus, no clock: 10^6 cycles take minutes,
not hours) and every closed cycle is evaluated, logged and aggregated as live.

Prints the RSS (``/proc/self/statm``) at log-spaced cycles, the RSS change from cycle 10^3
to the end and the least-squares slope (KiB per 1000 cycles) over that range. Goal: flat
within +-5 MB from 10^3 to 10^6. ``--keep-records`` keeps every record in memory (what the
service did before: +2.9 KiB a cycle) for comparison.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import uuid
from pathlib import Path

import can
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from fusion_center.service import FusionService  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402

SCENE = ROOT / "scenes" / "matrix57.toml"
PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=1_000_000)
    ap.add_argument("--keep-records", action="store_true", help="keep every record (the old behaviour)")
    ap.add_argument("--trace", action="store_true", help="also write a candump trace (.log)")
    args = ap.parse_args(argv)
    scene = load_scene(SCENE)
    n = scene.n
    rng = np.random.default_rng(10)
    footprint = rng.choice(n, size=6, replace=False)
    drop = [t.node_id for t in scene.taxels].index(18)

    tpdo = [[can.Message(arbitration_id=0x180 + t.node_id, data=bytes([v]), is_extended_id=False)
             for v in (0xFF, 0x01)] for t in scene.taxels]
    heartbeat = [can.Message(arbitration_id=0x700 + t.node_id, data=b"\x05", is_extended_id=False)
                 for t in scene.taxels]
    emcy = can.Message(arbitration_id=0x80 + 18, data=bytes([0x00, 0x50, 0x01, 0, 0, 0, 0, 0]),
                       is_extended_id=False)
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)

    tmp = Path(tempfile.mkdtemp(prefix="soak-"))
    log = tmp / "soak.jsonl"
    trace = tmp / "soak.log" if args.trace else None
    service = FusionService(scene, interface="virtual", channels=[f"soak-{uuid.uuid4().hex[:8]}"],
                            json_lines=log, trace=trace, keep_records=True if args.keep_records else False)
    checkpoints = sorted({int(x) for x in np.unique(np.logspace(2, np.log10(args.cycles), 31).astype(int))}
                         | {1000, args.cycles})
    marks: list[tuple[int, float]] = []
    period_us = int(scene.bus.sync_period_ms * 1000)
    t_us = 1_000_000
    start = time.perf_counter()
    with service:
        stream = service.stream
        receive = stream.receive
        for t in scene.taxels:  # boot-ups, then operational (as after NMT start)
            receive(can.Message(timestamp=t_us * 1e-6, arbitration_id=0x700 + t.node_id, data=b"\x00",
                                is_extended_id=False), 0)
        service.assembler.state[:] = 5
        next_mark = 0
        for k in range(args.cycles):
            t_us += period_us
            silent = (k % 5000) >= 4960
            sync.timestamp = t_us * 1e-6
            service.master.sync_sent_at[k] = time.perf_counter()
            receive(sync, 0)
            contact = (k % 200) >= 60 and (k % 200) < 140
            u = np.zeros(n, dtype=np.intp)
            if contact:
                u[footprint] = 1
            flips = rng.poisson(0.114)
            if flips:
                u[rng.integers(0, n, size=flips)] ^= 1
            ts = (t_us + 200) * 1e-6
            for i in range(n):
                if silent and i == drop:
                    continue
                msg = tpdo[i][u[i]]
                msg.timestamp = ts
                receive(msg, 0)
            if k % 10 == 0:
                ts = (t_us + 500) * 1e-6
                for i in range(n):
                    if silent and i == drop:
                        continue
                    heartbeat[i].timestamp = ts
                    receive(heartbeat[i], 0)
            if k % 5000 == 4999:
                emcy.timestamp = (t_us + 600) * 1e-6
                receive(emcy, 0)
            if k + 1 == checkpoints[next_mark]:
                marks.append((k + 1, rss_mib()))
                next_mark = min(next_mark + 1, len(checkpoints) - 1)
        service.drain()
        records = service.stats.records
        p50, p99 = service.latency.percentile(50), service.latency.percentile(99)
    elapsed = time.perf_counter() - start
    size = log.stat().st_size
    for p in tmp.iterdir():
        p.unlink()
    tmp.rmdir()

    print(f"soak: {args.cycles} cycles of matrix57 in virtual time, {elapsed:.1f} s "
          f"({args.cycles / elapsed:.0f} cycles/s), keep_records={args.keep_records}, trace={args.trace}")
    print(f"records: {records} ({size / 2**20:.1f} MiB decision log); evaluation latency p50 {p50:.3f} ms, "
          f"p99 {p99:.3f} ms (SYNC fed -> record, virtual time)")
    print("cycle        RSS MiB")
    for cycle, rss in marks:
        print(f"{cycle:>9}  {rss:9.2f}")
    tail = [(c, r) for c, r in marks if c >= 1000]
    if len(tail) >= 2:
        c = np.array([x for x, _ in tail], dtype=float)
        r = np.array([y for _, y in tail])
        slope = np.polyfit(c, r, 1)[0] * 1000 * 1024  # KiB per 1000 cycles
        change = r[-1] - r[0]
        verdict = "flat (within +-5 MB)" if abs(change) * 1.048576 <= 5 else "NOT flat"
        print(f"RSS from cycle {int(c[0])} to {int(c[-1])}: {r[0]:.2f} -> {r[-1]:.2f} MiB "
              f"({change:+.2f} MiB), slope {slope:+.2f} KiB per 1000 cycles: {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
