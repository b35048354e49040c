"""The centre's receive thread per cycle, wall and CPU time: which part of SYNC -> command is the
centre's own work and which is waiting - this tree side by side with other checkouts.

    .venv/bin/python bench/grip_turn_cpu.py [--scene grasp_lift_patch] [--transport player]
                                           [--cycles 600] [--rounds 2] [--against OTHER_CHECKOUT ...]

One run per tree and round (alternately, each tree's code in its own interpreter: ``--tree``),
bench/grip_latency.py's set-up (``player``: the taxel nodes at hardware speed, the drive a twin).
In the centre, wrappers around the receive thread's turn (``taxel_net.receiver.SelectNotifiers._turn``),
its read (``_Handle.dispatch_all``), the cycle's close (``CycleAssembler._close``) and the grip
command's send (``DriveLink.send_command``) take ``time.time()`` and ``time.thread_time()``
(the thread's CPU time: a system call, ~2 µs). Printed per run: for the turn that closed each
cycle, turn begin -> command sent in wall and CPU time (p50/p90/p99 ms; CPU close to wall: the
centre's own work, not waiting for the interpreter lock or a core), split into read (the turn's
datagrams), -> the close (echo filter, feed, close) and -> the command (evaluation, send); the
closing frame's kernel stamp -> the turn's begin (the wake-up); the frames of the closing turns
(COB-IDs, most common first); the receive thread's CPU per cycle over all its turns and its turns
per cycle; the master's heartbeats' offset after their SYNC and SYNC -> command (the centre's
clock: the SYNC's feed and send, the command's send and feed) of the cycles with a heartbeat
between the two against the others; the bench's ``answers``, ``wake``, ``centre`` and SYNC -> command on the bus; the load
average before and after. CPU time is less sensitive to the host's load than the latency
(docs/grip-control.md, "2026-11-30").
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

ONE = r'''
import bisect, collections, sys, threading, time
from pathlib import Path
root = Path(sys.argv[1]); scene, transport, ncycles = sys.argv[2], sys.argv[3], int(sys.argv[4])
sys.path.insert(0, str(root)); sys.path.insert(0, str(root / "bench"))
import numpy as np
import grip_latency
from fusion_center.service import drive_link, cycles as cycles_mod, stream as stream_mod
from taxel_net import receiver

wall, cpu = time.time, time.thread_time
turns, cur, closing = [], {}, {}
syncs, beats, commands = [], [], []   # time.time() of the SYNCs sent, the master's heartbeats, the commands

def wrap(cls, name, before=None, after=None):
    fn = getattr(cls, name)
    def wrapped(self, *a, **k):
        if before is not None:
            before(self, *a)
        out = fn(self, *a, **k)
        if after is not None:
            after(self, out, *a)
        return out
    setattr(cls, name, wrapped)

def turn_begin(self, *a):
    cur.clear(); cur.update(w0=wall(), c0=cpu())
def turn_end(self, out, *a):
    turns.append((cur["w0"], cur["c0"], wall(), cpu(), cur.get("ids"), cur.get("closed")))
def read(self, msgs, *a):
    cur.update(ids=tuple(m.arbitration_id for m in msgs), wd=wall(), cd=cpu())
def closed(self, out, *a):
    cur["closed"] = out.cycle
    closing[out.cycle] = dict(cur, kernel=(self.t0_us + out.close_us) * 1e-6, we=wall(), ce=cpu())
def sent(self, out, *a):
    commands.append(wall())
    m = closing.get(cur.get("closed"))
    if m is not None and "ws" not in m:
        m["ws"], m["cs"] = wall(), cpu()
def sync(self, channel, can_id, *a):
    if can_id == 0x080:
        syncs.append(wall())
def beat(self, *a):
    if threading.current_thread().name == "master-heartbeat":
        beats.append(wall())

wrap(receiver.SelectNotifiers, "_turn", turn_begin, turn_end)
wrap(receiver._Handle, "dispatch_all", read)
wrap(cycles_mod.CycleAssembler, "_close", None, closed)
wrap(drive_link.DriveLink, "send_command", None, sent)
wrap(stream_mod.EventStream, "transmit_fed_first", sync)
wrap(stream_mod.EventStream, "transmit_all", beat)
if transport == "player":
    grip_latency.run_embedded(scene, ncycles, instrumented=False)  # the recording, unmarked
turns.clear(); closing.clear(); syncs.clear(); beats.clear(); commands.clear()
start = grip_latency.uptime().split("average:")[1].strip()
out = grip_latency.RUNS[transport](scene, ncycles)
end = grip_latency.uptime().split("average:")[1].strip()
rows = [m for m in closing.values() if "ws" in m and "wd" in m]
def p(v):
    v = np.array(v) * 1e3
    return f"p50 {np.median(v):.3f} p90 {np.percentile(v, 90):.3f} p99 {np.percentile(v, 99):.3f}"
print(f"{root}: {scene} {transport}, {len(rows)} closing turns; load average {start} -> {end}")
print("  closing turn begin -> command sent, wall", p([m["ws"] - m["w0"] for m in rows]))
print("                                      CPU ", p([m["cs"] - m["c0"] for m in rows]))
print("    read (the turn's datagrams)       CPU ", p([m["cd"] - m["c0"] for m in rows]))
print("    -> cycle closed (echoes, feed)    CPU ", p([m["ce"] - m["cd"] for m in rows]))
print("    -> command sent (evaluation)      CPU ", p([m["cs"] - m["ce"] for m in rows]))
print("  closing frame's stamp -> turn begin wall", p([max(0.0, m["w0"] - m["kernel"]) for m in rows]))
print("  closing turns' frames:", [(" ".join(f"{i:#05x}" for i in ids), n) for ids, n in
                                   collections.Counter(m["ids"] for m in rows).most_common(4)])
done = [t for t in turns if t[0] is not None]
print(f"  receive thread CPU per cycle, all turns: {sum(t[3] - t[1] for t in done) / max(1, len(rows)) * 1e3:.3f} ms;"
      f" turns per cycle {len(done) / max(1, len(rows)):.2f}")
with_beat, without = [], []
for c in commands:
    k = bisect.bisect_right(syncs, c) - 1
    if k >= 0:
        (with_beat if any(syncs[k] <= b <= c for b in beats) else without).append(c - syncs[k])
offsets = [b - syncs[k] for b in beats if (k := bisect.bisect_right(syncs, b) - 1) >= 0]
if offsets and with_beat:
    print(f"  master heartbeats: p50 {np.median(offsets) * 1e3:.2f} ms after their SYNC; SYNC -> command sent "
          f"(centre's clock) with one between: n {len(with_beat)} {p(with_beat)}; without: n {len(without)} {p(without)}")
elif offsets:
    print(f"  master heartbeats: p50 {np.median(offsets) * 1e3:.2f} ms after their SYNC; none between a SYNC and its command")
stages = out["stages"]
print("  bench: " + ", ".join(f"{s} p50 {np.median(stages[s]):.3f} p99 {np.percentile(stages[s], 99):.3f}"
                              for s in ("answers", "wake", "centre")))
print("  SYNC -> command on the bus: " + p([x * 1e-3 for x in out["lat"]]))
'''


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="grasp_lift_patch")
    ap.add_argument("--transport", choices=("udp", "player"), default="player")
    ap.add_argument("--cycles", type=int, default=600)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--against", type=Path, nargs="*", default=[], help="other checkouts, run alternately")
    args = ap.parse_args(argv)
    trees = [ROOT] + [t.resolve() for t in args.against]
    for _ in range(args.rounds):
        for tree in trees:
            out = subprocess.run([sys.executable, "-c", ONE, str(tree), args.scene, args.transport, str(args.cycles)],
                                 capture_output=True, text=True, cwd=tree)
            if out.returncode:
                print(f"{tree}: failed\n{out.stderr[-2000:]}")
                continue
            print(out.stdout, end="", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
