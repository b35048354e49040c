"""Zenoh's per-message floor against a TCP pipe (issue 24): one sender process, one receiver
process, nothing else - the cost and the latency of carrying an assembler part (15 kB, 100 Hz)
from one process to another, without the centre.

    .venv/bin/python bench/zenoh_floor.py [--size 15000] [--rate 100] [--messages 1000]
                                          [--modes tcp,zenoh,zenoh-batched,zenoh-fifo,zenoh-direct]

Modes (each a fresh pair of processes, run alternating ``--repeat`` times):

* ``tcp``            ``multiprocessing.connection``'s ``send_bytes`` / ``recv_bytes`` (the link
                     before issue 24), the receiver a thread blocked in ``recv_bytes``;
* ``zenoh``          the assembler link's settings: a publisher ``CongestionControl.BLOCK``,
                     express, ``Priority.REAL_TIME``, reliable; the receiver's subscriber with a
                     Python callback (zenoh-python runs it in a thread of its own: indirect);
* ``zenoh-batched``  the same, not express;
* ``zenoh-fifo``     the subscriber's samples through a ``FifoChannel`` read by a thread of ours;
* ``zenoh-direct``   the callback run in Zenoh's network thread (``Callback(indirect=False)``).

Zenoh settings to try go in the environment, which the processes inherit: ``FLOOR_ZCONFIG``
a JSON map of Zenoh configuration keys to values set on both sessions (e.g.
``'{"transport/unicast/lowlatency": true, "transport/unicast/qos/enabled": false}'``), and
Zenoh's own ``ZENOH_RUNTIME`` (e.g. ``'(rx: (handover: app), tx: (handover: app))'``).

Per mode: the latency from the sender's ``time.time()`` before the send to the receiver's
callback (p50 / p99 / max, ms; one host's clock), and the CPU per message of each process
(user + system over the run, including the runtime's own threads, divided by the messages).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import struct
import subprocess
import sys
import threading
import time


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu() -> float:
    t = os.times()
    return t.user + t.system


def _zenoh_config(listen=None, connect=None):
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps(listen or []))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(connect))
    for key, value in json.loads(os.environ.get("FLOOR_ZCONFIG", "{}")).items():
        config.insert_json5(key, json.dumps(value))
    return config


def receiver(mode: str, port: int, messages: int) -> dict:
    lat: list[float] = []
    done = threading.Event()

    def got(data: bytes) -> None:
        lat.append((time.time() - struct.unpack_from("<d", data)[0]) * 1e3)
        if len(lat) >= messages:
            done.set()

    if mode == "tcp":
        from multiprocessing.connection import Listener

        listener = Listener(("127.0.0.1", port), authkey=b"floor")
        print("ready", flush=True)
        conn = listener.accept()
        c0 = _cpu()

        def loop():
            while len(lat) < messages:
                got(conn.recv_bytes())
            done.set()
        threading.Thread(target=loop, daemon=True).start()
        done.wait(600)
        cpu = _cpu() - c0
        conn.close()
    else:
        import zenoh

        session = zenoh.open(_zenoh_config(listen=[f"tcp/127.0.0.1:{port}"]))
        key = "floor/part"
        if mode == "zenoh-fifo":
            sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(1024))

            def loop():
                while len(lat) < messages:
                    got(sub.recv().payload.to_bytes())
                done.set()
            threading.Thread(target=loop, daemon=True).start()
        elif mode == "zenoh-direct":
            sub = session.declare_subscriber(key, zenoh.handlers.Callback(
                lambda s: got(s.payload.to_bytes()), indirect=False))
        else:
            sub = session.declare_subscriber(key, lambda s: got(s.payload.to_bytes()))
        print("ready", flush=True)
        first = sys.stdin.readline()  # the sender is connected
        c0 = _cpu()
        done.wait(600)
        cpu = _cpu() - c0
        sub.undeclare()
        session.close()
    lat.sort()
    return {"received": len(lat), "p50": statistics.median(lat), "p99": lat[int(0.99 * (len(lat) - 1))],
            "max": lat[-1], "rx_cpu_us": cpu / max(len(lat), 1) * 1e6, "first": first if mode != "tcp" else ""}


def sender(mode: str, port: int, messages: int, size: int, rate: float) -> dict:
    payload = bytearray(os.urandom(size))
    period = 1.0 / rate
    if mode == "tcp":
        from multiprocessing.connection import Client

        conn = Client(("127.0.0.1", port), authkey=b"floor")
        send = conn.send_bytes
        close = conn.close
    else:
        import zenoh

        session = zenoh.open(_zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]))
        pub = session.declare_publisher("floor/part", congestion_control=zenoh.CongestionControl.BLOCK,
                                        express=mode != "zenoh-batched", priority=zenoh.Priority.REAL_TIME,
                                        reliability=zenoh.Reliability.RELIABLE)
        end = time.monotonic() + 10
        while not pub.matching_status.matching and time.monotonic() < end:
            time.sleep(0.01)
        print("connected", flush=True)

        def send(data):
            pub.put(bytes(data))

        def close():
            time.sleep(0.5)
            pub.undeclare()
            session.close()
    c0 = _cpu()
    t_next = time.monotonic()
    for _ in range(messages):
        t_next += period
        delay = t_next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        struct.pack_into("<d", payload, 0, time.time())
        send(payload)
    cpu = _cpu() - c0
    close()
    return {"tx_cpu_us": cpu / messages * 1e6}


def one(mode: str, args) -> dict:
    port = _free_port()
    me = [sys.executable, os.path.abspath(__file__), "--port", str(port), "--messages", str(args.messages),
          "--size", str(args.size), "--rate", str(args.rate)]
    rx = subprocess.Popen(me + ["--child", f"rx:{mode}"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert rx.stdout.readline().strip() == "ready"
    tx = subprocess.Popen(me + ["--child", f"tx:{mode}"], stdout=subprocess.PIPE, text=True)
    if mode != "tcp":
        assert tx.stdout.readline().strip() == "connected"
        rx.stdin.write("go\n")
        rx.stdin.flush()
    out_tx = json.loads(tx.stdout.read().strip().splitlines()[-1])
    out_rx = json.loads(rx.stdout.read().strip().splitlines()[-1])
    tx.wait(30)
    rx.wait(30)
    return {**out_rx, **out_tx, "load": os.getloadavg()[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=15000)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--messages", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--modes", default="tcp,zenoh,zenoh-batched,zenoh-fifo,zenoh-direct")
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        role, mode = args.child.split(":")
        if role == "rx":
            print(json.dumps(receiver(mode, args.port, args.messages)))
        else:
            print(json.dumps(sender(mode, args.port, args.messages, args.size, args.rate)))
        return 0
    modes = args.modes.split(",")
    print(f"{args.messages} messages of {args.size} B at {args.rate:g} Hz, sender -> receiver process, "
          f"{args.repeat} runs a mode alternating", flush=True)
    runs = {m: [] for m in modes}
    for k in range(args.repeat):
        for mode in modes:
            r = one(mode, args)
            runs[mode].append(r)
            print(f"  {mode:13s} run {k + 1}: latency p50 {r['p50']:.3f} / p99 {r['p99']:.3f} / max {r['max']:.2f} ms; "
                  f"CPU a message: sender {r['tx_cpu_us']:.0f} us, receiver {r['rx_cpu_us']:.0f} us "
                  f"(received {r['received']}, load {r['load']:.1f})", flush=True)
    print("  medians:")
    for mode in modes:
        med = {key: statistics.median(r[key] for r in runs[mode]) for key in ("p50", "p99", "tx_cpu_us", "rx_cpu_us")}
        print(f"    {mode:13s} latency p50 {med['p50']:.3f} / p99 {med['p99']:.3f} ms; CPU a message: sender "
              f"{med['tx_cpu_us']:.0f} us, receiver {med['rx_cpu_us']:.0f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
