"""taxel_net/receiver.py: one select thread for every bus with a socket (udp_multicast here)."""

from __future__ import annotations

import random
import socket
import sys
import threading
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


def test_virtual_buses_share_one_thread_woken_by_their_queues():
    """python-can virtual buses: one thread serves them all (no socket to select on: each bus's
    receive queue signals it), every frame of every bus reaches its listeners in order - frames
    queued before the swap included, frames from python-can's own send and from the twins'
    burst sender alike - the bus's filters apply, and stop ends the thread."""
    from node_sim.channel import virtual_burst_sender
    from taxel_net.receiver import VirtualNotifiers

    names = [f"rx-{k}-{random.random()}" for k in range(3)]
    rx = [can.Bus(interface="virtual", channel=n) for n in names]
    tx = [can.Bus(interface="virtual", channel=n) for n in names]
    got = {k: [] for k in range(3)}
    try:
        assert not any(has_socket(b) for b in rx)
        tx[0].send(can.Message(arbitration_id=0x181, data=b"\x00", is_extended_id=False))  # queued before
        rx[2].set_filters([{"can_id": 0x181, "can_mask": 0x7FF, "extended": False}])
        handles = notifiers_for([(b, [lambda m, k=k: got[k].append((m.arbitration_id, m.data[0]))])
                                 for k, b in enumerate(rx)])
        owner = handles[0].owner
        assert isinstance(owner, VirtualNotifiers) and all(h.owner is owner for h in handles)
        threads = threading.active_count()
        burst = virtual_burst_sender(tx[1])
        for i in range(1, 200):
            tx[0].send(can.Message(arbitration_id=0x181, data=bytes([i]), is_extended_id=False))
            burst([(0x182, bytes([i])), (0x183, bytes([i]))])
            tx[2].send(can.Message(arbitration_id=0x181 if i % 2 else 0x281, data=bytes([i]), is_extended_id=False))
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and (len(got[0]) < 200 or len(got[1]) < 398 or len(got[2]) < 100):
            time.sleep(0.01)
        assert got[0] == [(0x181, i) for i in range(200)]
        assert got[1] == [(can_id, i) for i in range(1, 200) for can_id in (0x182, 0x183)]
        assert got[2] == [(0x181, i) for i in range(1, 200, 2)]          # 0x281 filtered out
        assert threading.active_count() == threads                       # no thread per bus
        owner.stop(1)
        assert not owner._thread.is_alive()
    finally:
        for b in rx + tx:
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
            # Linux turns receive time stamps on for the host only once a socket asks, from a
            # work queue: a datagram queued before that is stamped when it is read. Wait until
            # a probe is stamped on arrival, so both readers see the kernel's receive times.
            for _ in range(50):
                tx.send(can.Message(arbitration_id=0x7FF, is_extended_id=False))
                probe = reference.recv(1.0)
                time.sleep(0.05)
                late = rx.recv(1.0)
                if probe is not None and late is not None and abs(late.timestamp - probe.timestamp) < 0.02:
                    break
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
            assert all(abs(a.timestamp - b.timestamp) < 0.5 and a.timestamp > 1e9 for a, b in zip(got, expected)), [(a.timestamp, b.timestamp) for a, b in zip(got, expected)]
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


def test_draining_a_bus_reads_past_the_frames_its_filters_refuse():
    """Frames the filters refuse, queued ahead of wanted ones, do not hide those (python-can's
    ``recv(0)`` returns None at the first refused frame): a junk flood on the twins' virtual
    buses held their heartbeats and SYNCs back for seconds (every node fell pre-operational)."""
    from taxel_net.receiver import _recv_all

    name = f"filtered-{random.random()}"
    rx, tx = can.Bus(interface="virtual", channel=name), can.Bus(interface="virtual", channel=name)
    try:
        rx.set_filters([{"can_id": 0x700, "can_mask": 0x780, "extended": False}])
        for i in range(20):
            tx.send(can.Message(arbitration_id=0x7F0, data=bytes(8), is_extended_id=False))   # refused
            tx.send(can.Message(arbitration_id=0x77F, data=bytes([i]), is_extended_id=False))  # wanted
        assert [m.data[0] for m in _recv_all(rx)] == list(range(20))
        assert list(_recv_all(rx)) == []
    finally:
        rx.shutdown()
        tx.shutdown()


def test_a_flooded_bus_does_not_starve_the_others():
    """One thread serves every bus in turns of at most TURN_FRAMES frames: a frame of a quiet
    bus is handled before a flooded bus's backlog is through."""
    from taxel_net.receiver import TURN_FRAMES

    names = [f"turns-{k}-{random.random()}" for k in range(2)]
    rx = [can.Bus(interface="virtual", channel=n) for n in names]
    tx = [can.Bus(interface="virtual", channel=n) for n in names]
    order = []
    try:
        backlog = 4 * TURN_FRAMES
        for i in range(backlog):  # queued before the thread starts: one backlog
            tx[0].send(can.Message(arbitration_id=0x181, data=i.to_bytes(2, "little"), is_extended_id=False))
        tx[1].send(can.Message(arbitration_id=0x182, data=b"\x00", is_extended_id=False))
        handles = notifiers_for([(b, [lambda m, k=k: order.append(k)]) for k, b in enumerate(rx)])
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and len(order) < backlog + 1:
            time.sleep(0.01)
        assert sorted(order) == [0] * backlog + [1]
        assert order.index(1) <= TURN_FRAMES     # bus 1's turn came after at most one turn of bus 0
        handles[0].stop(1)
    finally:
        for b in rx + tx:
            b.shutdown()


class _FailsAfter(_Broken):
    """Readable; yields ``frames`` then fails (the read of a bus that goes away mid-turn)."""

    def __init__(self, frames):
        super().__init__()
        self._frames = list(frames)

    def _recv_internal(self, timeout):
        if self._frames:
            return self._frames.pop(0), True
        raise can.CanOperationError("gone")


def test_a_batch_listener_gets_each_turn_in_one_call_and_the_frames_before_a_failure():
    """Listeners that all have ``on_messages_received`` get the frames of a turn in one call, in
    order; a bus that fails mid-turn hands on what it read, then tells the failure once. With a
    listener among them that has not, every listener gets the frames one by one, each read
    after the one before was handled (the bus's filters as the listeners left them)."""
    frames = [can.Message(arbitration_id=0x181, data=bytes([i]), is_extended_id=False) for i in range(5)]
    batches, singles, events = [], [], []

    class Batch(can.Listener):
        def on_messages_received(self, msgs):
            batches.append([m.data[0] for m in msgs])
            events.append("frames")

        def on_message_received(self, msg):
            singles.append(msg.data[0])

        def on_error(self, exc):
            events.append("error")

    for others, want_batches, want_singles in (([], [[0, 1, 2, 3, 4]], []),
                                               ([lambda m: None], [], [0, 1, 2, 3, 4])):
        batches.clear(), singles.clear(), events.clear()
        bus = _FailsAfter(frames)
        loop = SelectNotifiers([(bus, [Batch(), *others])], timeout=0.01)
        try:
            deadline = time.monotonic() + 2
            while "error" not in events and time.monotonic() < deadline:
                time.sleep(0.01)
            assert batches == want_batches and singles == want_singles
            assert events[-1] == "error" and events.count("error") == 1
            assert isinstance(loop.handles[0].exception, can.CanOperationError)
        finally:
            loop.stop(1)
            bus.shutdown()


def test_a_filter_widened_by_a_frame_lets_the_next_frame_of_the_turn_through():
    """A plain listener that widens the bus's filters on a frame sees the frames after it that
    the new filters let through, though they were queued in the same turn."""
    names = f"widen-{random.random()}"
    rx, tx = can.Bus(interface="virtual", channel=names), can.Bus(interface="virtual", channel=names)
    got = []

    def listener(msg):
        got.append(msg.arbitration_id)
        if msg.arbitration_id == 0x605:  # as node_sim's channel after an SDO write of 0x1005
            rx.set_filters([{"can_id": 0x605, "can_mask": 0x7FF}, {"can_id": 0x081, "can_mask": 0x7FF}])

    try:
        rx.set_filters([{"can_id": 0x605, "can_mask": 0x7FF}])
        tx.send(can.Message(arbitration_id=0x605, data=b"\x01", is_extended_id=False))
        tx.send(can.Message(arbitration_id=0x081, data=b"\x01", is_extended_id=False))
        handles = notifiers_for([(rx, [listener])])
        deadline = time.monotonic() + 2
        while len(got) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert got == [0x605, 0x081]
        handles[0].stop(1)
    finally:
        rx.shutdown()
        tx.shutdown()
