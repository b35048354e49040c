"""Where the live Foxglove server's CPU goes (docs/robotics.md, *Cost*, "Where the live server's
time goes"): bench/robotics_outputs.py's ``live, 1 viewer`` pass, each thread's CPU apart.

    .venv/bin/python bench/robotics_live_threads.py [--scenes matrix57 skin4096] [--rounds 2] [--poll-s 0.1]

Per scene and round, alternating: ``bare``; ``live`` (as the bench); ``live, made before``: every
cycle's messages encoded before the run, the publisher only handing them to the SDK (what the
encoding costs in the run); ``live, by position``: the publisher's encode and SDK ``log`` of each
cycle timed by its place in the burst (the first after a wake-up against the rest; the timer's own
cost subtracted). Printed per cycle: the publisher thread's CPU, the SDK's (tokio) threads' and
their voluntary context switches (wake-ups), the outputs' threads over ``bare`` in per cent. Then
the CPU a thread pays to be woken by ``time.sleep``, ``Event.wait`` and ``Lock.acquire`` with a
timeout (the publisher's period). Every figure is thread CPU from ``/proc/self/task/*``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


def _tasks() -> dict[int, tuple[str, int, int]]:
    """{tid: (name, CPU ns, voluntary context switches)} of this process's threads."""
    out = {}
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/comm") as f:
                name = f.read().strip()
            with open(f"/proc/self/task/{task}/schedstat") as f:
                ns = int(f.read().split()[0])
            with open(f"/proc/self/task/{task}/status") as f:
                vol = int(f.read().split("voluntary_ctxt_switches:")[1].split()[0])
        except (OSError, IndexError, ValueError):
            continue
        out[int(task)] = (name, ns, vol)
    return out


def one(scene, frames, mode: str, tmp: Path, made: dict, positions: dict) -> dict:
    import robotics_outputs as bench
    from fusion_center.robotics import mcap_out, outputs as outputs_module

    snaps = []
    real = bench._thread_cpu_ns

    def marked(*, exclude, before=None):  # the bench's window: snapshot every thread there
        snaps.append((_tasks(), [t.native_id for t in threading.enumerate() if t.name == "robotics-publisher"]))
        return real(exclude=exclude, before=before)

    publish_all = outputs_module.RoboticsOutputs._publish_all
    tt = time.thread_time_ns
    timer = min(-(tt() - tt()) for _ in range(50))

    def from_made(self, items):
        for record, _, _ in items:
            self.live.log(*made[record["cycle"]])
            self.cycles += 1

    def by_position(self, items):
        done = []
        for k, (record, readings, _) in enumerate(items):
            a = tt()
            done.append(mcap_out.encode(self.topics, record, readings))
            positions.setdefault(("encode", min(k, 1)), []).append(tt() - a - timer)
        for k, (t, messages) in enumerate(done):
            a = tt()
            self.live.log(t, messages)
            positions.setdefault(("log", min(k, 1)), []).append(tt() - a - timer)
            self.cycles += 1

    patch = {"live, made before": from_made, "live, by position": by_position}.get(mode)
    bench._thread_cpu_ns = marked
    if patch is not None:
        outputs_module.RoboticsOutputs._publish_all = patch
    try:
        cpu, main_cpu, others, cycles, _ = bench.one_pass(scene, frames, "bare" if mode == "bare" else "live, 1 viewer",
                                                          tmp)
    finally:
        bench._thread_cpu_ns = real
        outputs_module.RoboticsOutputs._publish_all = publish_all
    (before, _), (after, publishers) = snaps
    pub = sdk = switches = 0
    for tid, (name, ns, vol) in after.items():
        _, ns0, vol0 = before.get(tid, (name, 0, 0))
        if tid in publishers:
            pub += ns - ns0
        elif name.startswith("tokio"):
            sdk += ns - ns0
            switches += vol - vol0
    return {"process": cpu / cycles * 1e6, "others": others / cycles * 1e6, "publisher": pub / cycles / 1e3,
            "sdk": sdk / cycles / 1e3, "sdk_wakeups": switches / cycles}


def wake_costs(n: int = 30) -> dict[str, float]:
    """Thread CPU (us) a wake-up of an idle thread costs, by how it waits 0.1 s."""
    event, lock = threading.Event(), threading.Lock()
    lock.acquire()
    out = {}
    for name, wait in (("time.sleep(0.1)", lambda: time.sleep(0.1)), ("Event.wait(0.1)", lambda: event.wait(0.1)),
                       ("Lock.acquire(timeout=0.1)", lambda: lock.acquire(timeout=0.1))):
        def run(name=name, wait=wait):
            t0 = time.thread_time_ns()
            for _ in range(n):
                wait()
            out[name] = (time.thread_time_ns() - t0) / n / 1e3
        th = threading.Thread(target=run)
        th.start()
        th.join()
    return out


def main() -> None:
    import can
    import robotics_outputs as bench

    from fusion_center.robotics import mcap_out, outputs as outputs_module
    from fusion_center.robotics.topics import TopicMap
    from fusion_center.service.traces import replay_trace
    from taxel_net.scene import load_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["matrix57", "skin4096"])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--cycles", type=int, default=300)
    ap.add_argument("--poll-s", type=float, default=None, help="the publisher's period (default its own POLL_S)")
    args = ap.parse_args()
    if args.poll_s is not None:
        outputs_module.POLL_S = args.poll_s
    modes = ("bare", "live", "live, made before", "live, by position")
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for scene_name in args.scenes:
            scene = load_scene(scene_name)
            trace = bench.record_trace(scene_name, args.cycles, tmp)
            frames = list(can.LogReader(str(trace)))
            records, _ = replay_trace(scene, trace)
            topics = TopicMap(scene)
            made = {r["cycle"]: mcap_out.encode(topics, r) for r in records}
            load0 = os.getloadavg()[0]
            got: dict[str, list] = {m: [] for m in modes}
            positions: dict = {}
            for _ in range(args.rounds):
                for mode in modes:
                    got[mode].append(one(scene, frames, mode, tmp, made, positions))
            print(f"{scene_name}: {args.cycles} cycles x {args.rounds} rounds, per cycle, median of rounds "
                  f"(poll {outputs_module.POLL_S} s; load average {load0:.1f} -> {os.getloadavg()[0]:.1f})")
            bare = [r["process"] for r in got["bare"]]
            for mode in modes[1:]:
                med = {k: statistics.median(r[k] for r in got[mode]) for k in got[mode][0]}
                share = statistics.median(r["others"] / b * 100 for r, b in zip(got[mode], bare))
                print(f"  {mode:18s} publisher {med['publisher']:6.1f} us, SDK threads {med['sdk']:5.1f} us "
                      f"({med['sdk_wakeups']:.2f} wake-ups), outputs' threads +{med['others']:6.1f} us = "
                      f"+{share:.1f} % of bare")
            for (step, first), values in sorted(positions.items()):
                print(f"  {step:6s} of a burst's {'first cycle' if first == 0 else 'other cycles'}: "
                      f"median {statistics.median(values) / 1e3:6.1f} us ({len(values)} cycles)")
    for name, us in wake_costs().items():
        print(f"wake-up of an idle thread by {name:26s} {us:6.1f} us of its CPU")


if __name__ == "__main__":
    main()
