"""One receive thread for every bus that has a socket (udp_multicast, socketcan): the centre's
buses and each node-sim process's.

python-can's ``Notifier`` runs one thread per bus. With eight buses (scenes/skin4096.toml) the
centre's eight receive threads took one frame each per turn on the interpreter lock, and
received frames waited 200-800 ms before the centre saw them (most PDOs late). One thread that
waits on every bus's socket at once (``select``) and drains each ready bus before waiting again
handles the same traffic with far less delay (bench/skin_scale.py --shards 2, side by side:
SYNC -> record p99 18 ms against 27 ms, late PDOs 521 in 150 cycles against 12,014 in 300).
The node twins of a node-sim process serving four channels had the same four threads (and
heard every frame of their buses, their own included: udp_multicast loops each datagram back
to every member of its group on the host).
Frames of one bus keep their order; across buses the order is no more fixed than with one
thread per bus (each frame carries its own time stamp and cycle tag).

:class:`SelectNotifiers` gives each bus a ``Notifier``-like handle (``add_listener``,
``remove_listener``, ``stop``, ``exception``: what the centre, its LSS master and canopen's
``Network`` use), all served by one thread. Buses without a file descriptor (python-can's
``virtual``) keep a ``can.Notifier`` each (:func:`notifiers_for`).

A ``udp_multicast`` bus of python-can 4.x (Linux, kernel time stamps) is drained straight from
its socket (:func:`udp_multicast_drain`): the datagrams ready are read without blocking, each
unpacked with python-can's own ``unpack_message`` and stamped with the kernel's receive time,
exactly as ``bus.recv`` does, minus the ``select`` ``recv`` makes before every datagram; the
bus's filters (``set_filters``) are applied before a ``can.Message`` is made. Any other bus is
read with ``bus.recv(0)``.
"""

from __future__ import annotations

import logging
import select
import threading
from typing import Iterator, Sequence

import can

from .udp_wire import udp_multicast_drain

logger = logging.getLogger("taxel_net.receiver")


def has_socket(bus: can.BusABC) -> bool:
    """The bus has a file descriptor ``select`` can wait on (udp_multicast, socketcan)."""
    try:
        return bus.fileno() >= 0
    except (NotImplementedError, OSError, AttributeError, ValueError):
        return False


def _recv_all(bus: can.BusABC) -> Iterator[can.Message]:
    while (msg := bus.recv(0)) is not None:
        yield msg


class _Handle:
    """The ``Notifier`` of one bus, served by a :class:`SelectNotifiers` thread."""

    def __init__(self, owner: "SelectNotifiers", bus: can.BusABC, listeners):
        self.owner = owner
        self.bus = bus
        self.listeners = list(listeners)
        self.exception: Exception | None = None
        self.drain = udp_multicast_drain(bus) or (lambda: _recv_all(bus))

    def add_listener(self, listener) -> None:
        self.listeners.append(listener)

    def remove_listener(self, listener) -> None:
        self.listeners.remove(listener)

    def stop(self, timeout: float = 5.0) -> None:
        self.owner.stop(timeout)

    def dispatch(self, msg: can.Message) -> None:
        for listener in list(self.listeners):
            if hasattr(listener, "on_message_received"):
                listener.on_message_received(msg)
            else:
                listener(msg)


class SelectNotifiers:
    """One thread reading every bus of ``pairs`` (bus, listeners): ``handles[k]`` is bus k's."""

    def __init__(self, pairs: Sequence[tuple[can.BusABC, list]], timeout: float = 0.05, name: str = "can-receive"):
        self.handles = [_Handle(self, bus, listeners) for bus, listeners in pairs]
        self.timeout = timeout
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        by_fd = {h.bus.fileno(): h for h in self.handles}
        fds = list(by_fd)
        while not self._stop.is_set() and fds:
            try:
                ready, _, _ = select.select(fds, [], [], self.timeout)
            except (OSError, ValueError):  # a bus closed under us: only at shutdown
                if self._stop.is_set():
                    return
                raise
            for fd in ready:
                handle = by_fd[fd]
                try:
                    for msg in handle.drain():  # every frame this bus holds now
                        handle.dispatch(msg)
                except Exception as exc:  # noqa: BLE001 - as can.Notifier: note it, tell the listeners
                    if self._stop.is_set():
                        return
                    handle.exception = exc
                    for listener in list(handle.listeners):
                        on_error = getattr(listener, "on_error", None)
                        if on_error is not None:
                            on_error(exc)
                    logger.error("receive thread: bus %s: %s: %s - no longer read", handle.bus.channel_info,
                                 type(exc).__name__, exc)
                    fds.remove(fd)  # as a can.Notifier's thread ends: this bus is not read again

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)


def notifiers_for(pairs: Sequence[tuple[can.BusABC, list]], timeout: float = 0.05, name: str = "can-receive") -> list:
    """A ``Notifier``-like handle per bus, in order: one shared select thread when every bus has
    a socket, else a ``can.Notifier`` each."""
    if pairs and all(has_socket(bus) for bus, _ in pairs):
        return list(SelectNotifiers(pairs, timeout, name).handles)
    return [can.Notifier(bus, list(listeners), timeout=timeout) for bus, listeners in pairs]
