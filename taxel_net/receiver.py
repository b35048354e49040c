"""One receive thread for all the buses of a process (udp_multicast, socketcan, virtual): the
centre's buses and each node-sim process's.

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
``Network`` use), all served by one thread. python-can's ``virtual`` buses have no file
descriptor: :class:`VirtualNotifiers` serves them with one thread too, woken by their receive
queues (each bus's queue swapped for one that signals a shared event when a frame is put in
it; python-can's ``VirtualBus.send`` and :func:`node_sim.rig.channel.virtual_burst_sender` put
frames there). With a ``can.Notifier`` per bus, the demo of scenes/skin4096.toml ran sixteen
receive threads (eight buses for the centre, eight for the twins) in one process and fell
behind its 10 ms SYNC for good (p50 29 ms, 7,001 of ~8,800 PDOs late in 100 cycles). Other
buses keep a ``can.Notifier`` each (:func:`notifiers_for`).

A ``udp_multicast`` bus of python-can 4.x (Linux, kernel time stamps) is drained straight from
its socket (:func:`udp_multicast_drain`): the datagrams ready are read without blocking, each
unpacked with python-can's own ``unpack_message`` and stamped with the kernel's receive time,
exactly as ``bus.recv`` does, minus the ``select`` ``recv`` makes before every datagram; the
bus's filters (``set_filters``) are applied before a ``can.Message`` is made. Any other bus is
read with ``bus.recv(0)``.
"""

from __future__ import annotations

import itertools
import logging
import queue
import select
import threading
from typing import Iterator, Sequence

import can

from .udp_wire import udp_multicast_drain

logger = logging.getLogger("taxel_net.receiver")

TURN_FRAMES = 256  # frames handled from one bus before the next bus's turn
# a listener with this method gets the frames of a turn in one call (its per-frame set-up - a
# lock, a dispatch - once per turn: at 4,096 taxels the centre takes ~100 frames a cycle) when
# every listener of the bus has it; such a listener does not change the bus's filters (the
# turn's frames were all read, and filtered, before it sees the first)
BATCH_METHOD = "on_messages_received"


def has_socket(bus: can.BusABC) -> bool:
    """The bus has a file descriptor ``select`` can wait on (udp_multicast, socketcan)."""
    try:
        return bus.fileno() >= 0
    except (NotImplementedError, OSError, AttributeError, ValueError):
        return False


def _recv_all(bus: can.BusABC) -> Iterator[can.Message]:
    """Every frame the bus holds now that its filters let through. Not ``bus.recv(0)`` in a
    loop: with no time left, ``recv`` returns None at the first frame its filters refuse, even
    with more frames queued behind it (the twins' receive thread, on virtual buses flooded with
    frames they filter out, then handled one frame per wake-up and fell seconds behind)."""
    recv_internal = getattr(bus, "_recv_internal", None)
    matches = getattr(bus, "_matches_filters", None)
    if recv_internal is None or matches is None:  # not a python-can 4.x BusABC: its public recv
        while (msg := bus.recv(0)) is not None:
            yield msg
        return
    while True:  # what BusABC.recv does for each frame, without its deadline
        msg, already_filtered = recv_internal(0.0)
        if msg is None:
            return
        if already_filtered or matches(msg):
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

    def dispatch_all(self, msgs: list[can.Message]) -> None:
        """The frames of one turn, in order, to every listener at once (each has
        ``on_messages_received``, :data:`BATCH_METHOD`)."""
        for listener in list(self.listeners):
            getattr(listener, BATCH_METHOD)(msgs)


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
                # the rest of a flooded bus's frames stays in its socket, ready at the next select
                if self._turn(by_fd[fd]) is None:
                    if self._stop.is_set():
                        return
                    fds.remove(fd)  # as a can.Notifier's thread ends: this bus is not read again

    def _turn(self, handle: _Handle) -> int | None:
        """One turn of a bus: the frames it holds now, at most TURN_FRAMES (a flooded bus does
        not starve the others), read, then handed to its listeners (:meth:`_Handle.dispatch_all`);
        returns how many. None when reading it failed - as a can.Notifier: the exception noted on
        the handle, the listeners told (``on_error``), one log line; not when the thread is
        stopping (a bus closed under it)."""
        msgs: list[can.Message] = []
        try:
            if all(hasattr(listener, BATCH_METHOD) for listener in handle.listeners):
                try:
                    msgs.extend(itertools.islice(handle.drain(), TURN_FRAMES))
                finally:  # what was read before a failure is still handed on, then the failure told
                    if msgs:
                        handle.dispatch_all(msgs)
            else:
                # frame by frame, read then handed on: the bus's filters apply to each frame as
                # its listeners left them after the one before (node_sim's channels widen
                # theirs when an SDO write moves a SYNC COB-ID)
                for msg in itertools.islice(handle.drain(), TURN_FRAMES):
                    msgs.append(msg)
                    handle.dispatch(msg)
        except Exception as exc:  # noqa: BLE001 - any failure of a bus ends its reading, not the thread
            if not self._stop.is_set():
                handle.exception = exc
                for listener in list(handle.listeners):
                    on_error = getattr(listener, "on_error", None)
                    if on_error is not None:
                        on_error(exc)
                logger.error("receive thread: bus %s: %s: %s - no longer read", handle.bus.channel_info,
                             type(exc).__name__, exc)
            return None
        return len(msgs)

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)


class _SignallingQueue(queue.Queue):
    """A ``VirtualBus`` receive queue that sets ``signal`` whenever a frame is put in it."""

    def __init__(self, maxsize: int, signal: threading.Event):
        super().__init__(maxsize)
        self.signal = signal

    def put(self, item, block: bool = True, timeout: float | None = None) -> None:
        super().put(item, block, timeout)
        if not self.signal.is_set():
            self.signal.set()


def _virtual_queue_swappable(bus: can.BusABC) -> bool:
    """A python-can 4.x ``VirtualBus`` whose receive queue (``queue``, listed in the shared
    channel list ``channel``) can be swapped (:class:`VirtualNotifiers`)."""
    try:
        from can.interfaces.virtual import VirtualBus
    except ImportError:  # pragma: no cover - python-can always ships it
        return False
    return (type(bus) is VirtualBus and isinstance(getattr(bus, "queue", None), queue.Queue)
            and isinstance(getattr(bus, "channel", None), list) and any(q is bus.queue for q in bus.channel))


def _move_queued(old: queue.Queue, new: queue.Queue) -> None:
    """Every frame in ``old`` put in ``new``, in order."""
    while True:
        try:
            new.put_nowait(old.get_nowait())
        except queue.Empty:
            return


class VirtualNotifiers(SelectNotifiers):
    """One thread reading every python-can ``virtual`` bus of ``pairs``: each bus's receive queue
    becomes a :class:`_SignallingQueue` (frames already queued moved over, in order), the thread
    waits on the shared event, clears it and drains every bus (``recv(0)``: the bus's filters
    apply) before waiting again - a frame put after the clear sets it again, so none waits for
    the ``timeout``."""

    def __init__(self, pairs: Sequence[tuple[can.BusABC, list]], timeout: float = 0.05, name: str = "can-receive"):
        from can.interfaces.virtual import channels_lock

        self._signal = threading.Event()
        for bus, _ in pairs:
            with channels_lock:
                old = bus.queue
                new = _SignallingQueue(old.maxsize, self._signal)
                _move_queued(old, new)
                bus.channel[next(k for k, q in enumerate(bus.channel) if q is old)] = new
                bus.queue = new
                _move_queued(old, new)  # from a sender that listed the channel's queues before the swap
        super().__init__(pairs, timeout, name)

    def _run(self) -> None:
        handles = list(self.handles)
        signal = self._signal
        while not self._stop.is_set() and handles:
            signal.wait(self.timeout)
            signal.clear()
            for handle in list(handles):
                taken = self._turn(handle)
                if taken is None:
                    if self._stop.is_set():
                        return
                    handles.remove(handle)
                elif taken == TURN_FRAMES:
                    signal.set()  # frames left in its queue: no wait before the next turn

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._signal.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)


def notifiers_for(pairs: Sequence[tuple[can.BusABC, list]], timeout: float = 0.05, name: str = "can-receive") -> list:
    """A ``Notifier``-like handle per bus, in order: one shared select thread when every bus has
    a socket, one shared thread when every bus is python-can's ``virtual``
    (:class:`VirtualNotifiers`), else a ``can.Notifier`` each."""
    if pairs and all(has_socket(bus) for bus, _ in pairs):
        return list(SelectNotifiers(pairs, timeout, name).handles)
    if pairs and all(_virtual_queue_swappable(bus) for bus, _ in pairs):
        return list(VirtualNotifiers(pairs, timeout, name).handles)
    return [can.Notifier(bus, list(listeners), timeout=timeout) for bus, listeners in pairs]
