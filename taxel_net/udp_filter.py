"""A ``udp_multicast`` bus's python-can filters applied in the kernel, as socketcan applies them.

python-can filters a ``udp_multicast`` bus in Python, after the datagram has been read. The
group loops every datagram back to every member on the host, so a ``node-sim`` process reads
all the frames its own patch nodes send (88 a cycle at 4,096 taxels) only to drop them, one
system call and a wake-up each. :func:`set_filters` sets the bus's filters
(``bus.set_filters``) and gives its socket a classic BPF program (``SO_ATTACH_FILTER``) that drops,
before they are queued, the datagrams python-can would drop: those in python-can's usual layout
(``taxel_net.udp_wire``: the map of ``pack_message`` starting with "timestamp" as a float64, then
"arbitration_id", then "is_extended_id") whose ID and format no filter lets through - with the
filters' own rule (``BusABC._matches_filters``: ``extended`` when given, then ``(id ^ can_id) &
can_mask == 0``). Every other datagram (another layout, shorter than the layout's first 60
bytes, none of python-can's) is left to the receiver, which filters again in Python
(:func:`taxel_net.udp_wire.udp_multicast_drain`), so the program can only drop what Python
would drop. Linux only; elsewhere, or for filters the program cannot express (a mask or ID
over 32 bits, more than fit a program), the bus keeps Python's filtering alone.

Filters set with ``bus.set_filters`` directly do not reach the kernel: use :func:`set_filters`.

**A sender's own frames** (:func:`drop_own_frames`): the group loops every datagram back to its
sender too, where a CAN controller never hands a node its own frames. The fusion centre sends its
datagrams with a tag of its own in python-can's ``timestamp`` field - a float64 that python-can's
receivers never read (``UdpMulticastBus`` and :func:`taxel_net.udp_wire.udp_multicast_drain`
replace it with the receive time stamp), so every receiver sees the frame it saw before - and
its socket's program drops the datagrams carrying that tag before they are queued: no wake-up,
no system call, no unpacking for an echo (the centre read its SYNC's echo in a receive turn of
its own, ~0.1 ms of the receive thread's time on the way to the cycle's command,
docs/grip-control.md). The tag is a negative number of about -1.6e9 with 52 random mantissa
bits: no clock writes it (a new ``can.Message`` and node_sim's senders write 0.0, a bridge or a
replay copies a receive or log time, all >= 0), and two centres on one group draw the same one
with a chance of 2^-52; datagrams of other senders, whatever their content, pass as before. The
program keeps the ID filters :func:`set_filters` put in the kernel, not those the bus was opened
with (``can_filters``), which stay Python's, so a later ``bus.set_filters`` changes what the bus
receives as it did before.
"""

from __future__ import annotations

import ctypes
import logging
import random
import socket
import struct
import weakref
from typing import Sequence

import can

from .udp_wire import _ARBITRATION_ID, _IS_EXTENDED_ID, _MAP_TIMESTAMP

logger = logging.getLogger("taxel_net.receiver")

SO_ATTACH_FILTER, SO_DETACH_FILTER = 26, 27  # <asm-generic/socket.h>
PAYLOAD = 8          # a UDP socket's filter sees the datagram from the UDP header on
MIN_LENGTH = 60      # shorter datagrams are left to Python (every load below stays inside)
ACCEPT, DROP = 0xFFFFFFFF, 0

# classic BPF (<linux/filter.h>): class | size | mode, jumps relative to the next instruction
_LD, _LDX, _ST, _ALU, _JMP, _RET = 0x00, 0x01, 0x02, 0x04, 0x05, 0x06
_W, _H, _B = 0x00, 0x08, 0x10
_IMM, _ABS, _IND, _MEM, _LEN = 0x00, 0x20, 0x40, 0x60, 0x80
_AND, _XOR = 0x50, 0xA0
_JA, _JEQ, _JGE = 0x00, 0x10, 0x30
_K = 0x00
_MAX_INSTRUCTIONS = 4096
TIMESTAMP_AT = PAYLOAD + len(_MAP_TIMESTAMP)  # the float64 of python-can's "timestamp" field

# bus -> the 8 bytes (big endian float64) its own datagrams carry in "timestamp" and its socket's
# program drops (drop_own_frames); set_filters keeps them in every program it attaches
_OWN_TAGS: "weakref.WeakKeyDictionary[can.BusABC, bytes]" = weakref.WeakKeyDictionary()
# bus -> the ID filters set_filters put in its socket's program (drop_own_frames keeps those only)
_KERNEL_FILTERS: "weakref.WeakKeyDictionary[can.BusABC, list]" = weakref.WeakKeyDictionary()


class _Program:
    """Instructions with symbolic forward jumps, resolved by :meth:`code`."""

    def __init__(self):
        self.lines: list[tuple[int, object, object, int]] = []
        self.labels: dict[str, int] = {}

    def op(self, code: int, k: int = 0, jt: object = 0, jf: object = 0) -> None:
        self.lines.append((code, jt, jf, k))

    def label(self, name: str) -> None:
        self.labels[name] = len(self.lines)

    def expect(self, load: int, offset: int, chunk: bytes) -> None:
        """Load ``len(chunk)`` (1, 2 or 4) bytes at ``offset`` (``_ABS``) or X + ``offset``
        (``_IND``); anything else than ``chunk`` accepts the datagram (left to Python)."""
        size = {1: _B, 2: _H, 4: _W}[len(chunk)]
        self.op(_LD | size | load, offset)
        self.op(_JMP | _JEQ | _K, int.from_bytes(chunk, "big"), 0, "accept")

    def expect_bytes(self, load: int, offset: int, expected: bytes) -> None:
        at = 0
        while at < len(expected):
            width = 4 if len(expected) - at >= 4 else 2 if len(expected) - at >= 2 else 1
            self.expect(load, offset + at, expected[at:at + width])
            at += width

    def code(self) -> bytes:
        out = []
        for index, (code, jt, jf, k) in enumerate(self.lines):
            jumps = []
            for target in (jt, jf):
                if isinstance(target, str):
                    target = self.labels[target] - index - 1
                if not 0 <= target <= 255:
                    raise OverflowError("jump out of reach")
                jumps.append(target)
            if code == _JMP | _JA and isinstance(k, str):
                k = self.labels[k] - index - 1
            out.append(struct.pack("HBBI", code, jumps[0], jumps[1], k))
        return b"".join(out)


def compile_filters(filters: Sequence[dict], own_tag: bytes | None = None) -> bytes | None:
    """The BPF program (``struct sock_filter`` array) of python-can ``filters`` (module
    docstring), or None when they cannot be expressed (an ID or mask beyond 32 bits, too many).
    ``own_tag`` (8 bytes): datagrams of python-can's layout whose ``timestamp`` float64 is
    exactly these bytes are dropped first (the sender's own, :func:`drop_own_frames`); with no
    ``filters`` every other datagram passes. No filters and no tag: None (no program)."""
    filters = list(filters or ())
    if not filters and own_tag is None:
        return None
    if own_tag is not None and len(own_tag) != 8:
        raise ValueError(f"own_tag: 8 bytes (a float64), got {len(own_tag)}")
    for f in filters:
        if not (0 <= int(f["can_id"]) < 2 ** 32 and 0 <= int(f["can_mask"]) < 2 ** 32):
            return None
    p = _Program()
    p.op(_LD | _W | _LEN)                                   # A = datagram length (UDP header included)
    p.op(_JMP | _JGE | _K, PAYLOAD + MIN_LENGTH, 0, "accept")
    p.expect_bytes(_ABS, PAYLOAD, _MAP_TIMESTAMP)          # fixmap(11), "timestamp", float64
    if own_tag is not None:  # the float64 is the sender's own tag: its own echo, dropped here
        p.op(_LD | _W | _ABS, TIMESTAMP_AT)
        p.op(_JMP | _JEQ | _K, int.from_bytes(own_tag[:4], "big"), 0, "not_own")
        p.op(_LD | _W | _ABS, TIMESTAMP_AT + 4)
        p.op(_JMP | _JEQ | _K, int.from_bytes(own_tag[4:], "big"), 0, "not_own")
        p.op(_RET | _K, DROP)   # (no scratch memory stored yet: the return may precede a label)
        p.label("not_own")
        if not filters:
            p.op(_JMP | _JA, "accept")
    p.expect_bytes(_ABS, PAYLOAD + 20, _ARBITRATION_ID)    # after the 8 bytes of the float
    at = PAYLOAD + 20 + len(_ARBITRATION_ID)                # the ID's msgpack marker
    p.op(_LD | _B | _ABS, at)
    p.op(_JMP | _JGE | _K, 0x80, "wide", 0)
    p.op(_ST, 0)                                            # positive fixint: M[0] = ID
    p.op(_LDX | _W | _IMM, at + 1)                          # X = where "is_extended_id" starts
    p.op(_JMP | _JA, "flag")
    p.label("wide")
    for marker, size, width in ((0xCC, _B, 1), (0xCD, _H, 2), (0xCE, _W, 4)):
        p.op(_JMP | _JEQ | _K, marker, 0, f"not{marker}")
        p.op(_LD | size | _ABS, at + 1)
        p.op(_ST, 0)
        p.op(_LDX | _W | _IMM, at + 1 + width)
        p.op(_JMP | _JA, "flag")
        p.label(f"not{marker}")
    p.op(_JMP | _JA, "accept")                              # another marker: left to Python
    p.label("flag")
    p.expect_bytes(_IND, 0, _IS_EXTENDED_ID)
    p.op(_LD | _B | _IND, len(_IS_EXTENDED_ID))
    p.op(_JMP | _JEQ | _K, 0xC2, "standard", 0)
    p.op(_JMP | _JEQ | _K, 0xC3, "extended", "accept")
    for name, extended in (("standard", False), ("extended", True)):
        p.label(name)
        for f in filters:
            if "extended" in f and bool(f["extended"]) != extended:
                continue
            p.op(_LD | _W | _MEM, 0)
            p.op(_ALU | _XOR | _K, int(f["can_id"]))
            p.op(_ALU | _AND | _K, int(f["can_mask"]))
            p.op(_JMP | _JEQ | _K, 0, "accept", 0)
        p.op(_JMP | _JA, "drop")
    # the returns last: the kernel's check of the scratch memory reads the program in order
    # and takes a return as falling through (a label right after one would look unset)
    p.label("drop")
    p.op(_RET | _K, DROP)
    p.label("accept")
    p.op(_RET | _K, ACCEPT)
    if len(p.lines) > _MAX_INSTRUCTIONS:
        return None
    try:
        return p.code()
    except OverflowError:
        return None


def _socket_of(bus: can.BusABC) -> socket.socket | None:
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    return sock if isinstance(sock, socket.socket) and sock.family in (socket.AF_INET, socket.AF_INET6) else None


def _attach(sock: socket.socket, program: bytes | None) -> bool:
    """``program`` attached to ``sock`` (None: any program detached); whether one is attached."""
    if program is None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
        except OSError:  # none attached
            pass
        return False
    buffer = ctypes.create_string_buffer(program, len(program))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, struct.pack("@HP", len(program) // 8, ctypes.addressof(buffer)))
    return True


def set_filters(bus: can.BusABC, filters: Sequence[dict] | None) -> bool:
    """``bus.set_filters(filters)``, and on a ``udp_multicast`` bus the same filters in its
    socket's kernel filter (module docstring); None / no filters: the kernel filter removed
    (but for the bus's own tag, :func:`drop_own_frames`, which every program keeps).
    Returns whether the kernel filters the bus's IDs now."""
    bus.set_filters(filters)
    _KERNEL_FILTERS.pop(bus, None)
    sock = _socket_of(bus)
    if sock is None:
        return False
    own = _OWN_TAGS.get(bus)
    if not filters:
        program = None
    else:  # (a bus without a tag: the filters' program as it always was)
        program = compile_filters(list(filters)) if own is None else compile_filters(list(filters), own)
    try:
        if program is None:  # no filters, or none the kernel can express: the own tag alone, if any
            _attach(sock, compile_filters((), own) if own is not None else None)
            return False
        _attach(sock, program)
        _KERNEL_FILTERS[bus] = list(filters)
        return True
    except OSError as exc:  # not Linux, or refused: Python's filtering alone
        logger.debug("udp_multicast bus %s: no kernel filter (%s)", bus.channel_info, exc)
        _OWN_TAGS.pop(bus, None)  # (its own frames come back again: the caller's echo filter takes them)
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
        except OSError:
            pass
        return False


_TAG_SIGN_EXPONENT = 0xC1D << 52  # sign 1, exponent 2^30: a float64 in [-2^31, -2^30)


def new_own_tag() -> float:
    """A tag for a bus's own datagrams (module docstring): a finite negative float64 in
    [-2^31, -2^30) with 52 random mantissa bits - no time stamp a clock writes."""
    bits = _TAG_SIGN_EXPONENT | random.SystemRandom().getrandbits(52)
    tag, = struct.unpack(">d", struct.pack(">Q", bits))
    return tag


def drop_own_frames(bus: can.BusABC) -> float | None:
    """On a ``udp_multicast`` bus (Linux): a tag for the bus's own datagrams, which its socket's
    kernel filter drops from now on (module docstring) - the ID filters :func:`set_filters` put
    in the kernel kept there; write it in the ``timestamp`` field of what the bus sends
    (:func:`taxel_net.udp_wire.udp_multicast_burst_sender` ``stamp``) and no echo of those
    comes back. None for any other bus, or where no filter can be attached (the echoes come
    back as before)."""
    sock = _socket_of(bus)
    if sock is None or not hasattr(bus, "_multicast"):
        return None
    tag = new_own_tag()
    packed = struct.pack(">d", tag)
    filters = _KERNEL_FILTERS.get(bus)
    program = compile_filters(filters, packed) if filters else None
    if program is None:  # no filters, or not expressible in the kernel (Python filters them)
        program = compile_filters((), packed)
    try:
        _attach(sock, program)
    except OSError as exc:
        logger.debug("udp_multicast bus %s: its own frames not dropped in the kernel (%s)", bus.channel_info, exc)
        return None
    _OWN_TAGS[bus] = packed
    return tag


def own_tag(bus: can.BusABC) -> float | None:
    """The tag :func:`drop_own_frames` gave the bus (its socket drops datagrams carrying it), or None."""
    packed = _OWN_TAGS.get(bus)
    return None if packed is None else struct.unpack(">d", packed)[0]
