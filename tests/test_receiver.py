"""service/receiver.py: one select thread for every bus with a socket (udp_multicast here)."""

from __future__ import annotations

import random
import socket
import sys
import time
from pathlib import Path

import can
import pytest

from fusion_center.service.receiver import SelectNotifiers, has_socket, notifiers_for

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
    from test_service_multiprocess import multicast_works

    port = random.randint(40000, 60000)
    why = multicast_works(port)
    if why is not None:
        pytest.skip(why)
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
