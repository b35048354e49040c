"""Cycle assemblers in other processes or hosts, one fuser (issue 14, "Beyond one host").

The per-channel work of the centre - decoding every PDO, liveness, NMT states, closing SYNC
cycles (:class:`~fusion_center.service.cycles.CycleAssembler`) - can run in separate
processes or hosts, each for a group of scene channels (``fusion-center assemble --serve
0-3``); one fuser (``fusion-center run --assemblers HOST:PORT``) merges their cycles and
evaluates them with the usual pipeline, writing the same records as
:class:`~fusion_center.service.fusion_service.FusionService`.

* **The buses** are existing transports only: every participant opens the same channels
  (python-can's ``udp_multicast`` on a LAN - any number of bus objects share a group;
  ``socketcand`` serves several clients in front of real interfaces; on one host several
  SocketCAN sockets see one bus). The fuser is the one CANopen master: it sends SYNC (with
  its counter), NMT, the SDO configuration and its heartbeat on every channel exactly as
  ``FusionService`` does. An assembler only listens: it hears the master's SYNCs like any
  node and runs a ``CycleAssembler`` over its channels (a sub-scene: the scene's taxels of
  those channels, the first of them as the channel whose SYNC opens a cycle).
* **Cycle numbers**: an assembler numbers its cycles by SYNC, as ``node_sim.rig`` does (the
  master's broadcast reset communication restarts the count; a jump of the SYNC counter is
  read as lost SYNCs). The fuser maps a part to the SYNC it sent by the part's SYNC counter
  (the latest SYNC it sent with that counter: unambiguous while a part arrives within
  ``sync_counter`` periods of its SYNC), without a counter by the assembler's number.
* **Assembler -> fuser**: :mod:`multiprocessing.connection` (``Listener``/``Client`` over
  TCP, HMAC challenge on a shared key, one pickled :class:`CyclePart` per closed cycle) -
  the standard library's message transport: framing, authentication and in-order delivery
  come with it, it works across hosts, and nothing is invented on the wire. (CANopen on an
  "uplink" bus was the alternative: a 4,096-taxel part is ~1 kB per cycle, i.e. segmented
  transfers and a second master role for no gain.) The key comes from the environment
  variable ``FUSION_CENTER_AUTHKEY``; without it only loopback addresses are allowed (the
  peer that knows the key can send any pickle).
* **Merge** (:class:`CycleMerger`): per SYNC the fuser sent, one part per channel group. The
  cycle is ``complete``-able when every group's part arrived; a group whose part has not
  arrived when a later part of that group arrived (parts come in order), when the group
  disconnected, or ``part_deadline_s`` after the SYNC, is *missing*: its taxels count as
  silent (received nothing), the record is degraded and names the group in
  ``parts_missing`` (``closed_by: "part_missing"``). Cycles are evaluated in SYNC order;
  a part for a cycle already evaluated is counted (``late_parts``), never mixed in.
* **Reconnects**: an assembler whose connection breaks without the fuser's ``bye`` keeps
  assembling its buses (the parts closed meanwhile are counted as not sent, never queued) and
  connects again (0.1 s doubling to 2 s between tries, for ``--reconnect-timeout`` s; then it
  exits 1). The fuser accepts a group of its run again with the same hello checks (a group that
  is still connected is refused), counts it (``reconnects``) and merges its parts from then on;
  the cycles in between are degraded naming the group. A restarted assembler process is
  accepted the same way (its cycles are mapped by the SYNC counter; in a scene without one
  only an assembler that heard the master's reset, i.e. the same process, can come back).

By job: :mod:`.assembler_parts` (what both sides share: addresses and keys, channel groups,
:class:`CyclePart`), :mod:`.assembler_process` (the assembler: ``GroupAssembler``,
``AssemblerProcess``), :mod:`.cycle_merger` (the merge) and this module, the fuser
(:class:`AssembledFusionService`); their public names are importable from here.
"""

from __future__ import annotations

import logging
import threading
import time

from taxel_net.errors import UsageError
from taxel_net.scene import Scene
from .assembler_parts import (AUTHKEY_ENV, COB_SYNC, DEFAULT_AUTHKEY, NMT_RESETS, PROTOCOL, CyclePart,  # noqa: F401
                              GroupLayout, RateLimitedLog, authkey_for, check_serve, group_layout, group_name,
                              is_loopback, parse_address, scene_fingerprint, shutdown_connection,
                              tune_connection)
from .assembler_process import AssemblerProcess, GroupAssembler  # noqa: F401 - public names of this module
from .cycle_merger import CycleMerger, MergeStats  # noqa: F401
from .cycle_records import ClosedCycle, quantise_timestamp
from .fusion_service import FusionService
from .stream import EventStream

logger = logging.getLogger("fusion_center.service.assemblers")

# what the master needs to hear (accept filters, 11-bit): NMT, SYNC + EMCY, TIME, SDO both ways,
# heartbeats / boot-ups, LSS - every COB-ID but the PDOs (0x181..0x57F), which the assemblers take
MASTER_FILTERS = [
    {"can_id": 0x000, "can_mask": 0x7FF, "extended": False},
    {"can_id": 0x080, "can_mask": 0x780, "extended": False},
    {"can_id": 0x100, "can_mask": 0x7FF, "extended": False},
    {"can_id": 0x580, "can_mask": 0x780, "extended": False},
    {"can_id": 0x600, "can_mask": 0x780, "extended": False},
    {"can_id": 0x700, "can_mask": 0x780, "extended": False},
    {"can_id": 0x7E4, "can_mask": 0x7FE, "extended": False},
]


# ---------------------------------------------------------------------------- the fuser

class _FuserStream(EventStream):
    """The fuser's event stream: notes every SYNC the master sends (before it goes out)."""

    on_sync = None  # callable(payload: bytes) set by the service

    def transmit_all(self, frames, remote: bool = False) -> None:
        frames = list(frames)
        if self.on_sync is not None and not remote:
            for channel, can_id, data in frames:
                if channel == 0 and can_id == COB_SYNC:
                    self.on_sync(bytes(data))
        super().transmit_all(frames, remote)


class AssembledFusionService(FusionService):
    """The fuser: the CANopen master of :class:`FusionService` on every channel, its cycles
    assembled by ``fusion-center assemble`` processes (module docstring).

    ``listen``: (host, port) of the ``multiprocessing.connection`` listener the assemblers
    connect to; :meth:`boot` waits up to ``assembler_wait_s`` for assemblers covering every
    scene channel. The service's own ``CycleAssembler`` still runs (boot-ups, SDO answers, NMT
    states for the master), its closed cycles are not evaluated.

    ``pdo_filter`` (off by default): the fuser's buses accept only the master's traffic
    (:data:`MASTER_FILTERS`; kernel filters on SocketCAN). Only for scenes without a synchronous
    window: with one, the own assembler would hold SYNC k+1 until SYNC k+2 (no node frame after
    the window closes k), and with it an SDO request of a mid-run reconfiguration - whose answer
    would then arrive unsolicited (not handed to the SDO client). Measured on udp_multicast it
    saved nothing (python-can filters after parsing every datagram)."""

    def __init__(self, scene: Scene, *, listen: tuple[str, int], authkey: bytes | None = None,
                 part_deadline_s: float | None = None, assembler_wait_s: float = 30.0,
                 pdo_filter: bool = False, **kwargs):
        super().__init__(scene, **kwargs)
        self.pdo_filter = bool(pdo_filter)
        self.listen_address = listen
        self.authkey = authkey if authkey is not None else authkey_for(listen[0], "--assemblers")
        period = scene.bus.sync_period_ms / 1000.0
        # an assembler without a window closes a cycle with a silent node at the next SYNC
        self.part_deadline_s = part_deadline_s if part_deadline_s is not None else 2.5 * period + 0.1
        self.assembler_wait_s = assembler_wait_s
        self.merger = CycleMerger(scene, part_deadline_s=self.part_deadline_s)
        self.own_closed = 0
        echoes = self.stream.echoes
        self.stream = _FuserStream(self.assembler, on_closed=self._own_cycle, after_closed=self._process_pending)
        self.stream.echoes = echoes
        self.stream.on_sync = self._on_sync
        self._listener = None
        self._conns: dict = {}  # group name -> its connection
        self._conn_lock = threading.Lock()  # a group's connection and its place in the merger change together
        self._log = RateLimitedLog(logger)
        self._threads: list[threading.Thread] = []
        self._stop_merge = threading.Event()
        self._merge_lock = threading.Lock()  # emission order into _pending
        self.refused: list[str] = []

    # -- life cycle
    def open(self) -> "AssembledFusionService":
        from multiprocessing.connection import Listener

        super().open()
        if self.pdo_filter:  # the PDOs are the assemblers' (kernel filters on SocketCAN, else python-can's)
            for bus in self.buses:
                bus.set_filters(MASTER_FILTERS)
        try:
            self._listener = Listener(self.listen_address, authkey=self.authkey)
        except OSError as exc:
            self.close()
            host, port = self.listen_address
            raise UsageError(f"--assemblers {host}:{port}: cannot listen there ({exc.strerror or exc})") from None
        for target, name in ((self._accept_loop, "assembler-accept"), (self._tick_loop, "merge-deadline")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def close(self) -> None:
        self._stop_merge.set()
        listener, self._listener = self._listener, None
        if listener is not None:
            try:
                listener.close()
            except OSError:
                pass
        with self._conn_lock:
            conns = list(self._conns.values())
        for conn in conns:
            try:
                conn.send({"kind": "bye"})
            except (OSError, ValueError, EOFError):
                pass
            try:
                conn.close()
            except OSError:
                pass
        super().close()

    def boot(self, timeout_s: float = 3.0, configure: bool = True) -> list[int]:
        self.wait_for_assemblers(self.assembler_wait_s)
        return super().boot(timeout_s, configure)

    def wait_for_assemblers(self, timeout_s: float) -> None:
        want = set(range(len(self.scene.bus.channels)))
        deadline = time.monotonic() + timeout_s
        while self.merger.covered() != want:
            if time.monotonic() >= deadline:
                lacking = sorted(want - self.merger.covered())
                host, port = self.listen_address
                why = f" (refused: {'; '.join(self.refused)})" if self.refused else ""
                raise UsageError(f"--assemblers {host}:{port}: no assembler for scene channel(s) {lacking} after "
                                 f"{timeout_s:g} s: start `fusion-center assemble --scene ... --serve "
                                 f"{group_name(lacking)} --fuser {host}:{port}`{why}")
            time.sleep(0.02)

    def run(self, cycles: int, *, before_sync=None, timeout_s: float | None = None):
        if cycles < 1:
            raise UsageError(f"--cycles {cycles}: must be >= 1")
        period = self.scene.bus.sync_period_ms / 1000.0
        self.master.start_sync(cycles, before_sync)
        self.master.wait_sync_done(timeout_s if timeout_s is not None else cycles * period * 3 + 10.0)
        self.master.stop()
        deadline = time.monotonic() + self.part_deadline_s + 1.0
        while self.merger.pending() and time.monotonic() < deadline:
            time.sleep(0.005)
        self._emit(final=True)
        self.drain(timeout=5.0)
        return self.summary()

    # -- merge
    def _own_cycle(self, closed: ClosedCycle) -> None:
        self.own_closed += 1  # the master's own view of the cycle: not evaluated (the parts are)

    def _on_sync(self, payload: bytes) -> None:
        t0 = self.assembler.t0_us
        wall = time.time()
        sync_us = quantise_timestamp(wall) - (t0 if t0 is not None else 0)
        self.merger.opened(payload[0] if payload else None, max(0, sync_us), time.monotonic(), wall)

    def _emit(self, final: bool = False) -> None:
        with self._merge_lock:
            for closed in self.merger.emit(time.monotonic(), final=final):
                self._pending.append(closed)
        self._process_pending()

    def _tick_loop(self) -> None:
        tick = max(0.002, min(0.02, self.part_deadline_s / 4))
        while not self._stop_merge.wait(tick):
            try:
                self._emit()
            except Exception:  # noqa: BLE001 - the deadline thread never dies
                logger.exception("merge tick failed")

    def evaluate(self, closed: ClosedCycle) -> dict:
        record = self.pipeline.evaluate(closed)
        info = self.merger.info.pop(closed.cycle, None)
        record["parts_missing"] = info["parts_missing"] if info else []
        return record

    # -- connections
    def _accept_loop(self) -> None:
        while not self._stop_merge.is_set():
            listener = self._listener
            if listener is None:
                return
            try:
                conn = listener.accept()
            except Exception as exc:  # noqa: BLE001 - wrong key, closed listener, a port scan
                if self._stop_merge.is_set():
                    return
                logger.warning("assembler connection refused: %s: %s", type(exc).__name__, exc)
                continue
            thread = threading.Thread(target=self._serve, args=(conn,), name="assembler-conn", daemon=True)
            thread.start()

    def drop_assembler(self, name: str) -> bool:
        """Break the connection of group ``name`` as a network fault would (its assembler
        reconnects); False when that group is not connected."""
        with self._conn_lock:
            conn = self._conns.get(name)
        if conn is None:
            return False
        shutdown_connection(conn)
        return True

    def _serve(self, conn) -> None:
        name = None
        back = False
        tune_connection(conn)  # a peer gone without closing is noticed (assembler_parts.KEEPALIVE)
        try:
            hello = conn.recv()
            why = self._check_hello(hello)
            if why is None:
                layout = group_layout(self.scene, hello["channels"])
                with self._conn_lock:
                    before = self.merger.stats.reconnects.get(layout.name, 0)
                    why = self.merger.add_group(layout)
                    if why is None:
                        name = layout.name
                        self._conns[name] = conn
                        back = self.merger.stats.reconnects.get(name, 0) > before
            if why is not None:
                self.refused.append(why)
                logger.warning("assembler refused: %s", why)
                conn.send({"kind": "refused", "why": why})
                return
            if back:
                self._log.warning(f"back {name}", f"assembler of channel(s) {name} is back (host "
                                  f"{hello.get('host')}, pid {hello.get('pid')}; reconnect "
                                  f"{self.merger.stats.reconnects[name]}): its parts merge again")
            conn.send({"kind": "welcome", "group": name})
            while not self._stop_merge.is_set():
                part = conn.recv()
                if isinstance(part, CyclePart):
                    self.merger.add_part(name, part, time.time())
                    self._emit()
        except (EOFError, OSError):
            pass
        except Exception:  # noqa: BLE001 - one bad assembler never stops the fuser
            logger.exception("assembler connection failed")
        finally:
            if name is not None:
                with self._conn_lock:
                    if self._conns.get(name) is conn:
                        self.merger.remove_group(name)
                        del self._conns[name]
                if not self._stop_merge.is_set():
                    self._log.warning(f"gone {name}", f"assembler of channel(s) {name} disconnected: its parts "
                                      "are missing until it is back")
                    self._emit()
            try:
                conn.close()
            except OSError:
                pass

    def _check_hello(self, hello) -> str | None:
        if not isinstance(hello, dict) or hello.get("kind") != "hello" or hello.get("protocol") != PROTOCOL:
            return f"not an assembler hello of protocol {PROTOCOL}: {str(hello)[:80]}"
        mine = scene_fingerprint(self.scene)
        theirs = hello.get("scene")
        if theirs != mine:
            return f"scene differs: assembler {theirs}, fuser {mine}"
        channels = hello.get("channels")
        n = len(self.scene.bus.channels)
        if not channels or not all(isinstance(c, int) and 0 <= c < n for c in channels):
            return f"channels {channels!r}: the scene has channels 0..{n - 1}"
        if not self.scene.bus.sync_counter and self.merger.sent and not hello.get("numbered_from_reset"):
            return ("the scene has no SYNC counter and this run's SYNCs have begun: an assembler started now "
                    "cannot number its cycles (only one that heard the master's reset can come back)")
        return None
