"""taxel_net/udp_wire.py: python-can's udp_multicast datagrams read and written on the socket."""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import can
import msgpack
import pytest
from can.interfaces.udp_multicast.utils import pack_message
from hypothesis import given, settings
from hypothesis import strategies as st

from taxel_net.udp_wire import PACKED_FIELDS, message_from_fields, peek_id, udp_multicast_burst_sender

ROOT = Path(__file__).resolve().parent.parent
GROUP = "239.74.163.41"
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)

messages = st.one_of(
    st.builds(lambda i, d, ts: can.Message(timestamp=ts, arbitration_id=i, data=d, is_extended_id=False),
              st.integers(0, 0x7FF), st.binary(max_size=8), st.floats(0, 2e9)),
    st.builds(lambda i, n: can.Message(arbitration_id=i, is_extended_id=True, is_remote_frame=True, dlc=n),
              st.integers(0, 0x1FFFFFFF), st.integers(0, 8)),
    st.builds(lambda i, n: can.Message(arbitration_id=i, data=bytes(n), is_extended_id=False, is_fd=True,
                                       bitrate_switch=True), st.integers(0, 0x7FF), st.sampled_from(FD_LENGTHS)),
)


SLOTS = tuple(name for name in can.Message.__slots__ if name != "__weakref__")
odd_values = st.one_of(st.booleans(), st.none(), st.integers(-2, 0x2000_0001), st.sampled_from((0x7FF, 0x800, 0x1FFF_FFFF)),
                       st.floats(allow_nan=True), st.binary(max_size=65), st.text(max_size=2),
                       st.lists(st.integers(0, 255), max_size=3))


def constructed(fields: dict, timestamp: float):
    """What python-can's constructor makes of the map (``unpack_message(..., replace=..., check=True)``):
    the message's attributes with their types, or the exception's type."""
    try:
        msg = can.Message(check=True, **{**fields, "timestamp": timestamp})
    except Exception as exc:  # noqa: BLE001 - compared by type
        return type(exc)
    return [(name, type(getattr(msg, name)), getattr(msg, name)) for name in SLOTS]


def made(fields: dict, timestamp: float):
    try:
        msg = message_from_fields(dict(fields), timestamp)
    except Exception as exc:  # noqa: BLE001 - compared by type
        return type(exc)
    assert type(msg) is can.Message
    return [(name, type(getattr(msg, name)), getattr(msg, name)) for name in SLOTS]


@settings(max_examples=400, deadline=None)
@given(messages, st.floats(0, 4e9), st.data())
def test_message_from_fields_is_python_cans_constructor(msg, timestamp, data):
    """A datagram's map made a ``can.Message`` directly gives the same attributes, of the same
    types, as python-can's ``Message(check=True, **fields)`` - and the same error where that
    refuses the map: for every frame python-can packs, and for maps with a field changed to a
    value of another type or out of range, a field dropped or one added."""
    fields = msgpack.unpackb(pack_message(msg), raw=False)
    assert fields.keys() == PACKED_FIELDS
    assert made(fields, timestamp) == constructed(fields, timestamp)
    changed = dict(fields)
    for _ in range(data.draw(st.integers(1, 3))):
        key = data.draw(st.sampled_from(sorted(PACKED_FIELDS) + ["is_rx", "other"]))
        if data.draw(st.booleans()) and key in changed:
            del changed[key]
        else:
            changed[key] = data.draw(odd_values)
    stamp = data.draw(st.one_of(st.just(timestamp), st.floats(allow_nan=True, allow_infinity=True)))
    assert made(changed, stamp) == constructed(changed, stamp)


@pytest.mark.parametrize("field, value", [
    ("arbitration_id", 0x800), ("arbitration_id", -1), ("dlc", 9), ("dlc", 7), ("is_remote_frame", True),
    ("is_error_frame", 1), ("bitrate_switch", True), ("error_state_indicator", 1), ("data", bytearray(8)),
    ("is_fd", 1), ("is_extended_id", 0)])
def test_message_from_fields_refuses_or_passes_on_what_the_constructor_would(field, value):
    """The borders of the direct path, one field at a time on a classic 8-byte frame: each value
    either made into the same message as the constructor's or refused with its error."""
    fields = msgpack.unpackb(pack_message(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)),
                             raw=False)
    fields[field] = value
    assert made(fields, 12.5) == constructed(fields, 12.5)
    assert made(fields, -1.0) == constructed(fields, -1.0) is ValueError


@settings(max_examples=300, deadline=None)
@given(messages)
def test_peek_id_reads_the_id_python_can_packed(msg):
    """The COB-ID and ID format read from a datagram's first bytes are the ones its msgpack map
    holds (every integer width of the ID: fixint, uint8, uint16, uint32)."""
    data = pack_message(msg)
    fields = msgpack.unpackb(data, raw=False)
    assert peek_id(data) == (fields["arbitration_id"], fields["is_extended_id"]) \
        == (msg.arbitration_id, msg.is_extended_id)


@settings(max_examples=300, deadline=None)
@given(messages, st.data())
def test_peek_id_never_guesses_on_a_cut_or_altered_start(msg, data):
    """A datagram cut short or with a changed byte in its start is either read right (the
    change did not touch the fields read) or refused (None, the caller unpacks it): never a
    wrong ID, never an exception."""
    datagram = bytearray(pack_message(msg))
    cut = data.draw(st.integers(0, len(datagram)))
    assert peek_id(bytes(datagram[:cut])) in (None, (msg.arbitration_id, msg.is_extended_id))
    at = data.draw(st.integers(0, min(60, len(datagram) - 1)))
    datagram[at] ^= data.draw(st.integers(1, 255))
    peeked = peek_id(bytes(datagram))
    if peeked is not None:
        try:
            fields = msgpack.unpackb(bytes(datagram), raw=False)
        except Exception:  # noqa: BLE001 - the change broke the map after the fields read
            fields = None
        if isinstance(fields, dict) and "arbitration_id" in fields:
            assert peeked == (fields["arbitration_id"], fields["is_extended_id"])
    assert peek_id(b"") is None and peek_id(b"\x81\xa1a\x01") is None


class _Recorder(socket.socket):
    """A (never bound) UDP socket standing in for the bus's: records what ``sendto`` is given."""

    def __init__(self):
        super().__init__(socket.AF_INET, socket.SOCK_DGRAM)
        self.sent = []

    def sendto(self, data, destination):
        self.sent.append((bytes(data), destination))
        return len(data)


def _bus(fd: bool) -> can.BusABC:
    sys.path.insert(0, str(ROOT / "tests"))
    from test_service_multiprocess import multicast_port

    return can.Bus(interface="udp_multicast", channel=GROUP, port=multicast_port(), hop_limit=0, fd=fd)


def test_burst_sender_sends_what_bus_send_would():
    """Byte for byte the datagrams python-can's ``bus.send`` makes of the same frames, to the
    same destination, in order; an FD frame on a classic bus refused as by ``bus.send``."""
    frames = ([(can_id, bytes(range(n))) for can_id in (0x000, 0x07F, 0x080, 0x181, 0x7FF) for n in range(9)]
              + [(0x281, bytes(n), True) for n in FD_LENGTHS] + [(0x181, bytearray(b"\x05\x06"))])
    for fd in (False, True):
        bus = _bus(fd)
        try:
            multicast = bus._multicast
            real = multicast._socket
            recorder = _Recorder()
            multicast._socket = recorder   # what the sender captures, and what bus.send uses below
            try:
                send_many = udp_multicast_burst_sender(bus)
                assert send_many is not None
                usable = [f for f in frames if fd or len(f) == 2]
                send_many(usable)
                burst = recorder.sent[:]
                recorder.sent.clear()
                for f in usable:
                    bus.send(can.Message(arbitration_id=f[0], data=f[1], is_extended_id=False, is_fd=len(f) == 3,
                                         bitrate_switch=len(f) == 3))
                assert len(burst) == len(usable) and burst == recorder.sent
                if not fd:
                    with pytest.raises(can.CanOperationError):
                        send_many([(0x281, bytes(12), True)])
            finally:
                multicast._socket = real
                recorder.close()
        finally:
            bus.shutdown()
    virtual = can.Bus(interface="virtual", channel="udp-wire-virtual")
    assert udp_multicast_burst_sender(virtual) is None
    virtual.shutdown()


def test_burst_reaches_a_python_can_receiver():
    """Sent on the group for real: a second bus's ``recv`` gets every frame, fields intact."""
    tx = _bus(True)
    rx = can.Bus(interface="udp_multicast", channel=GROUP, port=tx._multicast.port, hop_limit=0, fd=True)
    try:
        frames = [(0x181, b"\x01\x02\x03"), (0x282, bytes(range(24)), True), (0x080, b"")]
        udp_multicast_burst_sender(tx)(frames)
        got = []
        while len(got) < len(frames) and (m := rx.recv(2.0)) is not None:
            got.append(m)
        assert [(m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch, m.is_extended_id) for m in got] \
            == [(f[0], f[1], len(f) == 3, len(f) == 3, False) for f in frames]
        assert all(m.timestamp > 1e9 for m in got)   # the receiver's time stamp, as for bus.send
    finally:
        tx.shutdown()
        rx.shutdown()
