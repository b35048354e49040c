"""No SDO lost to the transport (issue 11): 57 concurrent SDO clients against one node-sim
process on udp_multicast complete every transfer. python-can leaves the sockets' receive buffer
at the kernel default (208 KiB on Linux), and under the burst the kernel dropped datagrams of
the node-sim process (0.1-0.6 % of the transfers lost, bench/sdo_udp_clients.py); node_sim and
the centre now raise SO_RCVBUF on every udp_multicast bus they open
(``taxel_net.canmsg.raise_receive_buffer``) and read the effective size back."""

import os
import random
import re
import socket
import threading
from pathlib import Path

import can
import canopen
import pytest

from taxel_net.canmsg import UDP_RECEIVE_BUFFER, raise_receive_buffer

ROOT = Path(__file__).resolve().parent.parent
MATRIX = ROOT / "scenes" / "matrix57.toml"


def _socket_inodes(pid: int) -> set[int]:
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            m = re.fullmatch(r"socket:\[(\d+)\]", os.readlink(fd))
        except OSError:
            continue
        if m:
            inodes.add(int(m.group(1)))
    return inodes


def _udp_drops(inodes: set[int], port: int) -> int | None:
    """Datagrams the kernel dropped on these sockets bound to ``port`` (Linux /proc/net/udp)."""
    total, found = 0, False
    for name in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(name).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if int(f[1].rsplit(":", 1)[1], 16) == port and int(f[9]) in inodes:
                total += int(f[12])
                found = True
    return total if found else None


def _rcvbuf(bus) -> int:
    return bus._multicast._socket.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)


def test_raise_receive_buffer_reads_the_effective_size_back_and_leaves_other_buses_alone():
    from test_service_multiprocess import GROUP

    port = random.randint(40000, 60000)
    try:
        bus = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"cannot open udp_multicast: {exc}")
    try:
        before = _rcvbuf(bus)
        effective = raise_receive_buffer(bus)
        assert effective == _rcvbuf(bus) and effective >= before
        assert raise_receive_buffer(bus, size=1024) == effective   # never lowered
        if effective < UDP_RECEIVE_BUFFER:                          # capped by net.core.rmem_max, no CAP_NET_ADMIN
            rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
            assert effective >= min(2 * rmem_max, before)
    finally:
        bus.shutdown()
    virtual = can.Bus(interface="virtual", channel=f"rb-{port}")
    try:
        assert raise_receive_buffer(virtual) is None
    finally:
        virtual.shutdown()


def test_the_rig_and_the_centre_open_udp_multicast_with_the_raised_buffer():
    from test_service_multiprocess import GROUP

    from fusion_center.service import FusionService
    from node_sim.rig import Rig
    from taxel_net.scene import load_scene

    port = random.randint(40000, 60000)
    scene = load_scene(MATRIX)
    try:
        probe = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"cannot open udp_multicast: {exc}")
    try:
        default = _rcvbuf(probe)                # python-can's: the kernel default
        wanted = raise_receive_buffer(probe)   # what this host grants
    finally:
        probe.shutdown()
    rig = Rig(scene, interface="udp_multicast", channel=GROUP, bus_kwargs={"port": port, "hop_limit": 0})
    try:
        rig.start()
        assert [_rcvbuf(b) for b in rig.buses] == [wanted]
        with FusionService(scene, interface="udp_multicast", channels=[GROUP],
                           bus_kwargs={"port": port, "hop_limit": 0}) as service:
            assert [_rcvbuf(b) for b in service.buses] == [wanted]
    finally:
        rig.stop()
    assert wanted >= default


@pytest.mark.multiprocess
def test_57_concurrent_sdo_clients_lose_no_transfer_on_udp_multicast():
    """One node-sim process (57 nodes), one client per node in threads, all at once: expedited
    downloads and uploads of 0x2001:1 and segmented uploads of 0x1008; canopen's client makes no
    retry and waits 5 s, so a dropped datagram is a lost transfer. Every transfer completes and
    the kernel dropped nothing on node-sim's sockets (Linux /proc/net/udp) but what their
    kernel filter drops (taxel_net.udp_filter: node-sim's own SDO answers looped back, counted
    as drops too): a socket of this process on the group with node-sim's filters, read by a
    thread, drops exactly those."""
    from node_sim.channel import CONSUMED_FILTERS
    from taxel_net.udp_filter import set_filters
    from process_helpers import start_node_sim, stop, udp_loopback, wait_ready
    from test_service_multiprocess import GROUP, multicast_port

    port = multicast_port()
    shadow = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    raise_receive_buffer(shadow)
    in_kernel = set_filters(shadow, CONSUMED_FILTERS + [{"can_id": 0x080, "can_mask": 0x7FF, "extended": False}])
    shadow_inodes = {os.fstat(shadow._multicast._socket.fileno()).st_ino}
    reading = threading.Event()
    reading.set()

    def read_shadow():
        while reading.is_set():
            shadow.recv(0.05)

    shadow_reader = threading.Thread(target=read_shadow, daemon=True)
    shadow_reader.start()
    sim = start_node_sim("--scene", str(MATRIX), *udp_loopback(GROUP, port))
    transfers = 30
    try:
        wait_ready(sim)
        inodes = _socket_inodes(sim.pid)
        drops_before = _udp_drops(inodes, port)
        filtered_before = _udp_drops(shadow_inodes, port)
        network = canopen.Network()
        network.connect(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
        raise_receive_buffer(network.bus)  # the clients' side too: this test is about node-sim
        od = canopen.import_od(str(ROOT / "eds" / "taxel_node.eds"))
        nodes = []
        for node_id in range(1, 58):
            node = canopen.RemoteNode(node_id, od)
            node.sdo.RESPONSE_TIMEOUT = 5.0
            node.sdo.MAX_RETRIES = 1
            network.add_node(node)
            nodes.append(node)
        results: list[list] = [[] for _ in nodes]
        go = threading.Barrier(len(nodes))

        def client(k):
            node = nodes[k]
            go.wait()
            for j in range(transfers):
                try:
                    if j % 3 == 0:
                        node.sdo[0x2001][1].raw = 1.0 + 0.5 * (j % 5)
                        results[k].append("ok")
                    elif j % 3 == 1:
                        results[k].append("ok" if node.sdo[0x2001][1].raw == 1.0 + 0.5 * ((j - 1) % 5) else "value")
                    else:
                        results[k].append("ok" if node.sdo[0x1008].raw else "empty")
                except canopen.SdoAbortedError as exc:
                    results[k].append(f"abort 0x{exc.code:08X}")
                except canopen.SdoCommunicationError as exc:
                    results[k].append(f"lost: {exc}")

        threads = [threading.Thread(target=client, args=(k,), daemon=True) for k in range(len(nodes))]
        for t in threads:
            t.start()
        for t in threads:
            t.join(300)
        drops_after = _udp_drops(inodes, port)
        filtered_after = _udp_drops(shadow_inodes, port)
        network.disconnect()
    finally:
        reading.clear()
        shadow_reader.join(2)
        shadow.shutdown()
        stop(sim)
    outcomes = [r for rs in results for r in rs]
    failed = [r for r in outcomes if r != "ok"]
    assert len(outcomes) == 57 * transfers and failed == [], failed[:10]
    if drops_before is not None and drops_after is not None:
        assert drops_after - drops_before == filtered_after - filtered_before
        assert (filtered_after - filtered_before > 0) == in_kernel  # node-sim's answers, filtered out
