"""The centre's CPU per cycle with ``--zenoh`` and ``--foxglove`` in the centre's process (before)
and in the robotics bridge process (``fusion_center.robotics.bridge_link``), side by side in one
run, at matrix57 and skin4096 (issue 24: the live server and Zenoh add at most 5 % to the centre).

    .venv/bin/python bench/robotics_bridge.py [--cycles 300] [--rounds 3] [--scenes matrix57 skin4096] [--log]

Per scene, a demo records a CAN trace once; its frames go, round after round, through a fresh
centre (event stream, cycle assembler, pipeline: as ``bench/robotics_outputs.py``, paced at the
trace's times - a SYNC every 10 ms), once per variant, in turn:

* ``bare``: no output;
* ``zenoh in-process``: :class:`ZenohPublisher` called with each record (today's ``--zenoh``
  before the bridge), a subscriber in another process;
* ``zenoh bridge``: the bridge with ``--zenoh``'s publication, the same subscriber;
* ``foxglove in-process``: ``RoboticsOutputs(foxglove=..., threaded=True)`` (the publisher thread,
  the SDK's threads), a viewer in another process subscribed to every channel;
* ``foxglove bridge``: the bridge's live server, the same viewer;
* ``both in-process`` / ``both bridge``: Zenoh and the live server, subscriber and viewer.

Measured from the first cycle after every consumer has had a message (and 20 cycles at least;
the warm-up - matching, subscription - is left out) to the last cycle plus 0.3 s (the outputs'
queues drained), per cycle: the centre's process CPU (``time.process_time``: every thread of it)
and, with the bridge, the bridge process's CPU (its threads' ``/proc/PID/task/*/schedstat``).
Printed per variant, medians of rounds: first the outputs' own CPU in the centre - the thread
time inside the record callbacks (the hand-over; in process the put or the queue append) plus
the CPU of the process's other threads (Zenoh's, the publisher's, the SDK's) over ``bare``'s
other threads - as % of ``bare``, the bridge process's CPU and their sum (the figure that
holds on a loaded host); then the process totals: the centre's CPU, its excess over ``bare`` of
the same round (paired, % of bare), the bridge's CPU and the total (centre + bridge) over
``bare`` (on a shared 2-core host these move by 10-20 % from pass to pass whatever runs).
``--log``: every variant writes the decision log (to /dev/null), whose line the hand-over and the
Zenoh publisher reuse. The host's load average is printed before and after.
"""

from __future__ import annotations

import argparse
import os
import selectors
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from robotics_outputs import VIEWER as _VIEWER, record_trace  # noqa: E402

VIEWER = _VIEWER.replace('print("subscribed", flush=True)\n        n = 0\n        try:\n            while True:\n'
                         '                await ws.recv()\n                n += 1',
                         'print("subscribed", flush=True)\n        n = 0\n        try:\n            while True:\n'
                         '                m = await ws.recv()\n                n += 1\n'
                         '                if n == 1: print("got", flush=True)')
assert 'print("got"' in VIEWER

SUBSCRIBER = r'''
import json, sys, time, zenoh
config = zenoh.Config()
config.insert_json5("mode", '"peer"')
config.insert_json5("scouting/multicast/enabled", "false")
config.insert_json5("listen/endpoints", "[]")
config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{sys.argv[1]}"]))
n = [0]
def on_sample(sample):
    n[0] += 1
    if n[0] == 1:
        print("got", flush=True)
with zenoh.open(config) as session:
    sub = session.declare_subscriber(f"taxel/{sys.argv[2]}/**", on_sample)
    print("subscribed", flush=True)
    sys.stdin.read()
'''

VARIANTS = ("bare", "zenoh in-process", "zenoh bridge", "foxglove in-process", "foxglove bridge",
            "both in-process", "both bridge")
WARM_CYCLES = 20


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _proc_cpu_ns(pid: int) -> int:
    total = 0
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/schedstat") as f:
                total += int(f.read().split()[0])
        except OSError:
            continue
    return total


def one_pass(scene, scene_name, frames, variant: str, log: bool):
    from fusion_center.robotics.bridge_link import RoboticsBridge
    from fusion_center.robotics.outputs import RoboticsOutputs
    from fusion_center.service.cycles import CycleAssembler
    from fusion_center.service.pipeline import CyclePipeline
    from fusion_center.service.records import RecordWriter
    from fusion_center.service.stream import EventStream
    from fusion_center.service.traces import trace_channel
    from fusion_center.service.zenoh_publisher import ZenohPublisher

    zenoh = "zenoh" in variant or "both" in variant
    fox = "foxglove" in variant or "both" in variant
    callbacks, closers, consumers = [], [], []
    bridge = None
    port = _free_port() if zenoh else None
    try:
        if variant.endswith("bridge"):
            bridge = RoboticsBridge(scene, {"scene": scene_name}, zenoh={"listen": [f"tcp/127.0.0.1:{port}"]}
                                    if zenoh else None, foxglove=("127.0.0.1", 0) if fox else None).open()
            callbacks.append(bridge.on_cycle)
            closers.append(bridge.close)
            fox_port = bridge.ready.get("foxglove", {}).get("port")
        else:
            if zenoh:
                pub = ZenohPublisher(scene.name, listen=[f"tcp/127.0.0.1:{port}"]).open()
                callbacks.append(lambda record, closed: pub(record))
                closers.append(pub.close)
            if fox:
                outputs = RoboticsOutputs(scene, foxglove=("127.0.0.1", 0), threaded=True)
                callbacks.append(outputs.on_cycle)
                closers.append(outputs.close)
                fox_port = outputs.live.port
        if zenoh:
            consumers.append(subprocess.Popen([sys.executable, "-c", SUBSCRIBER, str(port), scene.name],
                                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True))
        if fox:
            consumers.append(subprocess.Popen([sys.executable, "-c", VIEWER, str(fox_port)], stdout=subprocess.PIPE,
                                              text=True))
        for c in consumers:
            assert c.stdout.readline().strip() == "subscribed"
        return _measure(scene, frames, callbacks, consumers, bridge, log, CycleAssembler, CyclePipeline,
                        EventStream, trace_channel, RecordWriter)
    finally:
        for close in closers:
            close()
        for c in consumers:
            if c.stdin is not None:
                c.stdin.close()
            c.terminate()
            c.wait(timeout=10)


def _measure(scene, frames, callbacks, consumers, bridge, log, CycleAssembler, CyclePipeline, EventStream,
             trace_channel, RecordWriter):
    assembler = CycleAssembler(scene)
    pipeline = CyclePipeline(scene)
    writer = RecordWriter(os.devnull) if log else None
    closed: list = []
    stream = EventStream(assembler, on_closed=closed.append)
    start = next(k for k, msg in enumerate(frames) if msg.arbitration_id == 0x080 and not msg.is_extended_id)
    for msg in frames[:start]:
        stream.receive(msg, trace_channel(msg, ".log"))
    sel = selectors.DefaultSelector()
    waiting = set()
    for c in consumers:
        sel.register(c.stdout, selectors.EVENT_READ)
        waiting.add(c.stdout)
    first = frames[start].timestamp
    wall0 = time.monotonic()
    cycles = 0
    measuring = False
    cpu0 = bridge0 = main0 = 0
    handover = 0.0
    for msg in frames[start:]:
        ahead = (msg.timestamp - first) - (time.monotonic() - wall0)
        if ahead > 0.001:
            time.sleep(ahead)
        stream.receive(msg, trace_channel(msg, ".log"))
        while closed:
            item = closed.pop(0)
            record = pipeline.evaluate(item)
            if writer is not None:
                writer.write(record)
            t0 = time.thread_time()
            for callback in callbacks:
                callback(record, item)
            if measuring:
                handover += time.thread_time() - t0
                cycles += 1
            elif waiting:
                for key, _ in sel.select(0):
                    if key.fileobj.readline().strip() == "got":
                        waiting.discard(key.fileobj)
                        sel.unregister(key.fileobj)
                cycles += 1
            else:
                cycles += 1
                if cycles >= WARM_CYCLES:  # warm: every consumer has had a message
                    measuring, cycles = True, 0
                    cpu0 = time.process_time()
                    main0 = time.thread_time()
                    bridge0 = _proc_cpu_ns(bridge.proc.pid) if bridge is not None else 0
    assert measuring and not waiting, "the consumers never got a message"
    time.sleep(0.3)  # the outputs' queues drained (the publisher's 0.1 s tick; the bridge's reading)
    cpu = time.process_time() - cpu0
    main_cpu = time.thread_time() - main0
    bridge_cpu = (_proc_cpu_ns(bridge.proc.pid) - bridge0) * 1e-9 if bridge is not None else 0.0
    dropped = bridge.dropped if bridge is not None else 0
    if writer is not None:
        writer.close()
    sel.close()
    return cpu, bridge_cpu, cycles, dropped, main_cpu, handover


def main() -> None:
    import can

    from taxel_net.scene import load_scene

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--scenes", nargs="+", default=["matrix57", "skin4096"])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--log", action="store_true", help="every variant writes the decision log (/dev/null)")
    args = parser.parse_args()
    if "bare" not in args.variants:
        args.variants.insert(0, "bare")
    with tempfile.TemporaryDirectory() as tmp_name:
        for scene_name in args.scenes:
            scene = load_scene(scene_name)
            frames = list(can.LogReader(str(record_trace(scene_name, args.cycles + 60, Path(tmp_name)))))
            centre: dict[str, list] = {v: [] for v in args.variants}
            other: dict[str, list] = {v: [] for v in args.variants}
            drops: dict[str, int] = {v: 0 for v in args.variants}
            main_: dict[str, list] = {v: [] for v in args.variants}
            calls: dict[str, list] = {v: [] for v in args.variants}
            main = main_
            load0 = os.getloadavg()
            for _ in range(args.rounds):
                for variant in args.variants:
                    cpu, bridge_cpu, cycles, dropped, main_cpu, handover = one_pass(scene, scene_name, frames,
                                                                                   variant, args.log)
                    main[variant].append(main_cpu / cycles * 1e6)
                    calls[variant].append(handover / cycles * 1e6)
                    centre[variant].append(cpu / cycles * 1e6)
                    other[variant].append(bridge_cpu / cycles * 1e6)
                    drops[variant] += dropped
            load1 = os.getloadavg()
            base = centre["bare"]
            print(f"{scene_name}{' (decision log on)' if args.log else ''}: ~{args.cycles} cycles x {args.rounds} "
                  f"rounds, CPU per cycle, median of rounds (load average 1/5/15 min "
                  f"{'/'.join(f'{x:.1f}' for x in load0)} -> {'/'.join(f'{x:.1f}' for x in load1)})")
            # the outputs' own CPU in the centre: its calls in the cycle's thread plus its other threads'
            # (the process's CPU but the cycle's thread) over bare's - less moved by the host's load
            # than the process totals
            others = {v: [c - m for c, m in zip(centre[v], main[v])] for v in args.variants}
            own = {v: [k + o - ob for k, o, ob in zip(calls[v], others[v], others["bare"])] for v in args.variants}
            print("  outputs' own CPU in the centre (its calls + its threads; % of bare), the bridge's, the sum:")
            for variant in args.variants[1:]:
                o = [100 * x / b for x, b in zip(own[variant], base)]
                t = [100 * (x + y) / b for x, y, b in zip(own[variant], other[variant], base)]
                print(f"    {variant:<20} centre {statistics.median(own[variant]):6.1f}us {statistics.median(o):+5.1f} % ("
                      + ", ".join(f"{x:+.1f}" for x in o) + f"); bridge {statistics.median(other[variant]):6.1f}us; "
                      f"total {statistics.median(t):+5.1f} % of bare", flush=True)
            print(f"  {'variant':<20} {'centre':>9} {'centre over bare (rounds)':<36} {'bridge':>9} "
                  f"{'total over bare':>16}")
            for variant in args.variants:
                c = statistics.median(centre[variant])
                if variant == "bare":
                    print(f"  {variant:<20} {c:7.1f}us   (centre's thread {statistics.median(main[variant]):.1f}us)")
                    continue
                added = [100 * (v - b) / b for v, b in zip(centre[variant], base)]
                total = [100 * (v + o - b) / b for v, o, b in zip(centre[variant], other[variant], base)]
                rounds = ", ".join(f"{a:+.1f}" for a in added)
                print(f"  {variant:<20} {c:7.1f}us {statistics.median(added):+6.1f} % ({rounds})"
                      f"{'':<{max(0, 27 - len(rounds))}} {statistics.median(other[variant]):7.1f}us "
                      f"{statistics.median(total):+8.1f} %" + (f"  ({drops[variant]} dropped)" if drops[variant]
                                                               else "")
                      + f"  (centre's thread {statistics.median(main[variant]):.1f}us, in the callbacks "
                      f"{statistics.median(calls[variant]):.1f}us)", flush=True)


if __name__ == "__main__":
    main()
