"""Concurrent SDO clients against one node-sim process on udp_multicast: transfers completed
and lost, and where the datagrams went (issue 11, "no SDO lost to the transport").

For each client count C: a fresh ``node-sim`` process (scene matrix57, 57 nodes) on a private
udp_multicast port; in this process one canopen ``Network`` on one udp_multicast bus and C
``RemoteNode`` SDO clients (node-IDs 1..C of the scene), each in its own thread, all started
together; each makes ``--transfers`` transfers in turn: an expedited download of 0x2001:1 (ζ),
an expedited upload of it, a segmented upload of 0x1008 (device name). canopen's client makes
no retry here (``MAX_RETRIES = 1``) and waits ``--timeout`` s for each answer, so a lost
request or answer is a lost transfer, not a slow one. Aborts are counted apart (there should
be none).

Where datagrams were dropped: the kernel's per-socket drop counter (``/proc/net/udp``, column
``drops``, for the sockets of the node-sim process and of this one) and the socket's receive
buffer as ``ss`` reports it (``skmem rb``, bytes) when ``ss`` is installed. A node-sim of this
tree filters its sockets in the kernel (``taxel_net.udp_filter``): the counter then also holds
its own SDO answers looped back and dropped there (one per transfer and segment), not losses;
tests/test_node_sdo_udp.py tells the two apart.

    .venv/bin/python bench/sdo_udp_clients.py                       # 8 and 57 clients
    .venv/bin/python bench/sdo_udp_clients.py --clients 57 --transfers 60 --repeat 3

A tree before a change is measured side by side as docs/contributing.md describes
(``git worktree add /tmp/before <commit>``, then ``--against /tmp/before``: node-sim of that
tree; the clients and the measurement are this tree's).
"""

from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import canopen

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "matrix57.toml"
GROUP = "239.74.163.2"


def socket_inodes(pid: int) -> set[int]:
    out = set()
    fd_dir = Path(f"/proc/{pid}/fd")
    for fd in fd_dir.iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        m = re.fullmatch(r"socket:\[(\d+)\]", target)
        if m:
            out.add(int(m.group(1)))
    return out


def udp_drops(inodes: set[int], port: int) -> int:
    """Datagrams the kernel dropped on these sockets bound to ``port`` (``/proc/net/udp*``)."""
    total = 0
    for name in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(name).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            local_port = int(f[1].rsplit(":", 1)[1], 16)
            if local_port == port and int(f[9]) in inodes:
                total += int(f[12])
    return total


def receive_buffers(pid: int, port: int) -> list[int]:
    """``skmem rb`` (bytes) of the process's UDP sockets on ``port``, from ``ss``."""
    if shutil.which("ss") is None:
        return []
    out = subprocess.run(["ss", "-uanmp"], capture_output=True, text=True).stdout
    sizes = []
    lines = out.splitlines()
    for k, line in enumerate(lines):
        if f":{port} " in line and f"pid={pid}," in line:
            rest = " ".join(lines[k:k + 2])
            m = re.search(r"rb(\d+)", rest)
            if m:
                sizes.append(int(m.group(1)))
    return sizes


def start_node_sim(port: int, tree: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-c", "import sys; from node_sim.cli import main; sys.exit(main())",
           "--scene", str(SCENE), "--interface", "udp_multicast", "--channel", GROUP,
           "--bus-option", f"port={port}", "--bus-option", "hop_limit=0"]
    env = dict(os.environ, PYTHONPATH=str(tree))  # that tree's node_sim and taxel_net
    sim = subprocess.Popen(cmd, cwd=tree, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    ready = sim.stdout.readline()
    if "ready" not in ready:
        sim.kill()
        raise SystemExit(f"node-sim did not start: {ready}{sim.stderr.read()}")
    return sim


def open_bus(port: int) -> can.BusABC:
    """The clients' bus (the harness, always this tree's code): with the receive buffer the
    centre gives its own udp_multicast buses, so the harness itself loses nothing."""
    bus = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    from taxel_net import canmsg

    raise_buffer = getattr(canmsg, "raise_receive_buffer", None)
    if raise_buffer is not None:
        raise_buffer(bus)
    return bus


def run(clients: int, transfers: int, timeout: float, tree: Path) -> dict:
    port = random.randint(40000, 60000)
    sim = start_node_sim(port, tree)
    try:
        bus = open_bus(port)
        network = canopen.Network(bus)
        network.notifier = can.Notifier(bus, network.listeners, 0.1)
        od = canopen.import_od(str(ROOT / "eds" / "taxel_node.eds"))
        nodes = []
        for node_id in range(1, clients + 1):
            node = canopen.RemoteNode(node_id, od)
            node.sdo.RESPONSE_TIMEOUT = timeout
            node.sdo.MAX_RETRIES = 1  # no retry: a lost frame is a lost transfer
            network.add_node(node)
            nodes.append(node)
        own = {os.fstat(bus.fileno()).st_ino}
        sim_inodes = socket_inodes(sim.pid)
        drops0 = udp_drops(sim_inodes, port), udp_drops(own, port)
        done = [0] * clients
        lost = [0] * clients
        aborted = [0] * clients
        codes: dict[int, int] = {}
        start = threading.Barrier(clients + 1)

        def client(k: int) -> None:
            node = nodes[k]
            start.wait()
            for j in range(transfers):
                try:
                    step = j % 3
                    if step == 0:
                        node.sdo[0x2001][1].raw = 1.0 + 0.5 * (j % 7)
                    elif step == 1:
                        node.sdo[0x2001][1].raw
                    else:
                        node.sdo[0x1008].raw
                    done[k] += 1
                except canopen.SdoAbortedError as exc:
                    aborted[k] += 1
                    codes[exc.code] = codes.get(exc.code, 0) + 1
                except canopen.SdoCommunicationError:
                    lost[k] += 1

        threads = [threading.Thread(target=client, args=(k,), daemon=True) for k in range(clients)]
        for t in threads:
            t.start()
        t0 = time.perf_counter()
        start.wait()
        for t in threads:
            t.join()
        seconds = time.perf_counter() - t0
        drops1 = udp_drops(sim_inodes, port), udp_drops(own, port)
        rb_sim, rb_own = receive_buffers(sim.pid, port), receive_buffers(os.getpid(), port)
        network.notifier.stop()
        bus.shutdown()
    finally:
        sim.terminate()
        try:
            sim.wait(10)
        except subprocess.TimeoutExpired:
            sim.kill()
    return {"clients": clients, "transfers": clients * transfers, "completed": sum(done), "lost": sum(lost),
            "aborted": sum(aborted), "codes": codes, "seconds": seconds, "sim_drops": drops1[0] - drops0[0],
            "client_drops": drops1[1] - drops0[1], "sim_rb": rb_sim, "client_rb": rb_own}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", type=int, nargs="+", default=[8, 57])
    ap.add_argument("--transfers", type=int, default=30, help="transfers per client (default 30)")
    ap.add_argument("--timeout", type=float, default=2.0, help="SDO response time-out, s (default 2)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--against", type=Path, default=None,
                    help="another checkout (e.g. a git worktree before a change): measured after this one")
    args = ap.parse_args()
    trees = [("this tree", ROOT)] + ([(str(args.against), args.against.resolve())] if args.against else [])
    for _ in range(args.repeat):
        for label, tree in trees:
            for clients in args.clients:
                r = run(clients, args.transfers, args.timeout, tree)
                print(f"{label}: {r['clients']:3d} clients: {r['completed']}/{r['transfers']} transfers completed, "
                      f"{r['lost']} lost ({100 * r['lost'] / r['transfers']:.1f} %), {r['aborted']} aborted"
                      f"{' (' + ', '.join(f'0x{c:08X} x{n}' for c, n in sorted(r['codes'].items())) + ')' if r['codes'] else ''}, "
                      f"{r['seconds']:.1f} s; datagrams dropped by the kernel: node-sim {r['sim_drops']} (with its filter's), "
                      f"clients {r['client_drops']}; receive buffer (ss rb, bytes): node-sim {r['sim_rb']}, "
                      f"clients {r['client_rb']}", flush=True)


if __name__ == "__main__":
    main()
