"""CANopen master duties of the fusion centre (CiA 301): boot-up wait, SDO configuration from
the scene, NMT start, the SYNC producer, and the heartbeat consumer's bookkeeping.

Every frame the master sends goes through :meth:`EventStream.transmit` (SYNC, NMT and the
SDO requests canopen's client makes), so it lands in the trace and in the cycle assembler in
the order it was put on the bus. Liveness (0x1016 semantics) itself is evaluated by the
assembler at each SYNC from the event stream (see :mod:`fusion_center.service.cycles`).

The SDO configuration it writes to every node (the object dictionary entries, one-taxel and patch
nodes): :mod:`fusion_center.service.node_config`.

SDO aborts and time-outs are logged and counted (``sdo_aborts``, ``sdo_timeouts``), never
raised: a node whose configuration failed still takes part with its stored values.

The master's own heartbeat (CiA 301 0x1017 of the master, CiA 302): ``0x700 + [master] node_id``
with state 0x05 (operational) every ``Scene.master_heartbeat_ms`` on every channel, through the
stream, from :meth:`Master.start_heartbeat` (the start of the boot) until
:meth:`Master.stop_heartbeat` (the service closes), on a monotonic-clock thread of its own.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import canopen

from taxel_net import gcfreeze, patches, realtime
from taxel_net.scene import Scene
import numpy as np

from .cycle_records import C_BOOTUP
from .node_config import node_configuration, patch_configuration
from .stream import RateLimitedLog
from .decoder import (
    STATE_OPERATIONAL,
    STATE_PRE_OPERATIONAL,
    STATE_STOPPED,
    BASE_HEARTBEAT,
    COB_NMT,
    COB_SYNC,
    NMT_PRE_OPERATIONAL,
    NMT_RESET_COMMUNICATION,
    NMT_START,
    sync_payload,
)

logger = logging.getLogger("fusion_center.master")

BOOT_QUIET_S = 0.05  # after the reset at start: no new boot-up for this long before configuring
BOOT_LOG_NODES = 20  # missing nodes named in the one boot warning line (the rest counted)


def _join(thread: threading.Thread, timeout: float | None) -> None:
    """``thread.join(timeout)``, also for a thread whose ``start()`` a Ctrl-C cut short (the
    KeyboardInterrupt raised in the main thread after the OS thread began, before ``start``
    saw it running): Python refuses to join that one ("cannot join thread before it is
    started"), which turned the centre's orderly close into a traceback. Its stop event is set
    by the caller; it ends by itself."""
    try:
        thread.join(timeout)
    except RuntimeError:
        if thread is threading.current_thread():
            raise

def quiet_beat(planned: float, sync_schedule: tuple[float, float] | None, limit: float) -> float:
    """When to send the master's heartbeat planned at ``planned`` (monotonic s) while SYNCs run on
    the grid ``sync_schedule`` = (a SYNC's planned time, the SYNC period), never later than planned:
    a beat planned in the first half of a SYNC period - where the nodes' answers arrive and the
    grip command is made - goes a quarter period before the next SYNC instead, provided that is
    at most ``limit`` earlier (the heartbeat loop gives a quarter of its own period); else, and
    without SYNCs, as planned. The heartbeat and the SYNC run on one clock (50 ms and 10 ms in the
    grasp scenes), so a phase the start put right after a SYNC stayed there for the whole run and
    every fifth cycle's answers met the beat's send and feed (stream lock, interpreter lock) on
    their way to the command (docs/grip-control.md). The loop plans the next beat one period
    after this one: moving beats earlier shortens an interval, never lengthens one, so the
    consumers' heartbeat time (CiA 301 0x1016, longer than the producer's) is never at risk
    (a first version delayed beats into the second half instead: intervals of 45-55 ms on a
    50 ms heartbeat, and a drive watching with 55 ms tripped its 0x6007 reaction)."""
    if sync_schedule is None:
        return planned
    anchor, sync_period = sync_schedule
    if sync_period <= 0:
        return planned
    phase = (planned - anchor) % sync_period
    if phase >= sync_period / 2:
        return planned
    shift = phase + sync_period / 4
    return planned - shift if shift <= limit else planned


class Master:
    """NMT master + SYNC producer over a :class:`~fusion_center.service.stream.EventStream`."""

    def __init__(self, service, scene: Scene, networks: list[canopen.Network], od):
        self.service = service
        self.stream = service.stream
        self.scene = scene
        self.networks = networks
        self.patch = bool(scene.bus.patch_nodes)
        self.detector_writes = True  # patch nodes: also write 0x2010/0x2011 per taxel (docs/service.md)
        self.devices = patches.devices(scene)  # the CANopen nodes (one-taxel scenes: one per taxel)
        n_devices = len(self.devices)
        self.nodes: list[canopen.RemoteNode] = []
        for dev in self.devices:
            node = canopen.RemoteNode(dev.node_id, od)
            node.sdo.RESPONSE_TIMEOUT = 0.5
            networks[dev.channel].add_node(node)
            self.nodes.append(node)
        self.sdo_writes = 0
        self.sdo_aborts = 0
        self.sdo_timeouts = 0
        self.configured: set[int] = set()
        self.lss_report = None  # [master] assign_ids = "lss": what the LSS phase did (service.lss.LssReport)
        self.sync_sent = 0
        self.sync_overruns = 0
        self.sync_sent_at: dict[int, float] = {}  # cycle -> perf_counter at SYNC transmission
        self._stats_lock = threading.Lock()
        self._stop = threading.Event()
        self._sync_thread: threading.Thread | None = None
        self._heartbeat_stop = threading.Event()
        self._heartbeat_thread: threading.Thread | None = None
        self.heartbeats_sent = 0  # heartbeat instants (one frame per channel each)
        # while the SYNC producer runs: (its last SYNC's planned monotonic time, its period) - the
        # heartbeat keeps to the periods' quiet halves (quiet_beat)
        self._sync_schedule: tuple[float, float] | None = None
        self._reconfigure: set[int] = set()
        self.restart = scene.master.restart == "always"
        self._log = RateLimitedLog(logger, 2.0)
        self.restarts = 0                # NMT start commands sent to nodes found not operational
        self._off_since = np.full(n_devices, -1, dtype=np.int64)  # SYNC index a node was first seen off
        self._last_start = np.full(n_devices, -10**9, dtype=np.int64)  # SYNC index of its last restart
        hb = max(scene.bus.heartbeat_producer_ms, scene.bus.sync_period_ms)
        self._restart_every = max(2, int(hb / scene.bus.sync_period_ms))  # SYNCs between two restarts of a node
        # SYNCs a node must look off before it is restarted: a bit more than one heartbeat period
        # (a heartbeat sent just before the node took an NMT start still says pre-operational
        # until the next one), so it is deciding again within two heartbeat periods
        self._off_syncs = max(2, math.ceil(1.2 * scene.bus.heartbeat_producer_ms / scene.bus.sync_period_ms))

    # ------------------------------------------------------------------ NMT
    def nmt(self, command: int, node_id: int = 0, channel: int | None = None) -> None:
        channels = range(len(self.networks)) if channel is None else (channel,)
        for ch in channels:
            self.stream.transmit(ch, COB_NMT, bytes((command, node_id)))

    def wait_for_boot(self, timeout_s: float, listen_s: float = 0.3) -> list[int]:
        """Reset the communication of every node (CiA 302 boot-up of the NMT master: NMT reset
        communication to all), wait for every scene node's boot-up; return the missing.

        The reset puts nodes left running by an earlier master (a previous ``run``) back into
        their boot-up state, so every run starts from the same node state. On a scene with a
        gripper drive the taxel nodes are reset one by one (NMT reset communication to each): the
        drive is never reset, it may hold a part (:mod:`.drive_link`). Nodes not booted
        within ``listen_s`` get a second, per-node reset-communication; whoever has been heard
        neither by a boot-up nor otherwise since the reset at ``timeout_s`` is missing (and is
        configured and started later if it ever boots).
        """
        self.start_heartbeat()  # CiA 302: the master's heartbeat from its boot on
        if self.scene.master.assign_ids == "lss":
            self.assign_node_ids()
        assembler = self.stream.assembler
        with self.stream.lock:
            assembler.last_heard[:] = -1  # heard since the reset only
        if self.scene.gripper is None:
            self.nmt(NMT_RESET_COMMUNICATION, 0)  # the assembler notes its place in the stream
        else:  # never the gripper drive: it may hold a part (a centre started again takes it over)
            for t in self.devices:
                self.stream.transmit(t.channel, COB_NMT, bytes((NMT_RESET_COMMUNICATION, t.node_id)))
        start = time.monotonic()
        deadline = start + timeout_s
        reset_sent = False
        bootups, quiet_since = -1, start
        while True:
            with self.stream.lock:
                silent = [int(i) for i in np.flatnonzero(assembler.bootup_seq < assembler.reset_seq)]
                seen = assembler.counts[C_BOOTUP]
            now = time.monotonic()
            if seen != bootups:
                bootups, quiet_since = seen, now
            # every node booted after the reset, and no boot-up for BOOT_QUIET_S: a boot-up sent
            # just before the reset (fed after it) is followed by the one answering it
            if not silent and now - quiet_since >= min(BOOT_QUIET_S, timeout_s / 4):
                return []
            if not reset_sent and now - start >= min(listen_s, timeout_s / 2):
                for i in silent:
                    t = self.devices[i]
                    self.stream.transmit(t.channel, COB_NMT, bytes((NMT_RESET_COMMUNICATION, t.node_id)))
                reset_sent = True
            if now >= deadline:
                heard = set(range(len(self.devices))) - set(self.service.never_heard())
                silent = [i for i in silent if i not in heard]  # heard, no boot-up: present
                if silent:  # one line, however many (a skin of 4,096 one-taxel nodes: hundreds)
                    labels = [str(self.service.labels[i]) for i in silent]
                    shown = ", ".join(labels[:BOOT_LOG_NODES]) + (
                        f", ... ({len(labels) - BOOT_LOG_NODES} more)" if len(labels) > BOOT_LOG_NODES else "")
                    logger.warning("%d node(s) never booted within %.1f s: missing: %s", len(labels), timeout_s, shown)
                return silent
            time.sleep(0.005)

    def assign_node_ids(self):
        """``[master] assign_ids = "lss"``: the non-configured nodes found by LSS Fastscan, each
        given the node-ID the scene lists for its serial number (CiA 305, :mod:`.lss`); they
        boot under it. Returns the :class:`~fusion_center.service.lss.LssReport`."""
        from .lss import assign_node_ids

        od = self.nodes[0].object_dictionary
        identity = tuple(int(od[0x1018][sub].default) for sub in (1, 2, 3))
        report = self.lss_report = assign_node_ids(self.service, self.scene, identity)
        logger.info("LSS: %d node-IDs assigned in %.2f s (%d frames)%s", len(report.assigned), report.seconds,
                    report.frames, f"; {len(report.unknown)} node(s) not in the scene" if report.unknown else "")
        return report

    # ------------------------------------------------------------------ SDO
    def configuration(self, index: int) -> list[tuple[int, int, object, str | None]]:
        """(index, sub, value, struct format or None: typed by the EDS) of node ``index``."""
        if self.patch:
            return patch_configuration(self.scene, self.devices[index], detector=self.detector_writes)
        return [(idx, sub, value, None) for idx, sub, value in node_configuration(self.scene, index)]

    def configure_node(self, index: int) -> bool:
        """Configure node (device) ``index`` over SDO (one-taxel scenes: device = taxel)."""
        node = self.nodes[index]
        label = self.service.labels[index]
        ok = True
        for idx, sub, value, fmt in self.configuration(index):
            try:
                if fmt is not None:  # typed here: expedited download of the encoded value
                    node.sdo.download(idx, sub, struct.pack("<" + fmt, value))
                else:
                    var = node.sdo[idx][sub] if sub or not _is_variable(node, idx) else node.sdo[idx]
                    var.raw = value
                with self._stats_lock:
                    self.sdo_writes += 1
            except canopen.SdoAbortedError as exc:
                with self._stats_lock:
                    self.sdo_aborts += 1
                self._log.warning("sdo_abort", "node %s: SDO download 0x%04X:%d = %r aborted: %s", label, idx, sub,
                                  value, exc)
                ok = False
            except canopen.SdoCommunicationError as exc:
                with self._stats_lock:
                    self.sdo_timeouts += 1
                self._log.warning("sdo_timeout", "node %s: SDO download 0x%04X:%d: %s", label, idx, sub, exc)
                return False  # the node does not answer: no point in going on
            except (KeyError, canopen.ObjectDictionaryError) as exc:
                self._log.warning("sdo_not_in_eds", "node %s: 0x%04X:%d not in the EDS: %s", label, idx, sub, exc)
                ok = False
            except Exception as exc:  # noqa: BLE001 - a bus error must not stop the others
                with self._stats_lock:
                    self.sdo_timeouts += 1
                self._log.warning("sdo_failed", "node %s: SDO download 0x%04X:%d failed: %s", label, idx, sub, exc)
                return False
        self.configured.add(index)
        return ok

    def configure(self, indexes, workers: int = 8) -> None:
        indexes = list(indexes)
        if not indexes:
            return
        with ThreadPoolExecutor(max_workers=min(workers, len(indexes)), thread_name_prefix="sdo") as pool:
            list(pool.map(self.configure_node, indexes))

    def start_nodes(self) -> None:
        self.nmt(NMT_START, 0)

    # ------------------------------------------------------------------ recovery
    def on_bootup(self, index: int) -> None:
        """A node booted while running: configure it and start it (off the receive thread)."""
        if self._stop.is_set() or self._sync_thread is None:
            return
        with self._stats_lock:
            if index in self._reconfigure:
                return
            self._reconfigure.add(index)

        def work():
            # --rt-priority: at the receive thread's priority - each SDO request of the
            # reconfiguration is sent under the stream lock, and Python's locks pass no priority on
            # to a holder preempted by the host's other jobs (the heartbeat's reason, too)
            priority = getattr(self.service, "rt_priority", None)
            if priority is not None:
                realtime.fifo_threads([threading.current_thread()], priority)
            try:
                self.configure_node(index)
                t = self.devices[index]
                self.stream.transmit(t.channel, COB_NMT, bytes((NMT_START, t.node_id)))
                logger.info("node %s booted again: reconfigured and started", self.service.labels[index])
            except Exception:  # noqa: BLE001
                logger.exception("node %s: recovery failed", self.service.labels[index])
            finally:
                with self._stats_lock:
                    self._reconfigure.discard(index)

        threading.Thread(target=work, name=f"recover-{index}", daemon=True).start()

    # ------------------------------------------------------------------ heartbeat
    def start_heartbeat(self) -> None:
        """Start the master's heartbeat producer (idempotent; nothing when it is off)."""
        period_ms = self.scene.master_heartbeat_ms
        if period_ms <= 0 or (self._heartbeat_thread is not None and self._heartbeat_thread.is_alive()):
            return
        self._heartbeat_stop.clear()
        self._heartbeat_thread = threading.Thread(target=self._heartbeat_loop, args=(period_ms / 1000.0,),
                                                  name="master-heartbeat", daemon=True)
        self._heartbeat_thread.start()

    def stop_heartbeat(self) -> None:
        self._heartbeat_stop.set()
        if self._heartbeat_thread is not None:
            _join(self._heartbeat_thread, 5)
            self._heartbeat_thread = None

    def _heartbeat_loop(self, period: float) -> None:
        """0x700 + node-ID [0x05] on every channel every ``period`` s: the next beat one period
        after the planned time (no drift); one that fell behind by more than a period is re-phased
        (no burst of catch-up beats). While the SYNC producer runs, a beat planned in the first half
        of a SYNC period is sent earlier, in the second half of the period before, and the plan
        moves with it (:func:`quiet_beat`): a beat never comes later than one period after the
        last, as the consumers' heartbeat time (CiA 301 0x1016) expects."""
        cob = BASE_HEARTBEAT + self.scene.master.node_id
        frames = [(ch, cob, bytes((STATE_OPERATIONAL,))) for ch in range(len(self.networks))]
        next_at = time.monotonic()
        try:
            while True:
                next_at = quiet_beat(next_at, self._sync_schedule, period / 4)
                delay = next_at - time.monotonic()
                if delay > 0:
                    if self._heartbeat_stop.wait(delay):
                        return
                elif self._heartbeat_stop.is_set():
                    return
                elif delay < -period:
                    next_at = time.monotonic()
                self.stream.transmit_all(frames)
                self.heartbeats_sent += 1
                next_at += period
        except Exception:  # noqa: BLE001 - e.g. the bus went away: stop beating, never hang
            logger.exception("master heartbeat stopped")

    # ------------------------------------------------------------------ SYNC
    def start_sync(self, cycles: int, before_sync: Callable[[int], None] | None = None,
                   on_start: Callable[[], None] | None = None) -> None:
        """The SYNC producer's thread started; ``on_start`` runs in it before its first SYNC
        (FusionService: ``--rt-priority``'s raise, so that the first cycle is raised too)."""
        self._stop.clear()
        self._sync_thread = threading.Thread(target=self._sync_loop, args=(cycles, before_sync, on_start),
                                             name="sync-producer", daemon=True)
        self._sync_thread.start()

    def wait_sync_done(self, timeout: float | None = None) -> bool:
        if self._sync_thread is None:
            return True
        _join(self._sync_thread, timeout)
        return not self._sync_thread.is_alive()

    def stop(self) -> None:
        self._stop.set()
        if self._sync_thread is not None:
            _join(self._sync_thread, 5)

    def _sync_loop(self, cycles: int, before_sync, on_start=None) -> None:
        if on_start is not None:
            try:
                on_start()
            except Exception:  # noqa: BLE001 - the run goes on as it would without it
                logger.exception("SYNC producer: start hook failed")
        period = self.scene.bus.sync_period_ms / 1000.0
        overflow = self.scene.bus.sync_counter
        counter = 0
        channels = list(range(len(self.networks)))
        next_at = time.monotonic()
        window = self.scene.bus.sync_window / 1e6
        last_sent = None
        supervise = None  # the SYNC whose supervision is due, half a period after it
        try:
            for k in range(cycles):
                if self._stop.is_set():
                    break
                if supervise is not None:
                    # mid-period, not right after the SYNC: _supervise takes the stream lock, which
                    # the receive thread needs when hardware-speed answers arrive (0.2-0.3 ms)
                    gap = next_at - period / 2 - time.monotonic()
                    if gap > 0 and self._stop.wait(gap):
                        break
                    self._supervise(supervise)
                    supervise = None
                    # the cyclic collector's due work, here rather than in whichever thread
                    # allocates next - often the receive thread between a cycle's answers and
                    # its command (taxel_net.gcfreeze.defer, FusionService.run)
                    gcfreeze.collect_due()
                delay = next_at - time.monotonic()
                if delay > 0:
                    if self._stop.wait(delay):
                        break
                elif delay < -period:
                    self.sync_overruns += 1
                    next_at = time.monotonic()  # fell behind by more than a period: re-phase
                if last_sent is not None and window:
                    # never two SYNCs closer than the synchronous window (a late SYNC catching
                    # up would otherwise let a node's answer to the previous one fall in this one)
                    gap = last_sent + window - time.monotonic()
                    if gap > 0 and self._stop.wait(gap):
                        break
                if before_sync is not None:
                    try:
                        before_sync(k)
                    except Exception:  # noqa: BLE001
                        logger.exception("before_sync hook failed at cycle %d", k)
                if overflow:
                    counter = counter % overflow + 1
                payload = sync_payload(counter if overflow else None)
                sent_at = self.sync_sent_at
                sent_at[k] = time.perf_counter()
                if len(sent_at) > 256:  # cycles never evaluated (e.g. lost): keep the map bounded
                    sent_at.pop(next(iter(sent_at)), None)
                last_sent = time.monotonic()
                if len(channels) == 1:  # fed, then sent: the lock free while the answers arrive
                    self.stream.transmit_fed_first(0, COB_SYNC, payload)
                else:  # every channel's SYNC sent, then fed: the last one leaves sooner
                    self.stream.transmit_all([(ch, COB_SYNC, payload) for ch in channels])
                self.sync_sent += 1
                supervise = k
                next_at += period
                self._sync_schedule = (next_at - period, period)  # the SYNCs' planned grid (quiet_beat)
            self._sync_schedule = None
            # let the last cycle complete (early close) for up to one period, then end it
            deadline = time.monotonic() + period
            while time.monotonic() < deadline and self.stream.cycle_open():
                time.sleep(0.0005)
            self.stream.transmit_all([(ch, COB_NMT, bytes((NMT_PRE_OPERATIONAL, 0))) for ch in channels])
        except Exception:  # noqa: BLE001 - e.g. the bus went away: end the run, never hang
            logger.exception("SYNC producer stopped")
        finally:
            self._sync_schedule = None


    # ------------------------------------------------------------------ supervision
    def _supervise(self, k: int) -> None:
        """Half a period after SYNC ``k`` (off the answers' way: it takes the stream lock): a live node found not operational (stopped or pre-operational: by a
        heartbeat, or by an NMT command of another master seen in the stream) at every SYNC for
        1.2 heartbeat periods is started again (``[master] restart = "always"``), at most once per heartbeat
        period; a node being reconfigured after its boot-up is left to that. ``"never"``: the
        record names it (``nodes_by_state``) and nothing is sent. The taxel nodes only: the
        gripper drive, under the same setting, is started again by
        :meth:`.drive_link.DriveLink.start_again` from its records (2026-11-30 (stop 32))."""
        if not self.restart:
            return
        assembler = self.stream.assembler
        with self.stream.lock:
            state = assembler.state
            off = ~assembler.missing & ((state == STATE_STOPPED) | (state == STATE_PRE_OPERATIONAL))
        since = self._off_since
        since[~off] = -1
        if not off.any():
            return
        since[off & (since < 0)] = k
        due = off & (k - since >= self._off_syncs) & (k - self._last_start >= self._restart_every)
        if not due.any():
            return
        with self._stats_lock:
            busy = set(self._reconfigure)
        for i in np.flatnonzero(due):
            i = int(i)
            if i in busy:
                continue
            t = self.devices[i]
            self._last_start[i] = k
            self.restarts += 1
            self.stream.transmit(t.channel, COB_NMT, bytes((NMT_START, t.node_id)))
            self._log.warning("restart", "node %s is %s: NMT start sent (restart %d)", self.service.labels[i],
                              "stopped" if state[i] == STATE_STOPPED else "pre-operational", self.restarts)


def _is_variable(node, index: int) -> bool:
    try:
        return isinstance(node.object_dictionary[index], canopen.objectdictionary.ODVariable)
    except KeyError:
        return False
