"""The CPU of one ``--zenoh`` put, bare (issue 24): which of Zenoh 1.x's settings lowers it?

    .venv/bin/python bench/zenoh_put_floor.py [--puts 500] [--rounds 3] [--size 1700]
                                              [--variants default,qos-off,...] [--busy 0]

One publisher process and one subscriber process, nothing else: the publisher opens a session
as ``--zenoh`` does (:func:`fusion_center.service.zenoh_config.resolve`: loopback, scouting off,
16 data batches) plus the variant's settings, declares a publisher as
:class:`~fusion_center.service.zenoh_publisher.ZenohPublisher` does (express, DROP, DATA,
``application/json``) and puts ``--size`` bytes every 10 ms (the SYNC period), ``--puts``
times after 50 unmeasured ones. The subscriber (another process, Zenoh's defaults but
loopback, the variant's ``sub`` settings) counts what it receives: none may be lost.

Measured in the publisher, per put: the calling thread's CPU (``time.thread_time``) and the
CPU of every thread of the process (``/proc/self/task/*/schedstat``), by thread name (Zenoh's
runtimes name theirs ``tx-0``, ``rx-0``, ``net-0``, ``acc-0``, ``app-0``), and the
process's total over the measured puts. The variants run alternating, ``--rounds`` times,
each a fresh pair of processes; ``--busy N`` starts N processes spinning on the CPU for the
whole run (the drop test: a cycle's puts must not be dropped with the CPU busy).

Variants (``--variants``, comma-separated; default all):

* ``default``        the project's session and publisher as they are;
* ``no-batching``    ``transport/link/tx/queue/batching/enabled: false``;
* ``time-limit-0``   ``transport/link/tx/queue/batching/time_limit: 0``;
* ``queue-2``        ``transport/link/tx/queue/size/data: 2`` (Zenoh's default; the project sets 16);
* ``alloc-init``     ``transport/link/tx/queue/allocation/mode: "init"`` (batches allocated at once);
* ``batch-8k``       ``transport/link/tx/batch_size: 8192`` (Zenoh's default 65535);
* ``tx-threads-4``   ``transport/link/tx/threads: 4`` (read into the transport manager, used
                     nowhere in Zenoh 1.x's source: expected no change);
* ``qos-off``        ``transport/unicast/qos/enabled: false`` on the publisher only (the
                     subscriber keeps Zenoh's default: QoS is then off for the link);
* ``qos-off-both``   the same on both sides;
* ``lowlatency``     ``transport/unicast/lowlatency: true``, QoS off, both sides (the
                     publisher writes in the caller's thread; negotiated - one side alone
                     falls back to the normal transport);
* ``lowlatency-pub`` the same on the publisher only;
* ``rt-app``         ``ZENOH_RUNTIME='(tx: (handover: app), rx: (handover: app), net: (handover:
                     app), acc: (handover: app))'``: one runtime thread for all;
* ``rt-tx-blocking1`` ``ZENOH_RUNTIME='(tx: (max_blocking_threads: 1))'``;
* ``session-put``    ``session.put(key, ...)`` with the same options instead of a declared
                     publisher;
* ``zbytes``         the payload as a ``zenoh.ZBytes`` made beforehand (the conversion left out);
* ``not-express``    the publisher declared ``express=False`` (batched);
* ``block``          ``CongestionControl.BLOCK`` instead of DROP;
* ``real-time``      ``Priority.REAL_TIME`` instead of DATA;
* ``unixsock``       the publisher listens on a Unix socket (``unixsock-stream/PATH``) the
                     subscriber connects to, instead of TCP on the loopback;
* ``no-subscriber``  the default with no subscriber at all: what a put costs Zenoh's routing
                     alone (nothing is sent; ``ZenohPublisher`` skips such puts by the matching
                     status, this measures what it would be);
* ``no-subscriber-b2b`` the same, the puts back to back (no 10 ms sleep between them): the cost
                     of the same code with its caches warm;
* ``tcp``            no Zenoh: a plain TCP socket's ``sendall`` of the same bytes, the
                     receiver a thread reading them (the kernel's floor for one message);
* ``idle``           no put at all: the loop's own cost (the sleep).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

RT_APP = "(tx: (handover: app), rx: (handover: app), net: (handover: app), acc: (handover: app))"
QOS_OFF = {"transport/unicast/qos/enabled": False}
LOWLAT = {"transport/unicast/lowlatency": True, "transport/unicast/qos/enabled": False}
VARIANTS = {
    # name: publisher config keys, subscriber config keys, environment, publisher options
    "default": ({}, {}, {}, {}),
    "no-batching": ({"transport/link/tx/queue/batching/enabled": False}, {}, {}, {}),
    "time-limit-0": ({"transport/link/tx/queue/batching/time_limit": 0}, {}, {}, {}),
    "queue-2": ({"transport/link/tx/queue/size/data": 2}, {}, {}, {}),
    "alloc-init": ({"transport/link/tx/queue/allocation/mode": "init"}, {}, {}, {}),
    "batch-8k": ({"transport/link/tx/batch_size": 8192}, {}, {}, {}),
    "tx-threads-4": ({"transport/link/tx/threads": 4}, {}, {}, {}),
    "qos-off": (QOS_OFF, {}, {}, {}),
    "qos-off-both": (QOS_OFF, QOS_OFF, {}, {}),
    "lowlatency": (LOWLAT, LOWLAT, {}, {}),
    "lowlatency-pub": (LOWLAT, {}, {}, {}),
    "rt-app": ({}, {}, {"ZENOH_RUNTIME": RT_APP}, {}),
    "rt-tx-blocking1": ({}, {}, {"ZENOH_RUNTIME": "(tx: (max_blocking_threads: 1))"}, {}),
    "session-put": ({}, {}, {}, {"session_put": True}),
    "zbytes": ({}, {}, {}, {"zbytes": True}),
    "not-express": ({}, {}, {}, {"express": False}),
    "block": ({}, {}, {}, {"block": True}),
    "real-time": ({}, {}, {}, {"real_time": True}),
    "unixsock": ({}, {}, {}, {"unixsock": True}),
    "no-subscriber": ({}, {}, {}, {"no_sub": True}),
    "no-subscriber-b2b": ({}, {}, {}, {"no_sub": True, "period": 0.0}),
    "tcp": ({}, {}, {}, {"tcp": True}),
    "idle": ({}, {}, {}, {"idle": True}),
}
KEY = "taxel/floor/record"


def _threads() -> dict[int, tuple[str, int]]:
    out = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            out[int(task.name)] = ((task / "comm").read_text().strip(),
                                   int((task / "schedstat").read_text().split()[0]))
        except (OSError, ValueError, IndexError):
            pass
    return out


def _sub_config(endpoint: str, keys: dict):
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    for key, value in keys.items():
        c.insert_json5(key, json.dumps(value))
    return c


def subscriber(endpoint: str, keys: dict, tcp: bool) -> None:
    n = [0]
    if tcp:
        host, port = endpoint.rsplit(":", 1)
        conn = socket.create_connection((host, int(port)))
        print("ready", flush=True)
        size = int(sys.stdin.readline())

        def loop():
            buf = 0
            while True:
                data = conn.recv(1 << 16)
                if not data:
                    return
                buf += len(data)
                n[0], _ = divmod(buf, size)
        threading.Thread(target=loop, daemon=True).start()
        sys.stdin.readline()
        time.sleep(0.5)
        print(n[0], flush=True)
        return
    import zenoh

    with zenoh.open(_sub_config(endpoint, keys)) as s:
        s.declare_subscriber(KEY, lambda sample: n.__setitem__(0, n[0] + 1))
        print("ready", flush=True)
        sys.stdin.readline()
        sys.stdin.readline()
        time.sleep(0.5)
        print(n[0], flush=True)


def publisher(variant: str, puts: int, size: int) -> dict:
    pub_keys, sub_keys, _env, opts = VARIANTS[variant]
    payload = b'{"x":"' + b"1" * max(size - 8, 0) + b'"}'
    warm = 50
    sub_cmd = [sys.executable, os.path.abspath(__file__), "--child", "sub", "--variant", variant]
    if opts.get("tcp") or opts.get("idle"):
        srv = socket.socket()
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        endpoint = f"127.0.0.1:{srv.getsockname()[1]}"
        sub = subprocess.Popen(sub_cmd + ["--endpoint", endpoint], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               text=True)
        conn, _ = srv.accept()
        assert sub.stdout.readline().strip() == "ready"
        sub.stdin.write(f"{len(payload)}\n")
        sub.stdin.flush()
        put = (lambda data: None) if opts.get("idle") else conn.sendall
        close = conn.close
    else:
        import zenoh

        from fusion_center.service.zenoh_config import open_session, resolve

        if opts.get("unixsock"):
            endpoint = f"unixsock-stream/{tempfile.gettempdir()}/zfloor-{os.getpid()}.sock"
        else:
            endpoint = f"tcp/127.0.0.1:{random.randint(40000, 60000)}"
        config, what = resolve(listen=[] if opts.get("unixsock") else [endpoint])
        if opts.get("unixsock"):  # no PROTO/HOST:PORT: set past the flags' check
            config.insert_json5("listen/endpoints", json.dumps([endpoint]))
        for key, value in pub_keys.items():
            config.insert_json5(key, json.dumps(value))
        session = open_session(config, what)
        kw = dict(encoding=zenoh.Encoding.APPLICATION_JSON,
                  congestion_control=zenoh.CongestionControl.BLOCK if opts.get("block") else
                  zenoh.CongestionControl.DROP, express=opts.get("express", True),
                  priority=zenoh.Priority.REAL_TIME if opts.get("real_time") else zenoh.Priority.DATA)
        pub = session.declare_publisher(KEY, **kw)
        sub = None
        if not opts.get("no_sub"):
            sub = subprocess.Popen(sub_cmd + ["--endpoint", endpoint], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                   text=True)
            assert sub.stdout.readline().strip() == "ready"
            sub.stdin.write("go\n")
            sub.stdin.flush()
            end = time.monotonic() + 10
            while not pub.matching_status.matching and time.monotonic() < end:
                time.sleep(0.01)
        if opts.get("session_put"):
            def put(data, _s=session, _kw=kw):
                _s.put(KEY, data, **_kw)
        elif opts.get("zbytes"):
            zpayload = zenoh.ZBytes(payload)

            def put(data, _p=pub, _z=zpayload):
                _p.put(_z)
        else:
            put = pub.put

        def close():
            pub.undeclare()
            session.close()
    period = opts.get("period", 0.01)
    for _ in range(warm):
        put(payload)
        time.sleep(period)
    me = threading.get_native_id()
    before, t0, w0 = _threads(), time.thread_time(), time.monotonic()
    caller = 0.0
    t_next = time.monotonic()
    for _ in range(puts):
        t_next += period
        delay = t_next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        c0 = time.thread_time()
        put(payload)
        caller += time.thread_time() - c0
    loop_cpu = time.thread_time() - t0
    wall = time.monotonic() - w0
    after = _threads()
    time.sleep(0.3)
    received = -1
    if sub is not None:
        sub.stdin.write("done\n")
        sub.stdin.flush()
        received = int(sub.stdout.readline().strip() or -1)
        sub.wait(10)
    close()
    by_name: dict[str, float] = {}
    for tid, (comm, ns) in after.items():
        if tid in before:
            name = "caller" if tid == me else comm
            by_name[name] = by_name.get(name, 0) + (ns - before[tid][1]) / puts / 1e3
    return {"put_us": caller / puts * 1e6, "loop_us": loop_cpu / puts * 1e6,
            "threads_us": {k: round(v, 1) for k, v in sorted(by_name.items(), key=lambda kv: -kv[1]) if v >= 0.5},
            "process_us": sum(by_name.values()), "sent": puts + warm, "received": received,
            "wall_s": wall}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--puts", type=int, default=500)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--size", type=int, default=1700)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--busy", type=int, default=0, help="processes spinning on the CPU meanwhile")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--variant", default="default", help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child == "sub":
        _, sub_keys, _, opts = VARIANTS[args.variant]
        subscriber(args.endpoint, sub_keys, bool(opts.get("tcp") or opts.get("idle")))
        return 0
    if args.child == "pub":
        print(json.dumps(publisher(args.variant, args.puts, args.size)))
        return 0
    variants = args.variants.split(",")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}: expected some of {', '.join(VARIANTS)}")
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    print(f"one put of {args.size} B every 10 ms, {args.puts} measured a run, {args.rounds} rounds alternating, "
          f"{args.busy} busy process(es); load average {os.getloadavg()[0]:.1f}", flush=True)
    runs: dict[str, list] = {v: [] for v in variants}
    try:
        for k in range(args.rounds):
            for variant in variants:
                env = {**os.environ, **VARIANTS[variant][2]}
                done = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "pub", "--variant", variant,
                                       "--puts", str(args.puts), "--size", str(args.size)], capture_output=True,
                                      text=True, env=env, timeout=600)
                if done.returncode != 0:
                    print(f"  {variant:16s} run {k + 1}: failed: {done.stderr.strip()[-400:]}", flush=True)
                    continue
                r = json.loads(done.stdout.strip().splitlines()[-1])
                r["load"] = os.getloadavg()[0]
                runs[variant].append(r)
                threads = ", ".join(f"{name} {us:.0f}" for name, us in r["threads_us"].items())
                print(f"  {variant:16s} run {k + 1}: put {r['put_us']:6.1f} us in the caller, process "
                      f"{r['process_us']:6.1f} us a put ({threads}); received {r['received']} of {r['sent']} "
                      f"(load {r['load']:.1f})", flush=True)
    finally:
        for proc in busy:
            proc.terminate()
            proc.wait(10)
    print("medians a put (us): caller's put / the process's CPU - idle's loop (the put's whole cost) / "
          "threads other than the caller")
    idle = statistics.median(r["process_us"] for r in runs["idle"]) if runs.get("idle") else 0.0
    for variant in variants:
        rs = runs[variant]
        if not rs:
            continue
        put = statistics.median(r["put_us"] for r in rs)
        proc = statistics.median(r["process_us"] for r in rs)
        other = statistics.median(r["process_us"] - r["threads_us"].get("caller", 0.0) for r in rs)
        lost = sum(r["sent"] - r["received"] for r in rs)
        what = "no subscriber, no loss counted" if any(r["received"] < 0 for r in rs) else \
            "no subscriber (the loop's)" if variant == "idle" else f"lost {lost} of {sum(r['sent'] for r in rs)}"
        print(f"  {variant:16s} {put:6.1f} / {proc - idle:6.1f} / {other:6.1f}   {what}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
