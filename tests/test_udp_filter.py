"""taxel_net/udp_filter.py: a udp_multicast bus's python-can filters in its socket's kernel filter
drop exactly the datagrams the Python side would drop by their first bytes (peek_id +
_matches), and nothing else - on python-can's own datagrams of random frames, and on
datagrams of other layouts, cut short or of random bytes."""

from __future__ import annotations

import random
import socket
import sys
import time
from pathlib import Path

import can
import pytest
from can.interfaces.udp_multicast.utils import pack_message

from taxel_net.canmsg import tune_udp_multicast
from taxel_net.udp_filter import MIN_LENGTH, compile_filters, set_filters
from taxel_net.udp_wire import _matches, peek_id

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_service_multiprocess import multicast_port  # noqa: E402

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SO_ATTACH_FILTER is Linux's")
GROUP = "239.74.163.41"


def random_filters(rng: random.Random) -> list[dict]:
    filters = []
    for _ in range(rng.randint(1, 6)):
        f = {"can_id": rng.randrange(0x800), "can_mask": rng.choice([0x7FF, 0x780, 0x700, 0x7F0])}
        if rng.random() < 0.3:
            f = {"can_id": rng.randrange(2 ** 29), "can_mask": rng.choice([0x1FFFFFFF, 0x1FFFFF00])}
            f["extended"] = True
        elif rng.random() < 0.7:
            f["extended"] = False
        filters.append(f)
    return filters


def random_datagrams(rng: random.Random, n: int) -> list[bytes]:
    out = []
    for k in range(n):
        extended = rng.random() < 0.2
        can_id = rng.randrange(2 ** 29 if extended else 0x800)
        if rng.random() < 0.5:  # IDs near the filters' values
            can_id = rng.choice([0x080, 0x000, 0x181, 0x701, 0x7E5, 0x605]) if not extended else can_id
        fd = rng.random() < 0.2
        length = rng.choice([0, 1, 8] + ([12, 64] if fd else []))
        msg = can.Message(arbitration_id=can_id, is_extended_id=extended, data=bytes(rng.randrange(256) for _ in range(length)),
                          is_fd=fd, bitrate_switch=fd, timestamp=rng.choice([0.0, 1.5, time.time()]),
                          channel=rng.choice([None, 3, "skin0"]))
        data = pack_message(msg)
        r = rng.random()
        if r < 0.05:
            data = data[:rng.randrange(len(data))]                        # cut short
        elif r < 0.1:
            data = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 120)))  # no python-can frame
        elif r < 0.15:
            i = rng.randrange(len(data))
            data = data[:i] + bytes([data[i] ^ (1 << rng.randrange(8))]) + data[i + 1:]  # one bit flipped
        out.append(data)
    return out


def python_keeps(filters, data: bytes) -> bool:
    """What the drain keeps by the first bytes (the rest is unpacked and filtered again)."""
    peeked = peek_id(data)
    return peeked is None or _matches(filters, *peeked)


def kernel_keeps(filters, data: bytes) -> bool:
    """What the kernel filter must keep: what Python keeps, and every datagram shorter than the
    program reads (left to Python, which may drop it)."""
    return len(data) < MIN_LENGTH or python_keeps(filters, data)


@pytest.mark.parametrize("seed", range(6))
def test_the_kernel_drops_only_what_python_would_drop(seed):
    rng = random.Random(seed)
    port = multicast_port()
    bus = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        tune_udp_multicast(bus)
        filters = random_filters(rng)
        assert set_filters(bus, filters) is True
        datagrams = random_datagrams(rng, 400)
        sock = bus._multicast._socket
        got = []
        for data in datagrams:
            tx.sendto(data, (GROUP, port))
            while True:
                try:
                    got.append(sock.recv(4096, socket.MSG_DONTWAIT))
                except BlockingIOError:
                    break
        deadline = time.monotonic() + 1.0
        expected = [d for d in datagrams if kernel_keeps(filters, d)]
        while len(got) < len(expected) and time.monotonic() < deadline:
            try:
                got.append(sock.recv(4096, socket.MSG_DONTWAIT))
            except BlockingIOError:
                time.sleep(0.01)
        time.sleep(0.05)
        while True:
            try:
                got.append(sock.recv(4096, socket.MSG_DONTWAIT))
            except BlockingIOError:
                break
        assert got == expected
        assert len(expected) < len(datagrams)  # the filters dropped some: the kernel filter did work
        assert set_filters(bus, None) is False
        tx.sendto(datagrams[0], (GROUP, port))
        time.sleep(0.05)
        assert sock.recv(4096, socket.MSG_DONTWAIT) == datagrams[0]   # no kernel filter left
    finally:
        tx.close()
        bus.shutdown()


def test_frames_through_the_bus_are_what_python_filters_alone_give():
    port = multicast_port()
    rx = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    tx = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    try:
        filters = [{"can_id": 0x080, "can_mask": 0x7FF, "extended": False},
                   {"can_id": 0x600, "can_mask": 0x780, "extended": False}]
        assert set_filters(rx, filters)
        for can_id in (0x080, 0x181, 0x605, 0x701, 0x67F, 0x081):
            tx.send(can.Message(arbitration_id=can_id, data=b"\x01", is_extended_id=False))
        tx.send(can.Message(arbitration_id=0x080, data=b"\x01", is_extended_id=True))
        got = []
        while (msg := rx.recv(0.2)) is not None:
            got.append((msg.arbitration_id, msg.is_extended_id))
        assert got == [(0x080, False), (0x605, False), (0x67F, False)]
    finally:
        rx.shutdown()
        tx.shutdown()


def test_filters_the_program_cannot_express_are_left_to_python():
    assert compile_filters([{"can_id": 2 ** 32, "can_mask": 0x7FF}]) is None
    assert compile_filters([{"can_id": 0x80, "can_mask": 2 ** 33}]) is None
    many = [{"can_id": k, "can_mask": 0x7FF} for k in range(1200)]
    assert compile_filters(many) is None                   # more than a program holds
    program = compile_filters([{"can_id": 0x80, "can_mask": 0x7FF}])
    assert program is not None and len(program) % 8 == 0


def test_a_sync_sent_once_the_sdo_answer_came_reaches_the_twin_whose_cob_id_it_moved(monkeypatch):
    """node_sim: an SDO write moving a node's SYNC COB-ID (0x1005) widens its channel's filters;
    the answer leaves only once the kernel filter has the new COB-ID, so a master's SYNC sent on
    it as soon as the answer came is heard - even with the filter's update slowed down."""
    import struct as struct_

    from node_sim.rig import Rig
    from taxel_net import udp_filter
    from taxel_net.scene import load_scene

    compile_now = udp_filter.compile_filters

    def slow_compile(filters):
        time.sleep(0.05)
        return compile_now(filters)

    monkeypatch.setattr(udp_filter, "compile_filters", slow_compile)
    root = Path(__file__).resolve().parent.parent
    scene = load_scene(root / "scenes" / "gripper18.toml")
    port = multicast_port()
    master = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    rig = Rig(scene, interface="udp_multicast", channel=[GROUP] * len(scene.bus.channels),
              bus_kwargs={"port": port, "hop_limit": 0}).start()
    try:
        node_id = sorted(rig._channels[0].nodes)[0]
        master.send(can.Message(arbitration_id=0x000, data=bytes([0x01, 0]), is_extended_id=False))
        time.sleep(0.3)
        while master.recv(0.05) is not None:
            pass
        master.send(can.Message(arbitration_id=0x600 + node_id, is_extended_id=False,
                                data=bytes([0x23, 0x05, 0x10, 0]) + struct_.pack("<I", 0x010)))
        deadline = time.monotonic() + 2
        while time.monotonic() < deadline:
            msg = master.recv(0.1)
            if msg is not None and msg.arbitration_id == 0x580 + node_id:
                break
        assert msg is not None and msg.data[0] == 0x60                     # the write was taken
        master.send(can.Message(arbitration_id=0x010, data=b"\x01", is_extended_id=False))
        answers = []
        deadline = time.monotonic() + 1
        while time.monotonic() < deadline:
            msg = master.recv(0.1)
            if msg is not None and msg.arbitration_id == 0x180 + node_id:   # its TPDO1 on that SYNC
                answers.append(msg.arbitration_id)
        assert answers, "the SYNC on the new COB-ID was not heard"
    finally:
        rig.stop()
        master.shutdown()


def _drain_raw(sock, settle: float = 0.05) -> list[bytes]:
    time.sleep(settle)
    got = []
    while True:
        try:
            got.append(sock.recv(4096, socket.MSG_DONTWAIT))
        except BlockingIOError:
            return got


@pytest.mark.parametrize("seed", range(3))
def test_the_kernel_drops_a_sender_s_own_tagged_datagrams_and_only_those(seed):
    """drop_own_frames: the datagrams whose python-can ``timestamp`` float64 is the bus's tag are
    dropped before they are queued - with and without ID filters, which keep their own rule - and
    every other datagram (python-can's with any other time stamp, other layouts, cut short,
    random bytes) is left as before."""
    import struct as struct_

    from taxel_net.udp_filter import drop_own_frames, own_tag

    rng = random.Random(seed)
    port = multicast_port()
    bus = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        tune_udp_multicast(bus)
        filters = random_filters(rng) if seed else None
        if filters:
            set_filters(bus, filters)
        tag = drop_own_frames(bus)
        assert tag is not None and -2.0 ** 31 <= tag < -2.0 ** 30 and own_tag(bus) == tag  # no clock's stamp
        packed = struct_.pack(">d", tag)
        datagrams = random_datagrams(rng, 300)
        for k in range(0, len(datagrams), 3):  # a third of them carry the tag where python-can's layout has it
            data = datagrams[k]
            if data.startswith(b"\x8b\xa9timestamp\xcb") and len(data) >= 20:
                datagrams[k] = data[:12] + packed + data[20:]
        near = bytearray(datagrams[3])
        near[19] ^= 1                                     # one bit off the tag: not ours
        datagrams.append(bytes(near))
        sock = bus._multicast._socket
        got = []
        for data in datagrams:
            tx.sendto(data, (GROUP, port))
            got += _drain_raw(sock, 0)
        got += _drain_raw(sock)

        def own(data: bytes) -> bool:
            return len(data) >= MIN_LENGTH and data.startswith(b"\x8b\xa9timestamp\xcb") and data[12:20] == packed

        expected = [d for d in datagrams if not own(d) and (filters is None or kernel_keeps(filters, d))]
        assert got == expected
        assert any(own(d) for d in datagrams) and own(datagrams[3]) and not own(datagrams[-1])
        if filters:  # filters set after the tag keep it; none at all: the tag alone
            set_filters(bus, filters)
            tx.sendto(datagrams[3], (GROUP, port))
            assert _drain_raw(sock) == []
        set_filters(bus, None)
        tx.sendto(datagrams[3], (GROUP, port))
        tx.sendto(datagrams[-1], (GROUP, port))
        assert _drain_raw(sock) == [datagrams[-1]]     # the tag outlives the filters' removal
    finally:
        tx.close()
        bus.shutdown()


def test_a_tagged_frame_is_the_frame_bus_send_sends_to_every_other_receiver():
    """The tag is python-can's ``timestamp`` field, which receivers replace with their receive
    time: another bus gets the same frame as from ``bus.send``; the sender's own socket none of
    it; a byte-identical frame of another sender (no tag) reaches the tagged bus."""
    from taxel_net.udp_filter import drop_own_frames
    from taxel_net.udp_wire import udp_multicast_burst_sender

    port = multicast_port()
    centre = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    other = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    try:
        tag = drop_own_frames(centre)
        assert tag is not None
        send = udp_multicast_burst_sender(centre, stamp=tag)
        sent_after = time.time()
        send([(0x080, b""), (0x240, bytes((0x0F, 0, 0x64, 0, 0, 0, 0, 0)))])
        other.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))  # another master's SYNC
        seen = []
        while (msg := other.recv(0.2)) is not None:
            seen.append(msg)
        assert [(m.arbitration_id, bytes(m.data), m.is_extended_id, m.is_fd, m.dlc) for m in seen[:2]] == \
            [(0x080, b"", False, False, 0), (0x240, bytes((0x0F, 0, 0x64, 0, 0, 0, 0, 0)), False, False, 8)]
        read_by = time.time()
        # the receiver's own stamp (the same clock, microseconds), not the tag the datagrams carried
        assert all(m.timestamp != tag and sent_after - 1e-6 <= m.timestamp <= read_by for m in seen), \
            ([m.timestamp for m in seen], tag, sent_after, read_by)
        heard = []
        while (msg := centre.recv(0.2)) is not None:
            heard.append((msg.arbitration_id, bytes(msg.data)))
        assert heard == [(0x080, b"")]                                     # the other sender's only
    finally:
        centre.shutdown()
        other.shutdown()


def test_filters_the_bus_was_opened_with_stay_python_s_so_a_later_set_filters_still_works():
    """drop_own_frames puts in the kernel only the ID filters set_filters put there: a bus opened
    with ``can_filters`` and given others later by python-can's own ``bus.set_filters`` receives
    what the new filters let through (a review's finding: the opening filters were copied into
    the kernel, which then dropped 0x181 that the new filters allow)."""
    from taxel_net.udp_filter import drop_own_frames

    port = multicast_port()
    bus = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0,
                  can_filters=[{"can_id": 0x700, "can_mask": 0x780, "extended": False}])
    other = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    try:
        assert drop_own_frames(bus) is not None
        bus.set_filters([{"can_id": 0x180, "can_mask": 0x780, "extended": False}])
        other.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        got = bus.recv(2.0)
        assert got is not None and got.arbitration_id == 0x181
    finally:
        bus.shutdown()
        other.shutdown()
