"""Does batching a cycle's Zenoh puts save CPU? (issue 24: ``--zenoh`` puts up to three samples a
cycle - record, grip, contact - each express.)

    .venv/bin/python bench/zenoh_cycle_puts.py [--cycles 300] [--rounds 2]

A session as ``--zenoh`` opens it (loopback, scouting off), a subscriber in another process on
the three keys; at 100 Hz (a 10 ms sleep between cycles, as the SYNC period), per cycle,
alternating round by round:

* ``3 express``: three express puts (1.5 kB, 200 B, 200 B) - what ``ZenohPublisher`` does in a
  cycle with a grip message and a contact event;
* ``2 batched + 1 express``: the first two from publishers declared ``express=False`` (Zenoh
  appends them to the link's current batch), the last express (sends the batch with it);
* ``1 express``: the record alone.

Printed: the caller's CPU a cycle (thread time), the CPU of Zenoh's transmit thread(s) (``tx-*``,
``/proc/self/task/*/schedstat``) and their context switches a cycle, the samples received (none
may be lost), the load average.
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

SUBSCRIBER = r'''
import json, sys, time, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"peer"'); c.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
c.insert_json5("scouting/multicast/enabled", "false"); c.insert_json5("listen/endpoints", "[]")
n = [0]
with zenoh.open(c) as s:
    subs = [s.declare_subscriber(k, lambda sample: n.__setitem__(0, n[0] + 1)) for k in ("bench/a", "bench/b", "bench/c")]
    print("ready", flush=True)
    sys.stdin.readline()
    time.sleep(0.5)
    print(n[0], flush=True)
'''
MODES = ("3 express", "2 batched + 1 express", "1 express")


def _tx_threads() -> dict:
    out = {}
    for task in os.listdir("/proc/self/task"):
        try:
            if not open(f"/proc/self/task/{task}/comm").read().startswith("tx"):
                continue
            status = open(f"/proc/self/task/{task}/status").read()
            switches = sum(int(status.split(f"{kind}_ctxt_switches:")[1].split()[0])
                           for kind in ("voluntary", "nonvoluntary"))
            out[task] = (int(open(f"/proc/self/task/{task}/schedstat").read().split()[0]), switches)
        except OSError:
            continue
    return out


def main() -> int:
    import zenoh

    from fusion_center.service.zenoh_config import open_session, resolve

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{random.randint(40000, 60000)}"
    session = open_session(*resolve(config_flag=None, listen=[endpoint], connect=None, mode=None))
    sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, endpoint], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                           text=True)
    assert sub.stdout.readline().strip() == "ready"
    kw = dict(encoding=zenoh.Encoding.APPLICATION_JSON, congestion_control=zenoh.CongestionControl.DROP,
              priority=zenoh.Priority.DATA)
    express = {k: session.declare_publisher(f"bench/{k}", express=True, **kw) for k in "abc"}
    batched = {k: session.declare_publisher(f"bench/{k}", express=False, **kw) for k in "abc"}
    time.sleep(1.0)
    record, small = b'{"x":' + b"1" * 1500 + b"}", b'{"y":' + b"2" * 200 + b"}"
    sent = 0
    print(f"{args.cycles} cycles at 100 Hz x {args.rounds} rounds (load average {os.getloadavg()[0]:.1f})", flush=True)
    for _ in range(args.rounds):
        for mode in MODES:
            before, t0 = _tx_threads(), time.thread_time()
            for _ in range(args.cycles):
                if mode == "3 express":
                    express["a"].put(record), express["b"].put(small), express["c"].put(small)
                elif mode == "1 express":
                    express["a"].put(record)
                else:
                    batched["a"].put(record), batched["b"].put(small), express["c"].put(small)
                time.sleep(0.01)
            caller = time.thread_time() - t0
            after = _tx_threads()
            tx_ns = sum(after[t][0] - before[t][0] for t in after if t in before)
            tx_sw = sum(after[t][1] - before[t][1] for t in after if t in before)
            sent += args.cycles * (1 if mode == "1 express" else 3)
            print(f"  {mode:22s} caller {caller / args.cycles * 1e6:6.1f} us a cycle, tx thread "
                  f"{tx_ns / args.cycles / 1e3:6.1f} us, {tx_sw / args.cycles:.2f} switches a cycle", flush=True)
    sub.stdin.write("done\n")
    sub.stdin.flush()
    print(f"received {sub.stdout.readline().strip()} of {sent} (load average {os.getloadavg()[0]:.1f})")
    sub.wait(10)
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
