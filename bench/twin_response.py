"""How fast the node twins answer a SYNC at skin scale, with no centre on the host (issue 14).

    .venv/bin/python bench/twin_response.py [--scene scenes/skin4096.toml ...] [--cycles 600]
                                            [--shards 1,2]

``bench/skin_scale.py`` measures SYNC -> record with the twins and the centre on one 2-core host;
its "SYNC -> closing event" part is capped by the 8 ms synchronous window (a cycle whose last
PDO comes later is closed by the window, that PDO counted late). This bench takes the centre
away: the twins run in ``--shards`` ``node-sim`` processes on ``udp_multicast`` (loopback) as
there, and a minimal master in this process starts them (NMT) and sends the scene's SYNCs at
its period (with counter); every PDO is attributed to its SYNC by its cycle tag (the SYNC
counter the patch copies into byte 0). Printed per scene and shard count: SYNC -> first and
last PDO of the cycle (over all channels; the kernel's receive time stamps), p50 / p90 / p99 /
max, the cycles where a PDO never came, and the twins' CPU per cycle - what the simulated
patches cost the host, and the least SYNC -> record the centre could show beside them.
"""

from __future__ import annotations

import argparse
import random
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from skin_scale import CpuMeter, start_shards  # noqa: E402
from taxel_net import patches  # noqa: E402
from taxel_net.canmsg import tune_udp_multicast  # noqa: E402
from taxel_net.receiver import notifiers_for  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402


class PdoClock(can.Listener):
    """Receive time of the first and last PDO of each SYNC counter value on one channel."""

    def __init__(self, cob_ids: set[int], lock: threading.Lock, seen: dict):
        self.cob_ids, self.lock, self.seen = cob_ids, lock, seen

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id in self.cob_ids and msg.data:
            with self.lock:
                first, last, count = self.seen.get(msg.data[0], (msg.timestamp, msg.timestamp, 0))
                self.seen[msg.data[0]] = (min(first, msg.timestamp), max(last, msg.timestamp), count + 1)


def run(scene, cycles: int, shards: int) -> dict:
    port = random.randint(40000, 60000)
    groups = [f"239.74.167.{10 + k}" for k in range(len(scene.bus.channels))]
    devices = patches.devices(scene)
    if not all(t.tagged for d in devices for t in d.tpdos):
        raise SystemExit(f"{scene.path}: needs patch nodes with tagged TPDOs (the cycle tag attributes each PDO)")
    cob_ids = [{t.cob_id for d in devices if d.channel == k for t in d.tpdos} for k in range(len(groups))]
    expected = sum(len(d.tpdos) for d in devices)
    overflow = scene.bus.sync_counter
    period = scene.bus.sync_period_ms / 1000.0
    procs, buses = [], []
    try:
        start_shards(scene, shards, groups, port, procs)
        buses = [can.Bus(interface="udp_multicast", channel=g, port=port, hop_limit=0, fd=scene.bus.fd) for g in groups]
        for bus in buses:
            tune_udp_multicast(bus)
        lock = threading.Lock()
        per_cycle: dict[int, dict] = {}
        seen: dict[int, tuple] = {}
        handles = notifiers_for([(bus, [PdoClock(ids, lock, seen)]) for bus, ids in zip(buses, cob_ids)])
        for bus in buses:
            bus.send(can.Message(arbitration_id=0x000, data=b"\x01\x00", is_extended_id=False))
        time.sleep(1.0)
        counter = 0
        sync_time = {}
        with CpuMeter([p.pid for p in procs]) as cpu:
            t_next = time.monotonic()
            for cycle in range(cycles):
                counter = counter % overflow + 1 if overflow else 0
                with lock:  # the tag of the previous lap of the counter: that cycle's PDOs are in
                    done = seen.pop(counter, None)
                if done is not None:
                    per_cycle[cycle - overflow] = done
                sync_time[cycle] = time.time()
                for bus in buses:
                    bus.send(can.Message(arbitration_id=0x080, data=bytes([counter]) if overflow else b"",
                                         is_extended_id=False))
                t_next += period
                time.sleep(max(0.0, t_next - time.monotonic()))
        time.sleep(0.1)
        for cycle in range(cycles - overflow, cycles):  # the last lap
            tag = cycle % overflow + 1
            if tag in seen:
                per_cycle[cycle] = seen[tag]
        for handle in handles:
            handle.stop()
    finally:
        for bus in buses:
            bus.shutdown()
        for proc in procs:
            proc.terminate()
            proc.wait(10)
    warm = [c for c in range(20, cycles) if c in sync_time]
    complete = [c for c in warm if c in per_cycle and per_cycle[c][2] >= expected]
    first = np.array([(per_cycle[c][0] - sync_time[c]) * 1e3 for c in complete])
    last = np.array([(per_cycle[c][1] - sync_time[c]) * 1e3 for c in complete])
    return {"first": first, "last": last, "cycles": len(warm), "complete": len(complete), "expected": expected,
            "twins_ms": cpu.twins_s / cycles * 1e3}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", nargs="+", type=Path, default=[ROOT / "scenes" / "skin4096.toml"])
    ap.add_argument("--cycles", type=int, default=600)
    ap.add_argument("--shards", default="1,2", help="node-sim process counts to compare, comma-separated")
    args = ap.parse_args(argv)
    shard_counts = [int(s) for s in args.shards.split(",")]
    if args.cycles < 100 or min(shard_counts) < 1:
        ap.error("--cycles must be >= 100 and --shards >= 1")
    for path in args.scene:
        scene = load_scene(path)
        for shards in shard_counts:
            r = run(scene, args.cycles, shards)
            if not r["complete"]:
                print(f"{scene.name}, {shards} node-sim: no cycle had all {r['expected']} PDOs")
                continue

            def pct(a):
                return " / ".join(f"{np.percentile(a, q):.2f}" for q in (50, 90, 99, 100))

            print(f"{scene.name}: {scene.n} taxels, {r['expected']} PDOs a cycle on {len(scene.bus.channels)} channels, "
                  f"twins in {shards} node-sim process(es), no centre; {r['cycles']} cycles")
            print(f"  SYNC -> first PDO p50 / p90 / p99 / max: {pct(r['first'])} ms")
            print(f"  SYNC -> last PDO  p50 / p90 / p99 / max: {pct(r['last'])} ms "
                  f"({r['cycles'] - r['complete']} cycles with a PDO missing)")
            print(f"  twins' CPU per cycle: {r['twins_ms']:.2f} ms of a {scene.bus.sync_period_ms:g} ms period")
    return 0


if __name__ == "__main__":
    sys.exit(main())
