"""python-can's ``udp_multicast`` frames read and written straight on the socket.

python-can's ``UdpMulticastBus`` carries one CAN frame per datagram: the ``msgpack`` map of
``can.interfaces.udp_multicast.utils.pack_message`` (eleven fields in a fixed order, the data as
``bin``), stamped on receipt with the kernel's time (``SO_TIMESTAMPNS``). At skin scale
(scenes/skin4096.toml: ~100 frames every 10 ms on 8 groups) the per-frame Python around the
system call is most of what the centre and the twins spend on the bus, so both ends work on the
datagrams directly, byte for byte what python-can reads and writes:

* :func:`udp_multicast_drain` - every frame a bus's socket holds now, without blocking, as
  ``bus.recv(0)`` would return them (filters applied, kernel time stamps); a frame the bus's
  filters refuse is dropped from its first 60 bytes, before it is unpacked (the twins hear
  every frame they send: udp_multicast loops each datagram back to every member of the group
  on the host).
* :func:`udp_multicast_burst_sender` - the datagrams of a burst of 11-bit data frames built
  from a cached prefix per (COB-ID, length, FD) and sent one ``sendto`` each: the same bytes as
  ``bus.send(can.Message(...))``, without a ``can.Message`` and a ``msgpack`` map per frame.

Both return None for any other bus, or a python-can whose layout they do not know (the caller
then uses ``bus.recv`` / ``bus.send``).
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import time
from typing import Callable, Iterator

import can

logger = logging.getLogger("taxel_net.receiver")

# The start of every python-can datagram (pack_message's map of 11 fields: "timestamp" with a
# float64, then "arbitration_id", then "is_extended_id"); the COB-ID and the ID-format flag sit
# at fixed places after it once the ID's msgpack width is known.
_MAP_TIMESTAMP = b"\x8b\xa9timestamp\xcb"     # fixmap(11), fixstr "timestamp", float64 marker
_ARBITRATION_ID = b"\xaearbitration_id"
_IS_EXTENDED_ID = b"\xaeis_extended_id"
_ID_AT = len(_MAP_TIMESTAMP) + 8 + len(_ARBITRATION_ID)    # 35: the COB-ID's msgpack integer
_UINT = {0xCC: (1, struct.Struct(">B")), 0xCD: (2, struct.Struct(">H")), 0xCE: (4, struct.Struct(">I"))}


def peek_id(data: bytes) -> tuple[int, bool] | None:
    """``(arbitration_id, is_extended_id)`` of a python-can datagram read from its first bytes
    without unpacking it, or None where its start is not the layout above (the caller unpacks
    it in full: a datagram of another layout, or none of python-can's)."""
    if not data.startswith(_MAP_TIMESTAMP) or data[20:_ID_AT] != _ARBITRATION_ID:
        return None
    marker = data[_ID_AT:_ID_AT + 1]
    if not marker:
        return None
    first = marker[0]
    if first < 0x80:                       # positive fixint
        can_id, flag_at = first, _ID_AT + 1
    elif first in _UINT:
        width, fmt = _UINT[first]
        if len(data) < _ID_AT + 1 + width:
            return None
        can_id, = fmt.unpack_from(data, _ID_AT + 1)
        flag_at = _ID_AT + 1 + width
    else:
        return None
    if data[flag_at:flag_at + len(_IS_EXTENDED_ID)] != _IS_EXTENDED_ID:
        return None
    flag = data[flag_at + len(_IS_EXTENDED_ID):flag_at + len(_IS_EXTENDED_ID) + 1]
    if flag == b"\xc2":
        return can_id, False
    if flag == b"\xc3":
        return can_id, True
    return None


def _matches(filters, can_id: int, extended: bool) -> bool:
    """python-can's ``BusABC._matches_filters`` on the fields of a frame not yet a Message."""
    for f in filters:
        if "extended" in f and f["extended"] != extended:
            continue
        if (f["can_id"] ^ can_id) & f["can_mask"] == 0:
            return True
    return False


# the fields of python-can's ``pack_message`` map, the keyword arguments of ``can.Message``
PACKED_FIELDS = frozenset(("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame",
                           "channel", "dlc", "data", "is_fd", "bitrate_switch", "error_state_indicator"))
_new_message = can.Message.__new__


def message_from_fields(fields: dict, timestamp: float) -> can.Message:
    """``can.Message(check=True, **fields)`` with ``timestamp`` in place of the map's: what
    python-can's ``UdpMulticastBus`` makes of a datagram it read (``unpack_message(data,
    replace={"timestamp": ...}, check=True)``), the same attributes of the same types, the same
    errors. A data frame whose fields are exactly what ``pack_message`` writes and pass every
    check of ``Message._check`` (an 11- or 29-bit ID in range, ``bytes`` data of the DLC's
    length, at most 8 bytes classic or 64 FD, no bit-rate switch or error state indicator on a
    classic frame) has its attributes set directly, in half the constructor's time (0.9 against
    1.8 µs; ~100 datagrams a cycle at skin scale); any other map goes through the constructor."""
    if len(fields) == 11 and 0.0 <= timestamp < math.inf:
        try:  # eleven fields, each of pack_message's names: exactly its map
            can_id, extended, remote, error, channel, dlc, data, fd, brs, esi, _ = (
                fields["arbitration_id"], fields["is_extended_id"], fields["is_remote_frame"],
                fields["is_error_frame"], fields["channel"], fields["dlc"], fields["data"], fields["is_fd"],
                fields["bitrate_switch"], fields["error_state_indicator"], fields["timestamp"])
        except KeyError:
            pass
        else:
            if (type(can_id) is int and type(data) is bytes and type(dlc) is int and remote is False
                    and error is False and dlc == len(data)
                    and (0 <= can_id < 0x800 if extended is False else extended is True and 0 <= can_id < 0x20000000)
                    and (dlc <= 64 if fd is True else fd is False and dlc <= 8 and not brs and not esi)):
                msg = _new_message(can.Message)
                msg.timestamp = timestamp
                msg.arbitration_id = can_id
                msg.is_extended_id = extended
                msg.is_remote_frame = False
                msg.is_error_frame = False
                msg.channel = channel
                msg.is_fd = fd
                msg.is_rx = True
                msg.bitrate_switch = brs
                msg.error_state_indicator = esi
                msg.data = bytearray(data)
                msg.dlc = dlc
                return msg
    fields["timestamp"] = timestamp
    return can.Message(check=True, **fields)


def udp_multicast_drain(bus: can.BusABC) -> Callable[[], Iterator[can.Message]] | None:
    """For a python-can 4.x ``UdpMulticastBus`` with kernel nanosecond time stamps: a function
    yielding the frames its socket holds now, without blocking - what ``bus.recv(0)`` returns in
    turn (the bus's filters applied, ``set_filters`` taking effect at the next call), read at
    one system call a frame, and a frame the filters refuse dropped before it is unpacked (or,
    where its start is not python-can's usual layout, before a ``can.Message`` is made of
    it). A datagram that is no python-can frame is skipped and logged (at most a line a
    second, with the count), where ``bus.recv`` raises and so ends the reading of the bus.
    None for any other bus (or another python-can layout): read it with ``bus.recv(0)``."""
    multicast = getattr(bus, "_multicast", None)
    sock = getattr(multicast, "_socket", None)
    if (not isinstance(sock, socket.socket) or not getattr(multicast, "timestamp_nanosecond", False)
            or not hasattr(bus, "_can_protocol") or not hasattr(bus, "_filters")):
        return None
    try:
        import msgpack
        from can.interfaces.udp_multicast.bus import SO_TIMESTAMPNS

        max_buffer = int(multicast.max_buffer)
        ancillary_size = int(multicast.received_ancillary_buffer_size)
        stamp = struct.Struct(multicast.received_timestamp_struct)
    except (ImportError, AttributeError, TypeError, ValueError, struct.error):
        return None
    fd_bus = bus._can_protocol is can.CanProtocol.CAN_FD
    recvmsg = sock.recvmsg
    dontwait = socket.MSG_DONTWAIT
    unpackb = msgpack.unpackb
    from_fields = message_from_fields
    undecodable = [0, float("-inf")]  # datagrams skipped, time of the last log line

    def drain() -> Iterator[can.Message]:
        while True:
            try:
                data, ancillary, _flags, _sender = recvmsg(max_buffer, ancillary_size, dontwait)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                raise can.CanOperationError(f"failed to receive from the udp_multicast socket: {exc}") from exc
            # as GeneralPurposeUdpMulticastBus.recv: one SO_TIMESTAMPNS control message
            if len(ancillary) != 1 or ancillary[0][0] != socket.SOL_SOCKET or ancillary[0][1] != SO_TIMESTAMPNS:
                raise can.CanOperationError("received control message type that was not requested")
            seconds, nanoseconds = stamp.unpack(ancillary[0][2])
            if nanoseconds >= 1_000_000_000:
                raise can.CanOperationError(f"Timestamp nanoseconds field was out of range: {nanoseconds}")
            filters = bus._filters
            if filters is not None:  # refused by its first bytes: not unpacked (module docstring)
                peeked = peek_id(data)
                if peeked is not None and not _matches(filters, *peeked):
                    continue
            try:  # as can.interfaces.udp_multicast.utils.unpack_message(data, replace=..., check=True)
                fields = unpackb(data, raw=False)
                if filters is not None and not _matches(filters, fields.get("arbitration_id", 0),
                                                        fields.get("is_extended_id", True)):
                    continue
                msg = from_fields(fields, seconds + nanoseconds * 1.0e-9)
            except Exception as exc:  # noqa: BLE001 - not a python-can frame: counted, skipped
                # (UdpMulticastBus.recv raises here, and a raising bus is no longer read: one stray
                # datagram on the group would deafen the receiver for good)
                undecodable[0] += 1
                now = time.monotonic()
                if now - undecodable[1] >= 1.0:
                    undecodable[1] = now
                    logger.warning("udp_multicast bus %s: %d datagram(s) that are no python-can frame skipped "
                                   "(last: %d bytes, %s: %s)", bus.channel_info, undecodable[0], len(data),
                                   type(exc).__name__, exc)
                continue
            if msg.is_fd and not fd_bus:  # as UdpMulticastBus._recv_internal: dropped
                continue
            yield msg

    return drain




def udp_multicast_burst_sender(bus: can.BusABC, stamp: float = 0.0) -> Callable[[list[tuple]], None] | None:
    """For a python-can 4.x ``UdpMulticastBus``: send a burst of 11-bit data frames (``(can_id,
    data)``, or ``(can_id, data, True)`` for CAN FD with bit-rate switch; ``node_sim.link``'s
    burst) as ``bus.send`` sends ``can.Message(arbitration_id=can_id, data=data,
    is_extended_id=False, is_fd=..., bitrate_switch=..., timestamp=stamp)`` for each, in order:
    the same datagram bytes (``pack_message``; the time stamp field ``stamp``, by default 0.0
    as a new Message's - receivers stamp the kernel's receive time; the centre writes its own
    tag there, :func:`taxel_net.udp_filter.drop_own_frames`), one ``sendto`` each, the same
    errors (an FD frame on a classic bus: ``CanOperationError``; a failed send:
    ``CanOperationError``, the frames before it sent). Each datagram is a cached prefix per
    (COB-ID, length, FD) + the data + a tail. None for any other bus, or a python-can whose
    datagrams these are not (checked once, on a probe frame, against ``pack_message``)."""
    multicast = getattr(bus, "_multicast", None)
    sock = getattr(multicast, "_socket", None)
    destination = getattr(multicast, "_send_destination", None)
    if not isinstance(sock, socket.socket) or destination is None or not hasattr(bus, "_can_protocol"):
        return None
    try:
        import msgpack
        from can.interfaces.udp_multicast.utils import pack_message
    except ImportError:
        return None
    fd_bus = bus._can_protocol is can.CanProtocol.CAN_FD
    prefixes: dict[tuple[int, int, bool], bytes] = {}
    tails = {}

    def pack(key, value) -> bytes:
        return msgpack.packb(key, use_bin_type=True) + msgpack.packb(value, use_bin_type=True)

    def prefix(can_id: int, length: int, fd: bool) -> bytes:
        bin_header = msgpack.packb(bytes(length), use_bin_type=True)[:-length or None]
        head = b"\x8b" + b"".join((pack("timestamp", float(stamp)), pack("arbitration_id", can_id), pack("is_extended_id", False),
                                  pack("is_remote_frame", False), pack("is_error_frame", False), pack("channel", None),
                                  pack("dlc", length), msgpack.packb("data", use_bin_type=True), bin_header))
        prefixes[can_id, length, fd] = head
        if fd not in tails:
            tails[fd] = pack("is_fd", fd) + pack("bitrate_switch", fd) + pack("error_state_indicator", False)
        return head

    probe = can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False, timestamp=float(stamp))
    if prefix(0x181, 2, False) + b"\x01\x02" + tails[False] != pack_message(probe):
        return None  # another python-can layout: bus.send per frame
    sendto = sock.sendto

    def send_many(frames: list[tuple]) -> None:
        for frame in frames:
            fd = len(frame) == 3
            can_id, data = frame[0], frame[1]
            if fd and not fd_bus:
                raise can.CanOperationError("cannot send FD message over bus with CAN FD disabled")
            head = prefixes.get((can_id, len(data), fd)) or prefix(can_id, len(data), fd)
            datagram = head + data + tails[fd]
            try:
                if sendto(datagram, destination) < len(datagram):
                    raise can.CanOperationError("failed to send via socket: datagram truncated")
            except OSError as error:
                raise can.CanOperationError("failed to send via socket") from error

    return send_many
