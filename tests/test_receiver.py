"""taxel_net/receiver.py: one select thread for every bus with a socket (udp_multicast here)."""

from __future__ import annotations

import random
import socket
import sys
import time
from pathlib import Path

import can

from taxel_net.receiver import SelectNotifiers, has_socket, notifiers_for

ROOT = Path(__file__).resolve().parent.parent
GROUPS = ["239.74.163.31", "239.74.163.32", "239.74.163.33"]


def _buses(port):
    from taxel_net.canmsg import tune_udp_multicast

    buses = [can.Bus(interface="udp_multicast", channel=g, port=port, hop_limit=0) for g in GROUPS]
    for b in buses:
        tune_udp_multicast(b)
    return buses


def test_virtual_buses_keep_a_python_can_notifier_each():
    buses = [can.Bus(interface="virtual", channel=f"rx-{k}-{random.random()}") for k in range(2)]
    try:
        assert not any(has_socket(b) for b in buses)
        notifiers = notifiers_for([(b, []) for b in buses])
        assert all(isinstance(n, can.Notifier) for n in notifiers)
        for n in notifiers:
            n.stop(1)
    finally:
        for b in buses:
            b.shutdown()


def test_one_thread_delivers_every_frame_of_every_bus_in_order_to_its_listeners():
    sys.path.insert(0, str(ROOT / "tests"))
    from test_service_multiprocess import multicast_port

    port = multicast_port()
    rx, tx = _buses(port), _buses(port)
    got = {k: [] for k in range(len(GROUPS))}
    extra = []
    try:
        assert all(has_socket(b) for b in rx)
        handles = notifiers_for([(b, [lambda m, k=k: got[k].append(m.data[0])]) for k, b in enumerate(rx)])
        assert all(h.owner is handles[0].owner for h in handles)    # one thread serves them all
        handles[1].add_listener(lambda m: extra.append(m.data[0]))
        for i in range(50):
            for k, b in enumerate(tx):
                b.send(can.Message(arbitration_id=0x181 + k, data=bytes([i]), is_extended_id=False))
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(len(v) < 50 for v in got.values()):
            time.sleep(0.02)
        assert all(v == list(range(50)) for v in got.values()), {k: len(v) for k, v in got.items()}
        assert extra == list(range(50))                            # an added listener gets bus 1's frames
        handles[0].stop(2)
        assert not handles[0].owner._thread.is_alive()
    finally:
        for b in rx + tx:
            b.shutdown()


class _Broken(can.BusABC):
    """Always readable, every read fails."""

    def __init__(self):
        self._a, self._b = socket.socketpair()
        self._b.send(b"x")
        super().__init__(channel="broken")

    def fileno(self):
        return self._a.fileno()

    def _recv_internal(self, timeout):
        raise can.CanOperationError("gone")

    def send(self, msg, timeout=None):
        pass

    def shutdown(self):
        self._a.close()
        self._b.close()
        super().shutdown()


def test_a_failing_bus_is_reported_once_and_no_longer_read():
    bus = _Broken()
    errors = []

    class Listener(can.Listener):
        def on_message_received(self, msg):
            pass

        def on_error(self, exc):
            errors.append(exc)

    loop = SelectNotifiers([(bus, [Listener()])], timeout=0.01)
    try:
        deadline = time.monotonic() + 2
        while not errors and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)
        assert len(errors) == 1 and isinstance(loop.handles[0].exception, can.CanOperationError)
        assert not loop._thread.is_alive()  # its only bus failed: nothing left to read
    finally:
        loop.stop(1)
        bus.shutdown()


def test_udp_multicast_drain_reads_what_recv_would_and_no_more():
    """The direct socket read yields what python-can's own ``recv`` gives a second bus of the
    same group (every field, the kernel's receive time; FD frames dropped on a classic bus),
    and returns at once when the socket is empty; the bus's filters apply as in ``recv``."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_service_multiprocess import multicast_port

    from taxel_net.udp_wire import udp_multicast_drain

    port = multicast_port()

    def fields(m):
        return m.arbitration_id, bytes(m.data), m.is_extended_id, m.is_remote_frame, m.dlc, m.is_fd, m.bitrate_switch

    for fd in (False, True):
        rx, reference = (can.Bus(interface="udp_multicast", channel=GROUPS[0], port=port, hop_limit=0, fd=fd)
                         for _ in range(2))
        tx = can.Bus(interface="udp_multicast", channel=GROUPS[0], port=port, hop_limit=0, fd=True)
        try:
            drain = udp_multicast_drain(rx)
            assert drain is not None
            assert list(drain()) == []  # nothing sent yet: returns without waiting
            sent = [can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False),
                    can.Message(arbitration_id=0x1234567, is_extended_id=True, is_remote_frame=True, dlc=3),
                    can.Message(arbitration_id=0x281, data=bytes(12), is_extended_id=False, is_fd=True,
                                bitrate_switch=True),
                    can.Message(arbitration_id=0x080, data=b"\x07", is_extended_id=False)]
            for m in sent:
                tx.send(m)
            expected = []
            while (m := reference.recv(1.0)) is not None:
                expected.append(m)
            assert [fields(m) for m in expected] == [fields(m) for m in sent if fd or not m.is_fd]
            got = list(drain())  # the reference has them all: so has this socket
            assert [fields(m) for m in got] == [fields(m) for m in expected]
            assert all(abs(a.timestamp - b.timestamp) < 0.5 and a.timestamp > 1e9 for a, b in zip(got, expected))
            # filters: applied by the drain as by recv (here on the reference bus)
            only = [{"can_id": 0x080, "can_mask": 0x7FF}, {"can_id": 0x1234560, "can_mask": 0x1FFFFFF0, "extended": True}]
            rx.set_filters(only)
            reference.set_filters(only)
            for m in sent:
                tx.send(m)
            expected = []
            while (m := reference.recv(1.0)) is not None:
                expected.append(m)
            assert [m.arbitration_id for m in expected] == [0x1234567, 0x080]
            assert [fields(m) for m in drain()] == [fields(m) for m in expected]
        finally:
            for bus in (rx, reference, tx):
                bus.shutdown()
    virtual = can.Bus(interface="virtual", channel=f"v-{random.random()}")
    assert udp_multicast_drain(virtual) is None
    virtual.shutdown()


def test_a_stray_datagram_is_skipped_not_fatal(caplog):
    """A datagram on the group that is no python-can frame: python-can's recv raises (and a
    Notifier stops reading the bus); the drain skips it, logs it and reads on."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_service_multiprocess import multicast_port

    port = multicast_port()
    rx = can.Bus(interface="udp_multicast", channel=GROUPS[1], port=port, hop_limit=0)
    tx = can.Bus(interface="udp_multicast", channel=GROUPS[1], port=port, hop_limit=0)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    got = []
    try:
        handles = notifiers_for([(rx, [got.append])])
        raw.sendto(b"\xc1 not msgpack", (GROUPS[1], port))
        tx.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            time.sleep(0.01)
        assert [m.arbitration_id for m in got] == [0x181]
        assert handles[0].exception is None
        assert "no python-can frame skipped" in caplog.text
        handles[0].stop(1)
    finally:
        raw.close()
        rx.shutdown()
        tx.shutdown()
