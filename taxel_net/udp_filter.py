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
"""

from __future__ import annotations

import ctypes
import logging
import socket
import struct
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


def compile_filters(filters: Sequence[dict]) -> bytes | None:
    """The BPF program (``struct sock_filter`` array) of python-can ``filters`` (module
    docstring), or None when they cannot be expressed (an ID or mask beyond 32 bits, too many)."""
    for f in filters:
        if not (0 <= int(f["can_id"]) < 2 ** 32 and 0 <= int(f["can_mask"]) < 2 ** 32):
            return None
    p = _Program()
    p.op(_LD | _W | _LEN)                                   # A = datagram length (UDP header included)
    p.op(_JMP | _JGE | _K, PAYLOAD + MIN_LENGTH, 0, "accept")
    p.expect_bytes(_ABS, PAYLOAD, _MAP_TIMESTAMP)          # fixmap(11), "timestamp", float64
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


def set_filters(bus: can.BusABC, filters: Sequence[dict] | None) -> bool:
    """``bus.set_filters(filters)``, and on a ``udp_multicast`` bus the same filters in its
    socket's kernel filter (module docstring); None / no filters: the kernel filter removed.
    Returns whether the kernel filters the bus now."""
    bus.set_filters(filters)
    sock = _socket_of(bus)
    if sock is None:
        return False
    program = compile_filters(list(filters)) if filters else None
    try:
        if program is None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
            except OSError:  # none attached
                pass
            return False
        buffer = ctypes.create_string_buffer(program, len(program))
        sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER,
                        struct.pack("@HP", len(program) // 8, ctypes.addressof(buffer)))
        return True
    except OSError as exc:  # not Linux, or refused: Python's filtering alone
        logger.debug("udp_multicast bus %s: no kernel filter (%s)", bus.channel_info, exc)
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
        except OSError:
            pass
        return False
