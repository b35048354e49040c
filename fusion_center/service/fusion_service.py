"""The fusion centre on one python-can interface: :class:`FusionService` (buses, canopen
networks, the master, evaluation of closed cycles, the decision log) and its
:class:`RunSummary`.

No worker thread: the thread whose event closed a cycle - the Notifier thread when the
cycle's last PDO arrives (``closed_by: complete``, the usual case), the SYNC producer when the
next SYNC or the final NMT closes it - evaluates it right away, after releasing the stream
lock (:meth:`FusionService._process_pending`): closed cycles are queued in stream order under
the stream lock and evaluated in that order under a separate evaluation lock (a thread that
finds it taken leaves its cycle to the holder), appended to the decision log (one JSON line,
flushed) and passed to the ``on_record`` callbacks, which must be quick and never wait for bus
traffic (they run on a receive thread). This saves the hand-off to a worker thread (a
wake-up on a loaded machine) on the SYNC -> record path.

The event stream and the listeners are in :mod:`fusion_center.service.stream`, trace files
and replay in :mod:`fusion_center.service.traces`.
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import can

from taxel_net.canmsg import tune_udp_multicast
from taxel_net import gcfreeze
from taxel_net.eds_file import import_eds
from taxel_net.errors import EdsError, UsageError
from taxel_net import realtime
from taxel_net.receiver import notifiers_for
from taxel_net.resources import eds_path, patch_eds_path
from taxel_net.udp_filter import drop_own_frames
from taxel_net.scene import Scene
from .aggregates import LatencyHistogram, RunAggregates
from .cycle_records import MALFORMED, ClosedCycle
from .cycles import CycleAssembler
from .pipeline import CyclePipeline
from .records import RecordWriter
from .echo_filter import EchoFilter
from .stream import EventStream, RateLimitedLog, _StreamListener
from .traces import open_trace_writer

logger = logging.getLogger("fusion_center.service")

LATENCY_SAMPLES = 4096  # recent latency samples kept as such (benchmarks); the histograms keep all

DEFAULT_EDS = eds_path()  # eds/taxel_node.eds, in the checkout or installed (taxel_net.resources)


@dataclass
class RunSummary:
    cycles: int = 0
    records: int = 0
    counters: dict = field(default_factory=dict)
    sdo_writes: int = 0
    sdo_aborts: int = 0
    sdo_timeouts: int = 0
    sync_overruns: int = 0
    missing_at_boot: list = field(default_factory=list)
    own_echoes: int = 0
    tx_errors: int = 0
    latency_ms: list = field(default_factory=list)  # the most recent samples (at most LATENCY_SAMPLES)
    latency_hist: LatencyHistogram | None = None     # every sample of the run (fixed size)

    def latency_percentile(self, q: float) -> float | None:
        if self.latency_hist is not None:
            return self.latency_hist.percentile(q)
        if not self.latency_ms:
            return None
        data = sorted(self.latency_ms)
        k = min(len(data) - 1, max(0, math.ceil(q / 100.0 * len(data)) - 1))
        return data[k]


def trace_failure(path, stream) -> str:
    """The one line of a trace ended by a failure (``EventStream.trace_error``): how far it got -
    at most the frames its writer took (what its buffers held at the failure is lost), nothing
    when the file is an empty regular file - and how many were not traced."""
    import os
    import stat

    try:
        st = os.stat(path)
        empty = stat.S_ISREG(st.st_mode) and st.st_size == 0
    except OSError:
        empty = False
    where = ("nothing of it reached the file" if empty else
             f"the file holds at most the {stream.traced} frames before it (replay reads it up to its last "
             "whole frame)")
    return (f"--log {str(path)!r}: {stream.trace_error}: the trace ends there, {where}; {stream.not_traced} later "
            "frames not traced (the trace is incomplete)")


def check_rt_priority(rt_priority) -> int | None:
    """``--rt-priority``: None (off) or 1-99; a bad value: UsageError naming the option, the
    value and what is allowed."""
    try:
        return None if rt_priority is None else realtime.check_priority(rt_priority)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


class FusionService:
    """The fusion centre on one python-can interface (one bus per scene channel).

    ``with FusionService(scene, ...) as svc: svc.boot(); svc.run(cycles)``. ``open`` (called by
    ``__enter__``) raises :class:`~taxel_net.errors.UsageError` for an unknown interface, a
    channel that cannot be opened, a missing EDS or an unwritable output file.

    Memory does not grow with the number of cycles except by ``keep_records``: ``True`` keeps
    every record in :attr:`records` (tests, short runs), ``False`` none, an int ``k`` the last
    ``k``. Records always go to the decision log and to :attr:`stats` (running aggregates);
    latencies to fixed-size histograms (:attr:`latency`, :attr:`centre_latency`) and the last
    :data:`LATENCY_SAMPLES` samples (:attr:`latency_ms`, :attr:`centre_latency_ms`).
    """

    def __init__(self, scene: Scene, *, interface: str = "virtual", channels: Sequence[str] | None = None,
                 bitrate: int | None = None, bus_kwargs: dict | None = None, json_lines=None, trace=None,
                 eds_path=DEFAULT_EDS, truth: bool = True, keep_records: bool = True,
                 on_record: Callable[[dict], None] | None = None, rt_priority: int | None = None):
        self.scene = scene
        # SCHED_FIFO for the receive thread(s), the SYNC producer and the heartbeat (--rt-priority;
        # taxel_net.realtime): None keeps the normal priority
        self.rt_priority = check_rt_priority(rt_priority)
        self.rt_threads: list[str] = []
        self.interface = interface
        names = list(scene.bus.channels)
        if channels is not None:
            channels = list(channels)
            if len(channels) != len(names):
                raise UsageError(f"--channel: the scene has {len(names)} channel(s) {names}, got {len(channels)}")
            names = channels
        self.channel_names = names
        self.bitrate = bitrate
        self.bus_kwargs = dict(bus_kwargs or {})
        self.json_lines = json_lines
        self.trace_path = trace
        if scene.bus.patch_nodes and Path(eds_path) == DEFAULT_EDS:
            eds_path = patch_eds_path()  # patch nodes: their own object dictionary (eds/taxel_patch.eds)
        self.eds_path = Path(eds_path)
        self.keep_records = keep_records
        self.on_record: list[Callable[[dict], None]] = [on_record] if on_record else []
        # called after on_record with (record, closed cycle): outputs that need more than the
        # record (fusion_center.robotics: the raw readings); same rules as on_record
        self.on_cycle: list[Callable[[dict, ClosedCycle], None]] = []
        self.assembler = CycleAssembler(scene)
        self.labels = self.assembler.labels
        self.pipeline = CyclePipeline(scene, truth=truth)
        if keep_records is True:
            self.records: list[dict] | deque[dict] = []
        else:
            self.records = deque(maxlen=max(0, int(keep_records)))
        self.stats = RunAggregates()
        self.latency = LatencyHistogram()         # SYNC transmission -> record written
        self.centre_latency = LatencyHistogram()  # closing event (last TPDO / SYNC) -> record written
        self.latency_ms: deque[float] = deque(maxlen=LATENCY_SAMPLES)
        self.centre_latency_ms: deque[float] = deque(maxlen=LATENCY_SAMPLES)
        self.pipeline_errors = 0
        self.own_echoes = 0
        self.buses: list[can.BusABC] = []
        self.notifiers: list[can.Notifier] = []
        self.networks = []
        self.master = None
        self.drive = None  # .drive_link.DriveLink on a [gripper] scene
        self._pending: deque[ClosedCycle] = deque()  # closed, not yet evaluated (stream order)
        self._eval_lock = threading.Lock()  # one evaluation at a time, in cycle order
        self.stream = EventStream(self.assembler, on_closed=self._pending.append,
                                  after_closed=self._process_pending)
        if interface == "udp_multicast":  # every datagram comes back to its sender
            self.stream.echoes = EchoFilter()
        self.writer: RecordWriter | None = None
        self.writer_failure: str | None = None  # after close: the decision log's failure (RecordWriter.failure)
        self.trace_failure: str | None = None   # after close: the trace's failure (EventStream.trace_error)
        self._trace_logger = None
        self._opened = False
        self.missing_at_boot: list[int] = []
        self._malformed_seen = {name: 0 for name in MALFORMED}
        self._rate_log = RateLimitedLog(logger, 2.0)

    # ------------------------------------------------------------------ life cycle
    def __enter__(self) -> "FusionService":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> "FusionService":
        import canopen

        self.writer_failure = None
        self.trace_failure = None

        if self.interface not in can.interfaces.VALID_INTERFACES:
            raise UsageError(f"--interface {self.interface!r}: not a python-can interface (known: "
                             + ", ".join(sorted(can.interfaces.VALID_INTERFACES)) + ")")
        if not self.eds_path.is_file():
            raise UsageError(f"EDS file {str(self.eds_path)!r} not found (needed for the SDO configuration)")
        try:
            od = import_eds(self.eds_path)  # any content: one line naming the file (taxel_net.eds_file)
        except EdsError as exc:
            raise UsageError(str(exc)) from None
        from .node_config import node_configuration

        for index in range(0 if self.scene.bus.patch_nodes else self.scene.n):  # every object the SDO configuration writes
            for obj, sub, _ in node_configuration(self.scene, index):
                try:
                    entry = od[obj]
                    if sub or not isinstance(entry, canopen.objectdictionary.ODVariable):
                        entry[sub]
                except (KeyError, TypeError):
                    raise UsageError(f"EDS file {str(self.eds_path)!r}: object 0x{obj:04X}:{sub} is missing "
                                     "(the SDO configuration of the nodes writes it)") from None
        try:
            for name in self.channel_names:
                self.buses.append(self._open_bus(name))
            self.stream.buses = self.buses
            if self.trace_path is not None:
                self._trace_logger = open_trace_writer(self.trace_path)
                self.stream.trace = self._trace_logger
            if self.json_lines is not None:
                self.writer = RecordWriter(self.json_lines)
            pairs = []
            for index, bus in enumerate(self.buses):
                network = canopen.Network(bus)
                network.send_message = self._sender(index)
                self.networks.append(network)
                pairs.append((bus, [_StreamListener(self, index, network)]))
            # one receive thread for all buses (sockets or python-can virtual buses:
            # taxel_net/receiver.py), else a python-can Notifier per bus
            self.notifiers = notifiers_for(pairs, timeout=0.05, name="centre-receive")
            for network, notifier in zip(self.networks, self.notifiers):
                network.notifier = notifier
            from .master import Master

            self.master = Master(self, self.scene, self.networks, od)
            if self.pipeline.grip is not None and self.scene.gripper.channel < len(self.networks):
                from .drive_link import DriveLink

                self.drive = DriveLink(self, self.networks)  # the gripper drive's end (issue 23)
        except BaseException:
            self.close()
            raise
        self._opened = True
        return self

    def _sender(self, channel: int):
        def send_message(can_id: int, data, remote: bool = False) -> None:
            self.stream.transmit(channel, can_id, bytes(data), remote)
        return send_message

    def _open_bus(self, name: str) -> can.BusABC:
        kwargs = dict(self.bus_kwargs)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        try:
            bus = can.Bus(interface=self.interface, channel=name, **kwargs)
        except can.exceptions.CanInterfaceNotImplementedError as exc:
            raise UsageError(f"--interface {self.interface!r}: not usable by python-can ({exc})") from None
        except Exception as exc:  # noqa: BLE001 - any backend failure: cannot open
            raise UsageError(f"--channel {name!r} cannot be opened with interface {self.interface!r}: "
                             f"{type(exc).__name__}: {exc}") from None
        tune_udp_multicast(bus)  # udp_multicast: its own group only, room for bursts (taxel_net.canmsg)
        if self.interface == "udp_multicast":  # its own datagrams dropped in the kernel on their way back
            drop_own_frames(bus)                # (taxel_net.udp_filter; the stream tags what it sends)
        return bus

    def close(self) -> None:
        if self.master is not None:
            self.master.stop()
            self.master.stop_heartbeat()  # the master's heartbeat ends with the centre
        for notifier in self.notifiers:
            try:
                notifier.stop(timeout=2)
            except Exception:  # noqa: BLE001
                logger.exception("notifier stop failed")
        self.notifiers = []
        self.drain(timeout=10.0)
        self.stream.counters()  # published as they end (the stream's counters_snapshot: a live view after the run)
        for bus in self.buses:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001
                logger.exception("bus shutdown failed")
        self.buses = []
        if self._trace_logger is not None:
            try:
                self.stream.close_trace()
            except Exception:  # noqa: BLE001
                logger.exception("trace close failed")
            self._trace_logger = None
            stream = self.stream
            if stream.trace_error is not None:
                self.trace_failure = trace_failure(self.trace_path, stream)
        if self.writer is not None:
            self.writer.close()
            self.writer_failure = self.writer.failure
            self.writer = None
        self._opened = False

    # ------------------------------------------------------------------ master steps
    def never_heard(self) -> list[int]:
        with self.stream.lock:
            return [int(i) for i in (self.assembler.last_heard < 0).nonzero()[0]]

    def boot(self, timeout_s: float = 3.0, configure: bool = True) -> list[int]:
        """Wait for the boot-ups, configure the nodes heard over SDO, NMT-start them.

        Returns the node (device) indexes that never booted (missing from the first cycle;
        one-taxel scenes: taxel indexes)."""
        missing = self.master.wait_for_boot(timeout_s)
        self.missing_at_boot = missing
        present = [i for i in range(self.assembler.n_devices) if i not in set(missing)]
        if configure:
            with self.stream.lock:
                mark = self.assembler.events
            self.master.configure(present)
            with self.stream.lock:  # booted (again) while being configured: its reset undid it
                again = [i for i in present if self.assembler.bootup_seq[i] >= mark]
            if again:
                self.master.configure(again)
            if self.drive is not None:
                self.drive.boot(timeout_s)
        self.master.start_nodes()
        return missing

    def on_bootup(self, index: int) -> None:
        if self.master is not None:
            self.master.on_bootup(index)

    def run(self, cycles: int, *, before_sync: Callable[[int], None] | None = None,
            timeout_s: float | None = None) -> RunSummary:
        """Produce ``cycles`` SYNCs, wait for their records, return the summary."""
        if cycles < 1:
            raise UsageError(f"--cycles {cycles}: must be >= 1")
        period = self.scene.bus.sync_period_ms / 1000.0
        # what the set-up allocated (EDS, canopen objects, scene arrays, caches) is not
        # traversed by the cyclic collector during the run: a full collection of it took
        # 40-130 ms at 4,096 taxels (bench/skin_scale.py), a SYNC -> record outlier each time
        gcfreeze.hold()
        # nor does the collector run on the way from a cycle's answers to its command: the SYNC
        # producer collects what is due half a period after each SYNC (taxel_net.gcfreeze.defer)
        gcfreeze.defer()
        try:
            self._start_sync(cycles, before_sync)
            if timeout_s is None:
                timeout_s = cycles * period * 3 + 10.0
            self.master.wait_sync_done(timeout_s)
            self.master.stop()
            self.drain(timeout=5.0)
        finally:
            gcfreeze.resume()
            gcfreeze.release()
        return self.summary()

    def _start_sync(self, cycles: int, before_sync) -> None:
        """The SYNC producer started; the threads of :meth:`_critical_threads` raised when
        ``rt_priority`` asks for it (every ``run``: the assembled centre's too) - by the SYNC
        producer itself before its first SYNC (raised from here, after the start, the first
        cycle or two ran at the normal priority, as far as this thread was late)."""
        on_start = None
        if self.rt_priority is not None:
            def on_start():
                self.rt_threads = realtime.fifo_threads(self._critical_threads(), self.rt_priority)
        self.master.start_sync(cycles, before_sync, on_start)

    def _critical_threads(self) -> list[threading.Thread]:
        """The threads on the SYNC -> command path: the receive thread(s), the SYNC producer, and
        the master's heartbeat - it takes the stream lock the receive thread needs, and Python's
        locks do not pass a waiter's priority on to their holder: a normal-priority holder
        preempted by the host's other jobs would keep the real-time receive thread waiting."""
        threads = []
        for notifier in self.notifiers:
            owner = getattr(notifier, "owner", None)  # a handle of taxel_net.receiver's one thread
            own = getattr(owner, "_thread", None)
            if own is not None:
                if own not in threads:
                    threads.append(own)
            else:  # python-can's Notifier: a thread per bus
                threads.extend(t for t in getattr(notifier, "_readers", []) if isinstance(t, threading.Thread))
        for name in ("_sync_thread", "_heartbeat_thread"):
            thread = getattr(self.master, name, None)
            if thread is not None:
                threads.append(thread)
        return threads

    def drain(self, timeout: float = 5.0) -> None:
        """Wait for the evaluation in progress, then evaluate every closed cycle still queued."""
        if not self._eval_lock.acquire(timeout=timeout):
            logger.warning("drain: an evaluation is still running after %.1f s", timeout)
            return
        try:
            while self._pending:
                self._handle(self._pending.popleft())
        finally:
            self._eval_lock.release()

    def summary(self) -> RunSummary:
        m = self.master
        return RunSummary(
            cycles=m.sync_sent if m else 0,
            records=self.stats.records,
            counters=self.stream.counters(),
            sdo_writes=m.sdo_writes if m else 0,
            sdo_aborts=m.sdo_aborts if m else 0,
            sdo_timeouts=m.sdo_timeouts if m else 0,
            sync_overruns=m.sync_overruns if m else 0,
            missing_at_boot=[self.labels[i] for i in self.missing_at_boot],
            own_echoes=self.own_echoes + self.stream.echoes_dropped_in_kernel,
            tx_errors=self.stream.tx_errors,
            latency_ms=list(self.latency_ms),
            latency_hist=self.latency,
        )

    # ------------------------------------------------------------------ evaluation
    def _process_pending(self) -> None:
        """Evaluate the queued closed cycles in stream order, in the calling thread (after the
        stream lock is released). If another thread is evaluating, it takes them: it checks the
        queue again after releasing the evaluation lock, so no cycle is left behind."""
        pending = self._pending
        while pending:
            if not self._eval_lock.acquire(blocking=False):
                return
            try:
                while pending:
                    self._handle(pending.popleft())
            finally:
                self._eval_lock.release()

    def _handle(self, item: ClosedCycle) -> None:
        """Evaluate one closed cycle (eval lock held): what the grip command needs first
        (:meth:`evaluate_command`), the command out on the bus at once, then the rest of the
        record (:meth:`finish_record`), the decision log (flushed), ``on_record``."""
        pending = record = None
        try:
            pending = self.evaluate_command(item)
        except Exception as exc:  # noqa: BLE001
            record = self._failed(item, exc)
        sent = self.master.sync_sent_at.pop(item.cycle, None) if self.master else None
        if self.drive is not None:  # the grip command before the rest of the record, from this thread
            try:
                self.drive.send_command(sent)
            except Exception:  # noqa: BLE001 - never stop the records
                logger.exception("cycle %d: sending the grip command failed", item.cycle)
        if pending is not None:
            try:
                record = self.finish_record(pending)
            except Exception as exc:  # noqa: BLE001
                record = self._failed(item, exc)
        if self.drive is not None:
            try:
                self.drive.after_record(item.cycle, record)
            except Exception:  # noqa: BLE001 - never stop the records
                logger.exception("cycle %d: the grip stage's bookkeeping failed", item.cycle)
        if sent is not None:
            ms = (time.perf_counter() - sent) * 1e3
            self.latency.add(ms)
            self.latency_ms.append(ms)
            t0 = self.assembler.t0_us
            if t0 is not None:
                ms = (time.time() - (t0 + item.close_us) * 1e-6) * 1e3
                self.centre_latency.add(ms)
                self.centre_latency_ms.append(ms)
        writer = self.writer
        if writer is not None and not writer.write(record) and writer.new_failure is not None:
            kind, error = writer.new_failure
            if kind == "io":
                logger.error("cycle %d: the decision log %r ends here: %s - no more records are written to it "
                             "(the run goes on; counted)", item.cycle, str(writer.path), error)
            else:
                logger.error("cycle %d: the decision log %r: the record cannot be encoded (%s) - left out "
                             "(further ones only counted)", item.cycle, str(writer.path), error)
        try:
            self.stats.add(record)
        except Exception:  # noqa: BLE001 - the aggregates never stop the records
            logger.exception("cycle %d: aggregating the record failed", item.cycle)
        if record.get("over_range_nodes"):
            self._rate_log.warning("over_range", "cycle %d: readings of node(s) %s over range, clipped at the "
                                   "INTEGER8/16 limit (EMCY 0x3000): the record's raw-mode results are flagged "
                                   "(over_range_nodes)", item.cycle, record["over_range_nodes"])
        if record.get("duplicate_nodes"):
            self._rate_log.warning("duplicate", "cycle %d: duplicate node-ID evidence for node(s) %s "
                                   "(two devices answer for one node-ID)", item.cycle, record["duplicate_nodes"])
        if self.keep_records is not False:
            self.records.append(record)
        for callback in self.on_record:
            try:
                callback(record)
            except Exception:  # noqa: BLE001
                logger.exception("on_record callback failed")
        for callback in self.on_cycle:
            try:
                callback(record, item)
            except Exception:  # noqa: BLE001
                logger.exception("on_cycle callback failed")
        if item.bad_frames:
            self._log_malformed()

    def _failed(self, item: ClosedCycle, exc: Exception) -> dict:
        self.pipeline_errors += 1
        logger.error("cycle %d: evaluation failed", item.cycle, exc_info=exc)
        return {"cycle": item.cycle, "t": round(item.sync_us * 1e-6, 6), "error": str(exc)}

    def evaluate_command(self, closed: ClosedCycle):
        """The part of the cycle's evaluation the grip command needs (``CyclePipeline.evaluate_command``)."""
        return self.pipeline.evaluate_command(closed)

    def finish_record(self, pending) -> dict:
        """The cycle's record once its command has left (``CyclePipeline.finish``)."""
        return self.pipeline.finish(pending)

    def evaluate(self, closed: ClosedCycle) -> dict:
        return self.finish_record(self.evaluate_command(closed))

    def _log_malformed(self) -> None:
        counters = self.stream.counters()
        for name in MALFORMED:
            new = counters[name] - self._malformed_seen[name]
            if new > 0:
                self._malformed_seen[name] = counters[name]
                self._rate_log.warning(name, "%d malformed frame(s): %s (total %d)", new, name, counters[name])


def stdout_is_tty() -> bool:
    try:
        return sys.stdout.isatty()
    except (AttributeError, ValueError):
        return False
