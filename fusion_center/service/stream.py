"""The serialised event stream: every frame, received or sent, time-stamped and ordered.

Threads of a live run:

* the receive thread(s) (:mod:`taxel_net.receiver`: one thread selecting on every bus's socket for
  udp_multicast / socketcan, else one python-can ``Notifier`` thread per bus), one listener
  per bus, :class:`_StreamListener`: it
  feeds :meth:`EventStream.receive`, then hands canopen (SDO client, heartbeat and EMCY
  consumers of ``canopen.Network``) only the frames canopen has subscribed to - guarded: an
  exception is counted as ``internal_error`` and never escapes (a raising listener stops
  python-can's Notifier for good);
* the SYNC producer (:class:`~fusion_center.service.master.Master`), monotonic clock.

:class:`EventStream` is the single point where events are ordered: under one lock each
event is time-stamped (integer µs, clamped to be monotonic), queued for the trace and fed to
the :class:`CycleAssembler`. The trace (``can.Logger``) is written outside the stream lock,
in stream order, after every closed cycle has been evaluated (and every
:data:`TRACE_BATCH` events between cycles), so a killed process loses at most the trace of
the cycle in flight: at each cycle's close the writer hands what it holds to the OS
(:func:`~.trace_writers.flush_to_os`). ``replay``
(:mod:`fusion_center.service.traces`) feeds a trace through the same class, so it
reproduces the live records exactly.

Also here: :class:`RateLimitedLog` (one log line per cause and interval, shared by the
stream and the service).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Callable, Iterable, Sequence

import can

from taxel_net.canmsg import TxMessage
from taxel_net.errors import one_line
from taxel_net.udp_filter import own_tag
from taxel_net.udp_wire import udp_multicast_burst_sender
from .common_frames import CommonFrames
from .node_frames import NodeFrames
from .trace_writers import flush_to_os
from .decoder import COB_SYNC
from .cycle_records import (
    FLAG_ERROR,
    FLAG_EXTENDED,
    FLAG_FD,
    FLAG_REMOTE,
    ClosedCycle,
    quantise_timestamp,
)
from .cycles import CycleAssembler, counters_of

if TYPE_CHECKING:
    from .echo_filter import EchoFilter
    from .fusion_service import FusionService

logger = logging.getLogger("fusion_center.service")

TRACE_BATCH = 256  # events queued for the trace before it is written even if no cycle closed
# after a bus error that follows another with no frame between (_StreamListener.on_error): python-can's
# Notifier calls recv again at once, so a bus that fails for good was read in a tight loop
BUS_ERROR_BACKOFF_S = 0.05


class RateLimitedLog:
    """Log a cause at most once per ``interval`` seconds, with the count since the last line."""

    def __init__(self, log: logging.Logger, interval: float = 1.0):
        self.log = log
        self.interval = interval
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._lock = threading.Lock()

    def warning(self, cause: str, message: str, *args) -> None:
        now = time.monotonic()
        with self._lock:
            last = self._last.get(cause)
            if last is not None and now - last < self.interval:
                self._suppressed[cause] = self._suppressed.get(cause, 0) + 1
                return
            self._last[cause] = now
            suppressed = self._suppressed.pop(cause, 0)
        if suppressed:
            message += f" (+{suppressed} similar suppressed)"
        self.log.warning(message, *args)


def message_flags(msg: can.Message) -> int:
    flags = 0
    if msg.is_error_frame:
        flags |= FLAG_ERROR
    if msg.is_remote_frame:
        flags |= FLAG_REMOTE
    if msg.is_extended_id:
        flags |= FLAG_EXTENDED
    if msg.is_fd:
        flags |= FLAG_FD
    return flags


class EventStream:
    """Serialises events: time-stamp (µs, monotonic), trace, assembler - under one lock.

    ``on_closed(closed)`` is called under the lock for every cycle an event closes (keep it
    short: the service queues the cycle); ``after_closed()`` is called after the lock is
    released by :meth:`receive` / :meth:`transmit_all` when their event(s) closed a cycle
    (the service evaluates the queued cycles there). Trace messages are queued under the lock
    and written by :meth:`flush_trace` (in stream order), which the stream calls after
    ``after_closed`` and whenever :data:`TRACE_BATCH` messages are queued.
    """

    def __init__(self, assembler: CycleAssembler, *, trace: can.Listener | None = None,
                 on_closed: Callable[[ClosedCycle], None] | None = None,
                 after_closed: Callable[[], None] | None = None,
                 buses: Sequence[can.BusABC] = ()):
        self.assembler = assembler
        self.trace = trace
        self.on_closed = on_closed
        self.after_closed = after_closed
        self.buses = list(buses)
        self.lock = threading.Lock()
        self.fed = 0
        self.last_us: int | None = None
        self.first_us: int | None = None
        self.tx_errors = 0
        self.trace_errors = 0
        self.traced = 0                 # frames the trace writer took
        self.trace_error: str | None = None   # the failure that ended the trace (one line), None while fine
        self.not_traced = 0             # frames not given to the writer: the trace had ended
        self._fed_at_end: int | None = None   # ``fed`` when the trace ended
        self.rate_log = RateLimitedLog(logger)
        self._trace_queue: list[can.Message] = []
        self._trace_lock = threading.Lock()  # taken before ``lock``, never while holding it
        self.echoes: EchoFilter | None = None  # set by the service on udp_multicast
        # SYNCs received (not sent by this centre) once it has sent a frame: another SYNC
        # producer on the bus; counted ``foreign_sync``, traced, never a cycle (see _feed_locked)
        self.foreign_syncs = 0
        # the counters as of the last closed cycle - (counts, held, foreign SYNCs), one tuple replaced whole
        # under the lock, read without it (counters_snapshot: the live view; its refresh never waits for the
        # lock a real-time receive thread needs); before the first closed cycle, as of every receive turn
        self._published: tuple = self._snapshot_locked()
        self._publish_each_turn = True
        self._sent_any = False
        self._senders: dict[int, Callable[[list[tuple]], None] | None] = {}  # channel -> _direct_sender
        # channel -> its direct sender tags the datagrams its socket's kernel filter drops on their
        # way back (taxel_net.udp_filter.drop_own_frames): no echo to await (self.echoes)
        self._own_dropped: dict[int, bool] = {}
        self.echoes_dropped_in_kernel = 0  # frames sent so tagged: their echoes the kernel dropped
        # the common frames of a receive turn fed in one loop (None: each by _feed_locked): packed
        # patch TPDOs (.common_frames), or one-taxel nodes' TPDO1 / TPDO2 (.node_frames)
        self.common: CommonFrames | NodeFrames | None = (CommonFrames.for_assembler(assembler)
                                                         or NodeFrames.for_assembler(assembler))

    def _feed_locked(self, msg: can.Message, channel: int) -> bool:
        """Feed one event (stream lock held); True when it closed a cycle."""
        self.fed += 1
        try:
            # the frame's own time stamp (µs), not clamped to be monotonic: the assembler uses it
            # to tell a PDO sent before the open cycle's SYNC (late) from an answer to it, and
            # clamps its own clock; only a time before the first event is raised to it (a
            # trace cannot store a time before its start)
            us = quantise_timestamp(msg.timestamp)
            first = self.first_us
            if first is None:
                self.first_us = us
            elif us < first:
                us = first
            self.last_us = us
            if self.trace is not None:
                msg.timestamp = us / 1e6
                msg.channel = channel
                self._trace_queue.append(msg)
            flags = 0
            if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id or msg.is_fd:
                flags = message_flags(msg)
            if not msg.is_rx:
                self._sent_any = True
            elif (msg.arbitration_id == COB_SYNC and self._sent_any and not flags
                  and self.assembler._opens_cycle(bytes(msg.data))):
                # The centre is the SYNC producer (CiA 301: one per network). A well-formed SYNC
                # it did not send - another master, a tool - would open a cycle of its own (65
                # records for 60 SYNCs were seen). Received after the centre's first frame (a
                # trace the centre wrote has its NMT/SDO/heartbeat "Tx" frames first; a bus
                # monitor's trace has none, and its SYNCs stay SYNCs), it is counted and traced.
                # A malformed one is counted as malformed (bad_dlc / bad_value) by the assembler.
                self.foreign_syncs += 1
                self.rate_log.warning("foreign_sync", "channel %d: a SYNC this centre did not send (another SYNC "
                                      "producer on the bus?): no cycle, counted foreign_sync (total %d)",
                                      channel, self.foreign_syncs)
                return False
            closed = self.assembler.feed_all(us, channel, msg.arbitration_id, msg.data, flags)
            if closed and self.on_closed is not None:
                for cycle in closed:  # oldest first (a released hold can close two)
                    self.on_closed(cycle)
                return True
        except Exception as exc:  # noqa: BLE001 - the receive path never raises
            if self.assembler.events < self.fed:
                self.assembler.count_internal_error()
            self.rate_log.warning("internal_error", "receive path: %s: %s", type(exc).__name__, exc)
        return False

    def _after_feed(self, closed: bool) -> None:
        """Outside the stream lock: evaluate what closed, then write the queued trace."""
        if closed and self.after_closed is not None:
            try:
                self.after_closed()
            except Exception as exc:  # noqa: BLE001 - the receive path never raises
                self.rate_log.warning("after_closed", "after a closed cycle: %s: %s", type(exc).__name__, exc)
        if closed or len(self._trace_queue) >= TRACE_BATCH:
            self.flush_trace(to_disk=closed)

    def receive(self, msg: can.Message, channel: int) -> None:
        """A frame from the bus (or from a trace, in replay)."""
        self.receive_all((msg,), channel)

    def receive_all(self, msgs: Iterable[can.Message], channel: int) -> list[can.Message]:
        """Frames of one channel in bus order, as :meth:`receive` one by one, under one take of
        the stream lock; the cycles they close are evaluated after the last. Returns those the
        assembler took as the answer an SDO request of the centre awaits (``solicited``), in order.

        With no trace, runs of common frames (well-formed patch TPDOs of packed decisions, or
        one-taxel nodes' TPDO1 / TPDO2, that do not complete the open cycle, nor end its window)
        are fed by :attr:`common` in one loop, every other frame by :meth:`_feed_locked`: the same
        result as feeding each by :meth:`_feed_locked` (:mod:`.common_frames`, :mod:`.node_frames`)."""
        solicited = self.assembler.solicited
        answers = []
        closed = False
        if not isinstance(msgs, (list, tuple)):
            msgs = list(msgs)
        with self.lock:
            common = self.common if self.trace is None else None
            index, count = 0, len(msgs)
            while index < count:
                if common is not None:
                    fed, last_us = common.feed(msgs, index, channel, self.first_us)
                    if fed:
                        self.fed += fed
                        self.last_us = last_us
                        index += fed
                        if index == count:
                            break
                msg = msgs[index]
                index += 1
                closed |= self._feed_locked(msg, channel)
                if solicited[channel]:
                    solicited[channel] = False
                    answers.append(msg)
            self._publish_locked(closed)
        if closed or len(self._trace_queue) >= TRACE_BATCH:
            self._after_feed(closed)
        return answers

    def transmit(self, channel: int, can_id: int, data: bytes, remote: bool = False) -> None:
        """Send a frame of the master on ``channel`` and feed it as an event (same order)."""
        self.transmit_all([(channel, can_id, data)], remote)

    def transmit_all(self, frames: Iterable[tuple[int, int, bytes]], remote: bool = False) -> None:
        """Send several frames back to back (e.g. SYNC on every channel) as one atomic step: all
        sent first, then fed in the same order (under the stream lock throughout, so no received
        frame comes between them): the last channel's SYNC leaves after the sends before it, not
        after their feeding too (eight SYNCs at 4,096 taxels: ~0.4 ms earlier)."""
        closed = False
        with self.lock:
            sent = []
            for channel, can_id, data in frames:
                data = bytearray(data) if data is not None else bytearray()  # as can.Message keeps it
                sent_at = time.time()  # before the send: every answer to this frame is later
                direct = None if remote else self._direct_sender(channel)
                own = direct is not None and self._own_dropped.get(channel, False)  # its echo never comes back
                if self.echoes is not None and not own:  # before the send: its echo can come back at once
                    self.echoes.sent(channel, can_id, data, remote)
                msg = None
                try:
                    if direct is None:
                        msg = TxMessage(arbitration_id=can_id, data=data, is_extended_id=False,
                                        is_remote_frame=remote, channel=channel)
                        self.buses[channel].send(msg)
                    else:  # the datagram first, the stream's Message of it after (the grip command)
                        direct([(can_id, data)])
                except can.CanError as exc:
                    self._send_failed(channel, can_id, data, remote, exc, own)
                    continue
                if own:
                    self.echoes_dropped_in_kernel += 1
                if msg is None:
                    msg = TxMessage(arbitration_id=can_id, data=data, is_extended_id=False, channel=channel)
                msg.timestamp = sent_at
                msg.is_rx = False  # sent by the centre: "Tx" in the trace (.asc, .blf, .trc); after
                # the send, which has copied or serialised the frame (receivers see is_rx True)
                sent.append((msg, channel))
            for msg, channel in sent:
                closed |= self._feed_locked(msg, channel)
            self._publish_locked(closed)
        if closed or len(self._trace_queue) >= TRACE_BATCH:
            self._after_feed(closed)

    def transmit_fed_first(self, channel: int, can_id: int, data: bytes) -> None:
        """One frame - the SYNC of a one-channel network - fed as an event first, then sent: the
        stream lock is held for the feed only, not across the send. Every answer to the frame
        comes after its send, so none is fed before it (what :meth:`transmit_all` holds the lock
        for), and the receive thread no longer waits for the lock while the answers arrive:
        hardware-speed nodes answer within 0.2-0.3 ms, while the SYNC's feed took 0.17-0.20 ms
        p50 under the lock (``bench/grip_latency.py --transports player``, docs/grip-control.md).
        The event's time stamp is taken before the feed, as :meth:`transmit_all` takes it before
        the send. A send that fails leaves the fed SYNC's cycle without answers (it closes
        degraded); counted in ``tx_errors`` and logged as every failed send is."""
        data = bytearray(data) if data is not None else bytearray()
        sent_at = time.time()  # before the send: every answer to this frame is later
        fed = TxMessage(arbitration_id=can_id, data=data, is_extended_id=False, channel=channel)
        fed.timestamp = sent_at
        fed.is_rx = False  # sent by the centre: "Tx" in the trace
        direct = self._direct_sender(channel)
        own = direct is not None and self._own_dropped.get(channel, False)  # its echo never comes back
        with self.lock:
            if own:  # counted before the send (the lock is not taken again for it), undone if it fails
                self.echoes_dropped_in_kernel += 1
            elif self.echoes is not None:  # before the send: its echo can come back at once
                self.echoes.sent(channel, can_id, data, False)
            closed = self._feed_locked(fed, channel)
            self._publish_locked(closed)
        try:
            if direct is None:  # a Message of its own: the fed one is the stream's (time stamp, channel)
                self.buses[channel].send(TxMessage(arbitration_id=can_id, data=bytearray(data),
                                                   is_extended_id=False, channel=channel))
            else:
                direct([(can_id, data)])
        except can.CanError as exc:
            with self.lock:
                if own:
                    self.echoes_dropped_in_kernel -= 1
                self._send_failed(channel, can_id, data, False, exc, own)
        if closed or len(self._trace_queue) >= TRACE_BATCH:
            self._after_feed(closed)

    def _send_failed(self, channel: int, can_id: int, data, remote: bool, exc: can.CanError,
                     own: bool = False) -> None:
        """A frame that could not be sent (stream lock held): no echo will come, counted, logged."""
        if self.echoes is not None and not own:
            self.echoes.forget(channel, can_id, data, remote)
        self.tx_errors += 1
        self.rate_log.warning("tx_error", "transmit 0x%03X on channel %d failed: %s", can_id, channel, exc)

    def _direct_sender(self, channel: int) -> Callable[[list[tuple]], None] | None:
        """How a data frame leaves on a python-can udp_multicast bus: its datagram written
        straight on the socket (:func:`taxel_net.udp_wire.udp_multicast_burst_sender`: the
        bytes ``bus.send`` writes but the ``channel`` field, None - receivers stamp their own -
        in 14 against 21 µs a frame: the eight SYNCs of a skin4096 cycle leave ~60 µs sooner).
        Where the bus's socket drops its own datagrams in the kernel
        (:func:`taxel_net.udp_filter.drop_own_frames`, set when the service opened the bus), the
        datagrams carry the bus's tag in their ``timestamp`` field (which receivers replace with
        their receive time): no echo of them comes back to be read and dropped
        (``echoes_dropped_in_kernel`` counts them). None for any other bus (``bus.send``)."""
        try:
            return self._senders[channel]
        except KeyError:
            bus = self.buses[channel]
            tag = own_tag(bus)
            sender = udp_multicast_burst_sender(bus, stamp=tag if tag is not None else 0.0)
            self._own_dropped[channel] = sender is not None and tag is not None
            self._senders[channel] = sender
            return sender

    def flush_trace(self, to_disk: bool = False) -> None:
        """Write the queued trace messages, in stream order (any thread, outside the stream lock);
        ``to_disk`` (at every cycle close): also hand everything the writer holds to the OS
        (:func:`~.trace_writers.flush_to_os`: a file's buffer, BLF's container), so a SIGKILL
        loses at most the cycle in flight, in every format the centre writes."""
        with self._trace_lock:
            with self.lock:
                batch = self._trace_queue
                if not batch:
                    return
                self._trace_queue = []
                trace = self.trace
            if trace is None:
                if self.trace_error is not None:  # queued before the trace ended
                    self.not_traced += len(batch)
                return
            self._write_trace(trace, batch, to_disk)

    def _write_trace(self, trace, batch, to_disk: bool) -> None:
        """Write ``batch`` (holding ``_trace_lock``); ``to_disk``: then hand it all to the OS.
        :attr:`traced` counts the frames the writer took (which of them reached the file before a
        failure, its buffers decide)."""
        done = 0
        try:
            for msg in batch:
                trace.on_message_received(msg)
                done += 1
            if to_disk:
                flush_to_os(trace)
        except Exception as exc:  # noqa: BLE001 - a full disk: the trace ends here, the run goes on
            self.not_traced += len(batch) - done
            self._trace_ended(trace, exc)
        finally:
            self.traced += done

    def _trace_ended(self, trace, exc: BaseException) -> None:
        """The first failure (a full disk, a file-size limit, an I/O error) ends the trace (holding
        ``_trace_lock``): logged once; its file closed as it stands, not ``stop``ped (an ASC's end
        or a BLF's header written after a cut would make a cut trace pass for a complete one:
        replay reads an unclosed trace up to its last whole frame); every later frame counted in
        :attr:`not_traced` (the stream traces no more: its fast path for common frames back
        on); the service says so at the end
        (``FusionService.trace_failure``)."""
        self.trace_errors += 1
        self.trace_error = one_line(exc)
        logger.error("the trace ends here: %s - no more frames are written to it (the run goes on; counted)",
                     self.trace_error)
        file = getattr(trace, "file", None)
        try:
            if file is not None:
                file.close()
        except Exception:  # noqa: BLE001 - it fails to flush again: the descriptor is closed anyway
            pass
        with self.lock:
            if self.trace is trace:
                self.trace = None
            self._fed_at_end = self.fed

    def close_trace(self) -> None:
        """Write what is queued, then stop the trace writer (``can.Logger``) and detach it (a trace
        ended by a failure is not stopped: :meth:`_trace_ended`)."""
        self.flush_trace()
        with self._trace_lock:
            with self.lock:
                trace, self.trace = self.trace, None
                batch, self._trace_queue = self._trace_queue, []
            if trace is not None:
                self._write_trace(trace, batch, False)
            if trace is not None and self.trace_error is None:
                try:
                    trace.stop()
                except Exception as exc:  # noqa: BLE001 - its last flush failed: the trace is cut
                    self._trace_ended(trace, exc)
            with self.lock:
                if self._fed_at_end is not None:  # frames fed after the trace ended: never queued
                    self.not_traced += self.fed - self._fed_at_end
                    self._fed_at_end = self.fed

    def cycle_open(self) -> bool:
        with self.lock:
            return self.assembler.is_open

    def _snapshot_locked(self) -> tuple:
        """The counters' figures now (stream lock held): a tuple of plain values, cheap to make."""
        assembler = self.assembler
        return tuple(assembler.counts), len(assembler.held), self.foreign_syncs

    def _publish_locked(self, closed: bool) -> None:
        """After a turn that closed a cycle (before the first, after every turn; stream lock held):
        the counters for :meth:`counters_snapshot`."""
        if closed or self._publish_each_turn:
            self._published = self._snapshot_locked()
            if closed:
                self._publish_each_turn = False

    @staticmethod
    def _counters_of(snapshot: tuple) -> dict[str, int]:
        counts, held, foreign_syncs = snapshot
        counters = counters_of(counts, held)
        if foreign_syncs:
            counters["foreign_sync"] = foreign_syncs
        return counters

    def counters(self) -> dict[str, int]:
        """The counters now (takes the stream lock; publishes them for :meth:`counters_snapshot` too)."""
        with self.lock:
            snapshot = self._published = self._snapshot_locked()
        return self._counters_of(snapshot)

    def counters_snapshot(self) -> dict[str, int]:
        """The counters as :meth:`counters` gave them at the last closed cycle (or at the last
        :meth:`counters` call, or before the first closed cycle at the last receive turn) - without
        the stream lock: one reference read (atomic in CPython). The live view's, whose refresh
        runs at the normal priority while the receive thread may run under ``SCHED_FIFO``
        (``--rt-priority``): taking the lock there would be a priority inversion on the SYNC ->
        command path."""
        return self._counters_of(self._published)


class _StreamListener(can.Listener):
    """python-can listener of one channel: hands every frame to the stream, then to canopen
    (``canopen.network.MessageListener``) only the SDO answers its client is waiting for - as
    the stream validated them (8 bytes, 11-bit data frame, a request outstanding): junk never
    reaches the canopen library (no log line per malformed heartbeat/EMCY, no EMCY log or SDO
    response queue that grows). Heartbeats and EMCY are decoded by the stream. Never raises."""

    def __init__(self, service: "FusionService", channel: int, network=None):
        self.service = service
        self.channel = channel
        self.stream = service.stream
        self.echoes = service.stream.echoes
        self.network = network
        if network is not None:
            from canopen.network import MessageListener

            self.canopen = MessageListener(network)
            self.subscribers = network.subscribers  # COB-ID -> callbacks, updated by canopen
        self._failing = False  # the last thing the reader reported was a bus error (on_error)

    def on_message_received(self, msg: can.Message) -> None:
        self.on_messages_received((msg,))

    def on_messages_received(self, msgs: Sequence[can.Message]) -> None:
        self._failing = False  # a frame between two bus errors: no back-off (on_error)
        """The frames of one receive turn (taxel_net.receiver), in order: fed to the stream
        under one take of its lock; then the boot-ups they brought to the service and the SDO
        answers among them to canopen."""
        answers: list[can.Message] = []
        try:
            echoes = self.echoes
            if echoes is not None:  # our own frames looped back (udp_multicast) are dropped
                foreign = echoes.foreign(msgs, self.channel)
                if foreign is not msgs:
                    self.service.own_echoes += len(msgs) - len(foreign)
                    msgs = foreign
            if msgs:  # a turn of own echoes only (the SYNC's, just sent) never waits for the stream lock
                answers = self.stream.receive_all(msgs, self.channel)
            bootups = self.stream.assembler.bootups
            if bootups:
                with self.stream.lock:
                    drained = list(bootups)
                    bootups.clear()
                for index in drained:
                    self.service.on_bootup(index)
        except Exception as exc:  # noqa: BLE001 - never let the Notifier thread die
            self._internal_error(exc)
        for msg in answers:  # awaited SDO answers, each on its own (one failing loses no other)
            try:
                if self.network is not None and msg.arbitration_id in self.subscribers:
                    self.canopen.on_message_received(msg)
            except Exception as exc:  # noqa: BLE001
                self._internal_error(exc)

    def _internal_error(self, exc: Exception) -> None:
        with self.stream.lock:
            self.stream.assembler.count_internal_error()
        self.stream.rate_log.warning("listener", "listener: %s: %s", type(exc).__name__, exc)

    def on_error(self, exc: Exception) -> None:
        """A bus error, logged rate-limited. python-can's Notifier (interfaces without a socket:
        pcan, kvaser, vector, socketcand, ...) calls ``recv`` again at once after it: a bus that
        fails for good (adapter unplugged) was read in a tight loop - a core at 100 %, and under
        ``--rt-priority`` a SCHED_FIFO thread that starves the host's normal tasks. A second error
        with no frame between waits :data:`BUS_ERROR_BACKOFF_S` (the Notifier's own timeout) before
        the next read; a single one (taxel_net.receiver ends that bus's reading) waits for nothing."""
        self.stream.rate_log.warning("bus_error", "bus error on channel %d: %s", self.channel, exc)
        if self._failing:
            time.sleep(BUS_ERROR_BACKOFF_S)
        self._failing = True

    def stop(self) -> None:
        pass


