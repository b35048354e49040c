"""The centre's part of SYNC -> command split finer than bench/grip_latency.py's breakdown: one run,
the receive turn that closed each cycle followed mark by mark.

    .venv/bin/python bench/grip_latency_detail.py [--scene grasp_lift_patch] [--transport player]
                                                 [--cycles 600]

Marks (``time.time()``, taken by wrappers around the centre's and its receive thread's methods,
~1 µs each): ``kernel`` the closing frame's stamp (the record's ``closed_after_ms``), ``turn``
the receive thread's turn began (``select`` returned: the wake-up), ``dispatch`` the turn's
datagrams read and unpacked (``udp_multicast_drain``), ``recv_all`` the centre's own echoes
dropped (``EchoFilter.foreign``; since its datagrams carry its bus's tag, 2026-11-30, the kernel
drops them and this is the check that none is awaited), ``close_start`` / ``close_end`` the assembler's ``_close``
(the frames before it fed), ``pending`` the stream lock released and the closed cycle's
evaluation begun in the same thread, ``eval`` ``CyclePipeline.evaluate_command`` entered. Prints
p50/p90/p99 ms of each step over the cycles, the COB-IDs of the closing turns (most common
first) and the bench's own ``answers``, ``wake``, ``assemble`` and ``centre``.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import numpy as np  # noqa: E402

import grip_latency  # noqa: E402
from fusion_center.service import cycles, fusion_service, pipeline, stream  # noqa: E402
from taxel_net import receiver  # noqa: E402

KEYS = ("kernel", "turn", "dispatch", "recv_all", "close_start", "close_end", "pending", "eval")


def _wrap(cls, name, before=None, after=None):
    fn = getattr(cls, name)

    def wrapped(self, *args, **kwargs):
        if before is not None:
            before(self, *args)
        out = fn(self, *args, **kwargs)
        if after is not None:
            after(self, out)
        return out

    setattr(cls, name, wrapped)


def install() -> dict[int, dict]:
    """Wrap the classes (before the centre is made); returns cycle -> its closing turn's marks."""
    current = [{}]
    by_cycle: dict[int, dict] = {}

    def mark(name):
        return lambda self, *a: current[0].__setitem__(name, time.time())

    def turn(self, handle):
        current[0] = {"turn": time.time()}

    def dispatch(self, msgs):
        current[0].update(dispatch=time.time(), ids=tuple(f"{m.arbitration_id:#05x}" for m in msgs))

    def closed(self, out):
        current[0]["close_end"] = time.time()
        current[0]["kernel"] = (self.t0_us + out.close_us) * 1e-6
        by_cycle[out.cycle] = current[0]

    def evaluation(self, closed_cycle):
        marks = by_cycle.get(closed_cycle.cycle)
        if marks is not None and "eval" not in marks:
            marks["eval"] = time.time()

    _wrap(receiver.SelectNotifiers, "_turn", before=turn)
    _wrap(receiver._Handle, "dispatch_all", before=dispatch)
    _wrap(stream.EventStream, "receive_all", before=mark("recv_all"))
    _wrap(cycles.CycleAssembler, "_close", before=mark("close_start"), after=closed)
    _wrap(fusion_service.FusionService, "_process_pending", before=mark("pending"))
    _wrap(pipeline.CyclePipeline, "evaluate_command", before=evaluation)
    return by_cycle


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="grasp_lift_patch")
    ap.add_argument("--transport", choices=("udp", "player"), default="player")
    ap.add_argument("--cycles", type=int, default=600)
    args = ap.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.ERROR)
    if args.transport == "player":
        grip_latency.run_embedded(args.scene, args.cycles, instrumented=False)  # the recording, unmarked
    by_cycle = install()
    start = grip_latency.uptime()
    out = grip_latency.RUNS[args.transport](args.scene, args.cycles)
    rows = [m for m in by_cycle.values() if all(k in m for k in KEYS)]
    print(f"{args.scene} {args.transport}: {len(rows)} cycles; start {start}; end {grip_latency.uptime()}")
    print("closing turns (COB-IDs):", collections.Counter(m.get("ids") for m in rows).most_common(4))
    for a, b in zip(KEYS, KEYS[1:]):
        v = np.array([(m[b] - m[a]) * 1e3 for m in rows])
        print(f"  {a:>11s} -> {b:11s} ms p50 {np.median(v):.3f}  p90 {np.percentile(v, 90):.3f}  "
              f"p99 {np.percentile(v, 99):.3f}")
    for stage in ("answers", "wake", "assemble", "centre"):
        v = out["stages"][stage]
        print(f"  bench {stage:8s} p50 {np.median(v):.3f}  p99 {np.percentile(v, 99):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
