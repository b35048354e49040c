"""How fast the 57-node rig runs SYNC cycles on python-can's virtual bus, next to what a
real 1 Mbit/s CAN bus allows.

A master bus sends a SYNC, waits for all 57 one-byte TPDO1s (the local decisions u_i,
eqs 1-4), then sends the next SYNC: as fast as possible, in operational, heartbeats off.
Run twice: readings from the scene physics (node_sim.physics.sample_readings, the default)
and from a precomputed array (the node twins' own cost only).

Physical limit: one cycle needs 1 SYNC (no data) + 57 TPDOs (1 byte) on the wire:
    max cycles/s = bitrate / (bits(SYNC) + sum bits(TPDO_i))
with the exact frame lengths of fusion_center.core.bus_timing.frame_bits (actual stuff bits +
3-bit intermission), and with its worst-case bound 8n + 47 + floor((34 + 8n - 1)/4).

    .venv/bin/python bench/rig_cycles.py [--cycles 300] [--bitrate 1000000]
"""

from __future__ import annotations

import argparse
import struct
import sys
import time
import uuid
from dataclasses import replace
from pathlib import Path

import can
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from fusion_center.core.bus_timing import frame_bits, worst_case_frame_bits  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402
from node_sim import physics  # noqa: E402
from node_sim.rig import Rig  # noqa: E402


def exact_cycle_bits(node_ids, decisions) -> int:
    return frame_bits(0x80, b"") + sum(frame_bits(0x180 + nid, struct.pack("<b", int(u)))
                                       for nid, u in zip(node_ids, decisions))


def run(scene, cycles: int, reading_source=None) -> tuple[float, float]:
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    scene = replace(scene, bus=replace(scene.bus, channels=(channel,), heartbeat_producer_ms=0,
                                       transmission_type=1))
    n = scene.n
    tpdo_ids = {0x180 + t.node_id for t in scene.taxels}
    master = can.Bus(interface="virtual", channel=channel)
    try:
        with Rig(scene, reading_source=reading_source) as rig:
            while master.recv(0.2) is not None:     # boot-ups
                pass
            master.send(can.Message(arbitration_id=0x000, data=[0x01, 0], is_extended_id=False))
            deadline = time.monotonic() + 10
            while any(node.state != 0x05 for node in rig.nodes.values()) and time.monotonic() < deadline:
                time.sleep(0.001)
            sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
            frames = 0
            t0 = time.perf_counter()
            for _ in range(cycles):
                master.send(sync)
                got = 0
                while got < n:
                    msg = master.recv(5.0)
                    if msg is None:
                        raise RuntimeError("a TPDO never came")
                    if msg.arbitration_id in tpdo_ids:
                        got += 1
                frames += 1 + n
            elapsed = time.perf_counter() - t0
    finally:
        master.shutdown()
    return cycles / elapsed, frames / elapsed


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=300)
    ap.add_argument("--bitrate", type=int, default=1_000_000)
    ap.add_argument("--scene", default=str(ROOT / "scenes" / "matrix57.toml"))
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    n = scene.n
    node_ids = [t.node_id for t in scene.taxels]

    readings = np.stack([physics.sample_readings(scene, c) for c in range(args.cycles)])
    results = {
        "physics readings": run(scene, args.cycles),
        "precomputed readings": run(scene, args.cycles, reading_source=lambda c: readings[c]),
    }

    all_absent = exact_cycle_bits(node_ids, [-1] * n)
    all_present = exact_cycle_bits(node_ids, [1] * n)
    worst = worst_case_frame_bits(0) + n * worst_case_frame_bits(1)
    limits = {"exact, all u=-1": all_absent, "exact, all u=+1": all_present, "worst-case bound": worst}
    print(f"scene {scene.name}: {n} nodes, {args.cycles} cycles, virtual bus, SYNC -> wait for {n} TPDO1")
    print(f"bits per cycle (1 SYNC + {n} one-byte TPDOs): " +
          ", ".join(f"{k}: {v}" for k, v in limits.items()))
    for name, (cps, fps) in results.items():
        print(f"\n{name}: {cps:9.1f} cycles/s  {fps:10.1f} frames/s")
        for lname, bits in limits.items():
            limit = args.bitrate / bits
            print(f"   vs {args.bitrate / 1e6:g} Mbit/s limit ({lname}): {limit:7.1f} cycles/s"
                  f"  -> ratio twin/bus = {cps / limit:6.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
