"""Does a stalled subscriber hold ``--zenoh``'s puts with Zenoh's low-latency transport?
(issue 24: why ``transport/unicast/lowlatency`` is not the project's default.)

    .venv/bin/python bench/zenoh_lowlatency_stall.py [--lowlatency | --default] [--wait 20]

A :class:`~fusion_center.service.zenoh_publisher.ZenohPublisher` (the project's session, plus
``transport/unicast/lowlatency: true`` and QoS off from a Zenoh file with ``--lowlatency``) and,
in this process, a peer session configured alike whose subscriber's callback blocks until
released; 1,500 records of ~40 kB (far beyond the queues and the kernel's socket buffers) are
put from a thread. Printed: how many puts returned within ``--wait`` seconds while the
subscriber was stalled, and whether the publishing thread was still inside a put then. The
default transport drops (CongestionControl.DROP): every put returns; the low-latency transport
writes in the caller's thread with no congestion control and waits for the socket.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--lowlatency", dest="lowlatency", action="store_true", default=True)
    mode.add_argument("--default", dest="lowlatency", action="store_false")
    ap.add_argument("--wait", type=float, default=20.0)
    args = ap.parse_args()
    import zenoh

    from fusion_center.service.zenoh_publisher import ZenohPublisher

    ll = args.lowlatency
    port = random.randint(40000, 60000)
    with tempfile.NamedTemporaryFile("w", suffix=".json5", delete=False) as f:
        json.dump({"transport": {"unicast": {"lowlatency": ll, "qos": {"enabled": not ll}}}}, f)
    pub = ZenohPublisher("stall", listen=[f"tcp/127.0.0.1:{port}"], config_file=f.name).open()
    os.unlink(f.name)
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    if ll:
        c.insert_json5("transport/unicast/lowlatency", "true")
        c.insert_json5("transport/unicast/qos/enabled", "false")
    peer = zenoh.open(c)
    release = threading.Event()
    peer.declare_subscriber("taxel/stall/record", lambda sample: release.wait(args.wait + 60))
    end = time.monotonic() + 10
    while not pub._publishers["record"].matching_status.matching and time.monotonic() < end:
        time.sleep(0.01)
    big = {"cycle": 0, "decision": "H0", "present_nodes": list(range(6000))}
    done: list[int] = []

    def run():
        for k in range(1500):
            pub({**big, "cycle": k})
            done.append(k)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(args.wait)
    held = thread.is_alive()
    print(f"{'low-latency' if ll else 'default'} transport: {len(done)} of 1500 puts returned within "
          f"{args.wait:g} s while the subscriber was stalled; the publishing thread "
          f"{'still inside a put (held)' if held else 'done (never held)'}", flush=True)
    release.set()
    thread.join(60)
    print(f"after the release: {len(done)} puts returned", flush=True)
    os._exit(0)  # the sessions' threads: no orderly close needed for a measurement


if __name__ == "__main__":
    sys.exit(main())
