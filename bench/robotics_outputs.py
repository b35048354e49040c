"""The centre's CPU per cycle with and without the robotics outputs (issue 24: at most +5 %),
side by side in one run, at matrix57 and skin4096.

    .venv/bin/python bench/robotics_outputs.py [--cycles 300] [--rounds 3] [--scenes matrix57 skin4096]

Per scene, a demo records a CAN trace once (``--log``); its frames are read into memory. Then,
round after round, the same frames go through a fresh centre - the event stream, the cycle
assembler and the per-cycle pipeline, as ``replay`` does; the boot's frames at once, unmeasured,
then from the first SYNC on paced at the trace's own times (a SYNC every 10 ms, as live) - once
per variant, in turn:

* ``bare``: no output;
* ``mcap``: ``--mcap`` (the publisher thread, the SDK's MCAP writer);
* ``live, no viewer``: ``--foxglove`` with nobody connected;
* ``live, 1 viewer``: ``--foxglove`` with a WebSocket client in another process subscribed to
  every channel and reading everything (its CPU is not the centre's);
* ``mcap + live``: both, the viewer connected;
* ``mcap in the cycle`` (not a command's: ``RoboticsOutputs(threaded=False)``, as ``replay``): the
  MCAP file written by the thread that made the record, no publisher thread.

Measured, from the first frame to the last cycle published (the steady state: opening and closing
the outputs - the server's start and stop, the file's summary - happen once a run and are left
out), per cycle:

* ``process``: this process's CPU time (``time.process_time``: every thread - the centre's, the
  publisher, the SDK's Rust threads of the writer and the server) - the side-by-side figure, and
  its ratio to ``bare`` of the same round (paired: the variants of a round run back to back);
* ``other threads``: the CPU time of every thread but the centre's (``/proc/self/task/*/schedstat``,
  ns) - the publisher, the SDK's threads, and numpy's BLAS threads, which run in ``bare`` too -
  minus the same figure of ``bare`` in that round: what the outputs add besides the callback's
  append, as a share of ``bare``'s process CPU per cycle. On a shared, loaded host the process
  figure moves by +-10-20 % from pass to pass whatever runs; this one depends less on that.

What it leaves out is the reading of sockets and python-can's frame handling of a live run (the
centre's own per-cycle CPU is larger live, so the ratios here are upper bounds). Printed: the
median over rounds; the host's load average before and after.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

VIEWER = r'''
import asyncio, json, sys
from websockets.asyncio.client import connect

async def main(port):
    async with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        channels = {}
        await ws.recv()  # serverInfo
        while not channels:
            msg = json.loads(await ws.recv())
            if msg["op"] == "advertise":
                channels = {c["id"]: c for c in msg["channels"]}
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": cid} for k, cid in enumerate(channels)]}))
        print("subscribed", flush=True)
        n = 0
        try:
            while True:
                await ws.recv()
                n += 1
        except Exception:
            pass
        print(n, flush=True)

asyncio.run(main(int(sys.argv[1])))
'''

VARIANTS = ("bare", "mcap", "live, no viewer", "live, 1 viewer", "mcap + live", "mcap in the cycle")


def record_trace(scene_name: str, cycles: int, out: Path) -> Path:
    trace = out / f"{scene_name}.log"
    subprocess.run([sys.executable, "-m", "fusion_center.cli", "demo", "--scene", scene_name, "--cycles", str(cycles),
                    "--log", str(trace), "--no-live"], cwd=ROOT, check=True, capture_output=True, text=True)
    return trace


def one_pass(scene, frames, variant: str, tmp: Path) -> tuple[float, int, dict]:
    from fusion_center.robotics.outputs import RoboticsOutputs
    from fusion_center.service.cycles import CycleAssembler
    from fusion_center.service.pipeline import CyclePipeline
    from fusion_center.service.stream import EventStream
    from fusion_center.service.traces import trace_channel

    outputs = viewer = None
    if variant != "bare":
        mcap = tmp / "bench.mcap" if "mcap" in variant else None
        live = ("127.0.0.1", 0) if "live" in variant else None
        outputs = RoboticsOutputs(scene, mcap=mcap, foxglove=live, threaded=variant != "mcap in the cycle")
        if variant in ("live, 1 viewer", "mcap + live"):
            viewer = subprocess.Popen([sys.executable, "-c", VIEWER, str(outputs.live.port)], stdout=subprocess.PIPE,
                                      text=True)
            assert viewer.stdout.readline().strip() == "subscribed"
            end = time.monotonic() + 10
            while not outputs.live.watched and time.monotonic() < end:
                time.sleep(0.01)
    main_tid = threading.get_native_id()
    assembler = CycleAssembler(scene)
    pipeline = CyclePipeline(scene)
    closed: list = []
    stream = EventStream(assembler, on_closed=closed.append)
    cycles = 0
    # the boot (boot-ups, the SDO configuration) unmeasured: fed at once, up to the first SYNC
    start = next(k for k, msg in enumerate(frames) if msg.arbitration_id == 0x080 and not msg.is_extended_id)
    for msg in frames[:start]:
        stream.receive(msg, trace_channel(msg, ".log"))
    first = frames[start].timestamp
    wall0 = time.monotonic()
    others0 = _thread_cpu_ns(exclude=main_tid)
    main0 = time.thread_time()
    cpu0 = time.process_time()
    for msg in frames[start:]:
        ahead = (msg.timestamp - first) - (time.monotonic() - wall0)
        if ahead > 0.001:
            time.sleep(ahead)  # the trace's pace: a SYNC every period, as live
        stream.receive(msg, trace_channel(msg, ".log"))
        while closed:
            item = closed.pop(0)
            record = pipeline.evaluate(item)
            cycles += 1
            if outputs is not None:
                outputs.on_cycle(record, item)
    if outputs is not None:  # steady state: every cycle published (the publisher's next tick)
        end = time.monotonic() + 30
        while (outputs._queue or outputs.cycles + (outputs.live.unwatched if outputs.live else 0) < cycles) \
                and time.monotonic() < end:
            time.sleep(0.005)
    cpu = time.process_time() - cpu0
    main_cpu = time.thread_time() - main0
    others = _thread_cpu_ns(exclude=main_tid, before=others0) * 1e-9  # the publisher, the SDK's threads
    stats = outputs.close() if outputs is not None else {}  # once per run: not per cycle
    if viewer is not None:
        viewer.terminate()
        viewer.wait(timeout=10)
    return cpu, main_cpu, others, cycles, stats


def _thread_cpu_ns(*, exclude: int, before: dict | None = None):
    """{tid: ns on CPU} of this process's threads but ``exclude`` (``/proc/self/task/*/schedstat``);
    with ``before``: the total since then."""
    now = {}
    for task in os.listdir("/proc/self/task"):
        tid = int(task)
        if tid == exclude:
            continue
        try:
            with open(f"/proc/self/task/{task}/schedstat") as f:
                now[tid] = int(f.read().split()[0])
        except OSError:
            continue
    if before is None:
        return now
    return sum(ns - before.get(tid, 0) for tid, ns in now.items())


def bus_pass(variant: str, cycles: int, tmp: Path) -> tuple[float, float, int]:
    """matrix57 on a bus: node-sim in its own process, the centre in this one on udp_multicast
    (loopback) - its whole CPU per cycle, receive path included (from the first SYNC to the
    last record, boot and outputs' opening and closing left out): (process s, other threads s, cycles)."""
    import random

    from fusion_center.robotics.outputs import RoboticsOutputs
    from fusion_center.service import FusionService
    from taxel_net.scene import load_scene

    group, port = "239.74.163.2", random.randint(40000, 60000)
    scene = load_scene("matrix57")
    sim = subprocess.Popen([sys.executable, "-m", "node_sim.cli", "--scene", "matrix57", "--interface", "udp_multicast",
                            "--channel", group, "--bus-option", f"port={port}", "--bus-option", "hop_limit=0"],
                           cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    outputs = viewer = None
    try:
        assert "ready" in sim.stdout.readline()
        with FusionService(scene, interface="udp_multicast", channels=[group], bus_kwargs={"port": port, "hop_limit": 0},
                           keep_records=False) as service:
            if variant != "bare":
                outputs = RoboticsOutputs(scene, mcap=tmp / "bus.mcap" if "mcap" in variant else None,
                                          foxglove=("127.0.0.1", 0) if "live" in variant else None,
                                          threaded=variant != "mcap in the cycle")
                outputs.attach(service)
                if variant in ("live, 1 viewer", "mcap + live"):
                    viewer = subprocess.Popen([sys.executable, "-c", VIEWER, str(outputs.live.port)],
                                              stdout=subprocess.PIPE, text=True)
                    assert viewer.stdout.readline().strip() == "subscribed"
            service.boot(5.0)
            main_tid = threading.get_native_id()
            others0 = _thread_cpu_ns(exclude=main_tid)
            cpu0 = time.process_time()
            service.run(cycles)
            if outputs is not None:
                end = time.monotonic() + 30
                while outputs._queue and time.monotonic() < end:
                    time.sleep(0.005)
            cpu = time.process_time() - cpu0
            # the centre's own threads (receive, SYNC, heartbeat) are "others" here too: kept apart
            # by name - the publisher's and the SDK's
            publisher = outputs._thread.native_id if outputs is not None and outputs._thread is not None else None
            others = _named_cpu_ns(others0, publisher) * 1e-9
            done = service.stats.records
    finally:
        if outputs is not None:
            outputs.close()
        if viewer is not None:
            viewer.terminate()
            viewer.wait(timeout=10)
        sim.terminate()
        sim.wait(10)
    return cpu, others, done


def _named_cpu_ns(before: dict, publisher: int | None) -> int:
    """CPU ns since ``before`` of the outputs' threads: the publisher (its thread id) and the
    SDK's (tokio) ones."""
    total = 0
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/comm") as f:
                name = f.read().strip()
            if not (int(task) == publisher or name.startswith("tokio")):
                continue
            with open(f"/proc/self/task/{task}/schedstat") as f:
                total += int(f.read().split()[0]) - before.get(int(task), 0)
        except OSError:
            continue
    return total


def main() -> None:
    import can

    from taxel_net.scene import load_scene

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--scenes", nargs="+", default=["matrix57", "skin4096"])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--bus", action="store_true",
                        help="instead: matrix57 live on udp_multicast against node-sim in another process (the "
                             "centre's whole CPU per cycle, receive path included)")
    parser.add_argument("--poll-s", type=float, default=None,
                        help="the publisher's period (fusion_center.robotics.outputs.POLL_S; default its own)")
    args = parser.parse_args()
    if args.bus:
        with tempfile.TemporaryDirectory() as tmp_name:
            per: dict[str, list] = {v: [] for v in args.variants}
            extra: dict[str, list] = {v: [] for v in args.variants}
            load0 = os.getloadavg()[0]
            for _ in range(args.rounds):
                for variant in args.variants:
                    cpu, others, done = bus_pass(variant, args.cycles, Path(tmp_name))
                    per[variant].append(cpu / done * 1e6)
                    extra[variant].append(others / done * 1e6)
            print(f"matrix57 on udp_multicast, node-sim in another process: {args.cycles} cycles x {args.rounds} "
                  f"rounds, the centre's CPU per cycle (median; load average {load0:.1f} -> {os.getloadavg()[0]:.1f})")
            base = per.get("bare")
            for variant in args.variants:
                line = f"  {variant:<17} process {statistics.median(per[variant]):8.1f} us"
                if base and variant != "bare":
                    ratios = [v / b for v, b in zip(per[variant], base)]
                    line += (f" x{statistics.median(ratios):.3f} of bare (" + ", ".join(f"{r:.3f}" for r in ratios)
                             + f"); publisher + SDK threads {statistics.median(extra[variant]):6.1f} us = "
                             f"+{100 * statistics.median([e / b for e, b in zip(extra[variant], base)]):.1f} % of bare")
                print(line, flush=True)
        return
    if args.poll_s is not None:
        from fusion_center.robotics import outputs

        outputs.POLL_S = args.poll_s
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for scene_name in args.scenes:
            scene = load_scene(scene_name)
            frames = list(can.LogReader(str(record_trace(scene_name, args.cycles, tmp))))
            per: dict[str, list] = {v: [] for v in args.variants}
            added: dict[str, list] = {v: [] for v in args.variants}
            load0 = os.getloadavg()[0]
            for _ in range(args.rounds):
                for variant in args.variants:
                    cpu, main_cpu, others, cycles, _ = one_pass(scene, frames, variant, tmp)
                    per[variant].append(cpu / cycles * 1e6)
                    added[variant].append(others / cycles * 1e6)
            base = per.get("bare") or [1.0] * args.rounds
            print(f"{scene_name}: {args.cycles} cycles x {args.rounds} rounds, CPU per cycle (median of rounds; "
                  f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f})")
            for variant in args.variants:
                line = f"  {variant:<16} process {statistics.median(per[variant]):8.1f} us"
                if base and variant != "bare":
                    ratios = [v / b for v, b in zip(per[variant], base)]
                    line += f" x{statistics.median(ratios):.3f} of bare (" + ", ".join(f"{r:.3f}" for r in ratios) + ")"
                    extra = [a - b for a, b in zip(added[variant], added["bare"])] if "bare" in added \
                        else added[variant]
                    shares = [e / b for e, b in zip(extra, base)]
                    line += (f"; other threads +{statistics.median(extra):6.1f} us = "
                             f"+{100 * statistics.median(shares):.1f} % of bare")
                print(line, flush=True)


if __name__ == "__main__":
    main()
