"""CAN glue shared by the fusion centre's service and the node twins (not numerical core).

:class:`TxMessage` is a frame this process sends: a plain ``can.Message`` whose deep copy is
cheap. python-can's ``virtual`` interface deep-copies every sent frame once per receiving bus,
and ``Message.__deepcopy__`` goes through ``copy.deepcopy`` of the channel and the data
bytearray (~5 µs a frame: most of a node twin's cost per frame, and on the master's SYNC path).
This copy builds the same ``can.Message`` directly (the data copied into a new bytearray; the
channel is a str, int or None, immutable); every other field is copied as python-can does.
Other interfaces never copy.

:func:`raise_receive_buffer` gives a ``udp_multicast`` bus a socket receive buffer large enough
for bursts (python-can leaves the kernel default, 208 KiB on Linux: 57 concurrent SDO clients
made the kernel drop datagrams of the node-sim process, and with them transfers).
"""

from __future__ import annotations

import logging
import socket
import sys

import can

logger = logging.getLogger(__name__)

UDP_RECEIVE_BUFFER = 4 * 1024 * 1024  # bytes asked for (Linux reports and allots twice this)


class TxMessage(can.Message):
    """A ``can.Message`` with a cheap, field-for-field ``__deepcopy__`` (see module docstring)."""

    __slots__ = ()

    def __deepcopy__(self, memo) -> can.Message:
        return can.Message(
            timestamp=self.timestamp, arbitration_id=self.arbitration_id,
            is_extended_id=self.is_extended_id, is_remote_frame=self.is_remote_frame,
            is_error_frame=self.is_error_frame, channel=self.channel, dlc=self.dlc,
            data=bytearray(self.data), is_fd=self.is_fd, is_rx=self.is_rx,
            bitrate_switch=self.bitrate_switch, error_state_indicator=self.error_state_indicator)


def raise_receive_buffer(bus: can.BusABC, size: int = UDP_RECEIVE_BUFFER) -> int | None:
    """Raise the receive buffer (SO_RCVBUF) of a python-can ``udp_multicast`` bus's socket to
    ``size`` bytes and return the effective size read back (Linux doubles the value asked for,
    for its bookkeeping); None for any other bus. Never lowers it. The kernel caps SO_RCVBUF at
    ``net.core.rmem_max``; a process allowed to (CAP_NET_ADMIN) gets ``size`` anyway through
    SO_RCVBUFFORCE. Never raises: a buffer that cannot be raised stays as it was (logged, INFO)."""
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)  # python-can 4.x UdpMulticastBus
    if not isinstance(sock, socket.socket):
        return None
    try:
        before = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        if before < size:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
            force = getattr(socket, "SO_RCVBUFFORCE", None)
            if force is not None and sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) < size:
                try:  # beyond net.core.rmem_max: only with CAP_NET_ADMIN
                    sock.setsockopt(socket.SOL_SOCKET, force, size)
                except OSError:
                    pass
        effective = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    except OSError as exc:
        logger.warning("udp_multicast: cannot raise the socket receive buffer: %s", exc)
        return None
    # INFO, not WARNING: a capped buffer still works (it only drops under bursts), and command
    # output must not depend on the host's sysctl
    logger.info("udp_multicast: socket receive buffer %d bytes (was %d, asked for %d%s)", effective, before,
                size, "" if effective >= size else "; capped: raise net.core.rmem_max")
    return effective


IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)      # Linux <linux/in.h>
IPV6_MULTICAST_ALL = getattr(socket, "IPV6_MULTICAST_ALL", 29)  # Linux <linux/in6.h>, kernel >= 4.20


def receive_own_groups_only(bus: can.BusABC) -> bool | None:
    """Make a python-can ``udp_multicast`` bus hear only its own group: True when set, False
    when the host has no such option (not Linux), None for any other bus.

    python-can binds the socket to ``("", port)``, and Linux then delivers to it every multicast
    datagram for that port of *any* group some socket of the host joined (``IP_MULTICAST_ALL``,
    on by default): two scene channels on two groups with one port would hear each other's
    frames (the centre flags duplicate node-IDs). Turning the option off restricts the socket to
    the groups it joined itself, as separate CAN buses are."""
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if not isinstance(sock, socket.socket):
        return None
    if not sys.platform.startswith("linux"):
        return False
    level, option = ((socket.IPPROTO_IPV6, IPV6_MULTICAST_ALL) if sock.family == socket.AF_INET6
                     else (socket.IPPROTO_IP, IP_MULTICAST_ALL))
    try:
        sock.setsockopt(level, option, 0)
    except OSError as exc:
        logger.warning("udp_multicast: cannot restrict the socket to its own group: %s", exc)
        return False
    return True


def tune_udp_multicast(bus: can.BusABC) -> None:
    """What every ``udp_multicast`` bus of twins and centre gets: its own group only
    (:func:`receive_own_groups_only`) and a large receive buffer (:func:`raise_receive_buffer`);
    nothing for other interfaces."""
    receive_own_groups_only(bus)
    raise_receive_buffer(bus)
