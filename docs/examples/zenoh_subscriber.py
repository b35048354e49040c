"""A Zenoh subscriber of a run's records (docs/robotics.md, *Zenoh*): prints one line per
record, grip command and contact event that `fusion-center run|demo --zenoh` publishes.

    python3 docs/examples/zenoh_subscriber.py                       # connects to tcp/127.0.0.1:7447
    python3 docs/examples/zenoh_subscriber.py --scene matrix57 --count 200
    python3 docs/examples/zenoh_subscriber.py --listen tcp/127.0.0.1:7500   # the run connects here:
    fusion-center demo --zenoh --zenoh-connect tcp/127.0.0.1:7500 --zenoh-listen tcp/127.0.0.1:7501

Loopback and no multicast scouting, as the project's own sessions; ``--raw`` prints each
record's payload as it came (the decision log's line). Needs only ``eclipse-zenoh``.
"""

import argparse
import json
import sys
import threading

import zenoh


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default=None, metavar="ENDPOINT", help="default tcp/127.0.0.1:7447")
    ap.add_argument("--listen", default=None, metavar="ENDPOINT", help="listen here instead (the run connects)")
    ap.add_argument("--scene", default="*", help="the scene's name (default: every scene)")
    ap.add_argument("--count", type=int, default=0, help="stop after this many records (0: never)")
    ap.add_argument("--timeout", type=float, default=0.0, help="stop after this many seconds (0: never)")
    ap.add_argument("--raw", action="store_true", help="print each record's payload as it came")
    args = ap.parse_args(argv)

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps([args.listen] if args.listen else []))
    if not args.listen:
        config.insert_json5("connect/endpoints", json.dumps([args.connect or "tcp/127.0.0.1:7447"]))
    done = threading.Event()
    records = 0
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal records
        kind = str(sample.key_expr).rsplit("/", 1)[-1]
        payload = sample.payload.to_bytes()
        message = json.loads(payload)
        with lock:
            if kind == "record":
                records += 1
                if args.raw:
                    print(payload.decode(), flush=True)
                else:
                    print(f"record  cycle {message['cycle']:5d}  {message.get('decision', '-'):9s}  "
                          f"present {message.get('present_count', 0):4d}  U_G {message.get('U_G')}", flush=True)
            elif not args.raw and kind == "grip":
                print(f"grip    cycle {message['cycle']:5d}  command {message['command_n']} N  actual "
                      f"{message['actual_n']} N  {message['grip_state']}", flush=True)
            elif not args.raw and kind == "contact":
                print(f"contact cycle {message['cycle']:5d}  {message['event']}: {message['previous']} -> "
                      f"{message['decision']}", flush=True)
            if args.count and records >= args.count:
                done.set()

    with zenoh.open(config) as session:
        session.declare_subscriber(f"taxel/{args.scene}/*", on_sample)
        print(f"subscribed to taxel/{args.scene}/*", file=sys.stderr, flush=True)
        try:
            done.wait(args.timeout or None)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
