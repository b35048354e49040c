"""Junk flood: does a bus full of junk frames make the centre count a frame in the wrong cycle?

    .venv/bin/python bench/junk_flood.py [--cycles 300] [--rate 20000] [--repeat 1]

The demo set-up (the 57 node twins of scenes/matrix57.toml and the centre on one private
virtual bus, one process) plus a third bus object that floods the channel with junk at
``--rate`` frames/s (0 = as fast as it can): 11-bit IDs of no node, wrong-length TPDOs, 29-bit
frames, remote frames. Every record is checked against the physics (the twins' canonical
readings of that cycle, decided with eqs 1-4): a record whose received decisions differ from
the physics of its cycle carries a *misattributed* frame (issue 10: 16/300 at 19k junk
frames/s, 150/300 at 29k/s, when a PDO delayed past the next SYNC was taken for an answer to
it). Prints per run: junk frames sent and their rate, records complete / degraded (a node's
PDO came late and was dropped: the cycle is fused without it, marked ``degraded``) /
undecided, and misattributed (goal: 0).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from fusion_center.core.encoding import local_decision  # noqa: E402
from fusion_center.service import FusionService  # noqa: E402
from fusion_center.service.cycle_records import MALFORMED  # noqa: E402
from node_sim import physics  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402

SCENE = ROOT / "scenes" / "matrix57.toml"


def junk_frames() -> list[can.Message]:
    frames = [can.Message(arbitration_id=0x7F0 + k, data=bytes(8), is_extended_id=False) for k in range(8)]
    frames += [can.Message(arbitration_id=0x180 + nid, data=b"\x01\x02", is_extended_id=False)
               for nid in (3, 18, 40)]  # TPDO1 of a node, wrong length
    frames += [can.Message(arbitration_id=0x18FF0000 + k, data=b"\x01", is_extended_id=True) for k in range(4)]
    frames += [can.Message(arbitration_id=0x7E0, is_remote_frame=True, is_extended_id=False)]
    return frames


def flood(channel: str, rate: float, stop: threading.Event, sent: list[int]) -> None:
    bus = can.Bus(interface="virtual", channel=channel)
    frames = junk_frames()
    k = 0
    start = time.perf_counter()
    try:
        while not stop.is_set():
            bus.send(frames[k % len(frames)])
            k += 1
            if rate > 0 and k % 64 == 0:
                ahead = k / rate - (time.perf_counter() - start)
                if ahead > 0:
                    time.sleep(ahead)
    finally:
        sent.append(k)
        sent.append(time.perf_counter() - start)
        bus.shutdown()


def run_once(scene, cycles: int, rate: float) -> dict:
    from node_sim.rig import Rig

    channel = f"flood-{uuid.uuid4().hex[:8]}"
    service = FusionService(scene, interface="virtual", channels=[channel])
    rig = Rig(scene, interface="virtual", channel=[channel])
    stop = threading.Event()
    sent: list = []
    flooder = threading.Thread(target=flood, args=(channel, rate, stop, sent), daemon=True)
    with service:
        rig.start()
        service.boot(3.0)
        flooder.start()
        try:
            service.run(cycles)
        finally:
            stop.set()
            flooder.join(5)
            rig.stop()
    return check(scene, service.records, sent, service.stream.counters())


def check(scene, records, sent, counters) -> dict:
    figures = check_records(scene, records)
    return {"junk": sent[0], "junk_rate": sent[0] / sent[1] if sent[1] else 0.0, **figures,
            "late": counters.get("late", 0), "malformed": sum(counters.get(name, 0) for name in MALFORMED)}


def check_records(scene, records) -> dict:
    """Records against the physics of their cycle: ``misattributed`` counts the records whose
    received decisions differ from the twins' canonical decisions of that cycle (eqs 1-4)."""
    zeta = np.array([t.zeta_mv for t in scene.taxels])
    noise = np.array([t.noise_mv for t in scene.taxels])
    labels = [t.node_id for t in scene.taxels]
    wrong = complete = degraded = undecided = 0
    for r in records:
        if r["decision"] == "undecided":
            undecided += 1
        if r["n_received"] == 0:
            continue
        u = local_decision(physics.sample_readings(scene, r["cycle"]), noise, zeta, "pm1")
        physics_present = {labels[i] for i in np.flatnonzero(u == 1)}
        received_present = set(r["present_nodes"])
        if r["n_received"] == scene.n:
            complete += 1
            wrong += received_present != physics_present
        else:
            degraded += 1
            # the received nodes' decisions must still be this cycle's; the others are every node
            # the record lists by state: missing, silent, and live ones not operational at the
            # SYNC (stopped, pre-operational, ...: no PDO, CiA 301)
            absent = set().union(*r["nodes_by_state"].values())
            wrong += received_present != (physics_present - absent)
    return {"records": len(records), "complete": complete, "degraded": degraded, "undecided": undecided,
            "misattributed": wrong}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=300)
    ap.add_argument("--rate", type=float, default=20000.0, help="junk frames/s (0: as fast as possible)")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args(argv)
    scene = load_scene(SCENE)
    for _ in range(args.repeat):
        f = run_once(scene, args.cycles, args.rate)
        print(f"junk {f['junk']} frames at {f['junk_rate']:.0f}/s: {f['records']} records, {f['complete']} complete, "
              f"{f['degraded']} degraded, {f['undecided']} undecided, {f['late']} late PDOs dropped, "
              f"misattributed {f['misattributed']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
