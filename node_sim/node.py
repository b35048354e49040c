"""The taxel node firmware twin: CANopen slave behaviour around canopen's ``LocalNode``.

canopen 2.4.1's ``LocalNode`` supplies the object dictionary (loaded from the EDS), the
data store and the SDO server. It has no slave behaviour beyond that (no TPDO on SYNC, no
inhibit time / event timer, PDO data kept apart from the OD, no way out of INITIALISING
after an NMT reset: canopen issues #145, #520, #558, #47), so this module adds a small layer:

* NMT slave (CiA 301): boot-up ``0x700+id [0x00]`` then pre-operational; start (0x01),
  stop (0x02), enter pre-operational (0x80), reset node (0x81: the whole OD back to the
  start-up values), reset communication (0x82: only 0x1000-0x1FFF back); both resets send a
  new boot-up and return to pre-operational. SDO is served in pre-operational and
  operational only; in stopped only NMT and heartbeat are alive. Expedited and segmented
  transfers come from canopen's SdoServer; block transfers are refused with 0x05040001.
* heartbeat producer per 0x1017 (state byte 0x7F pre-op, 0x05 operational, 0x04 stopped).
* the application, on every SYNC (any state but INITIALISING): take X_i for that cycle,
  check it for sensor faults, run the local detector of the chapter (eqs 1-4, via
  :func:`local_decision_pm1`, the scalar form of :func:`fusion_center.core.encoding.local_decision`:
  u = +1 iff X − N ≥ ζ) and write u_i to
  0x2000 (INTEGER8 +1/−1), X_i to 0x6130:1 (REAL32 mV) and the AI status to 0x6150:1.
* TPDO1/TPDO2 per 0x1800/0x1801 + 0x1A00/0x1A01, in operational only: synchronous
  (transmission type 1..240: every n-th SYNC, honouring the SYNC start value 0x180x:6 when
  the SYNC carries a counter; type 0: on SYNC when the data changed) and event-driven
  (254/255: on change of the mapped data, spaced by the inhibit time 0x180x:3 in 100 µs
  units — a change inside the inhibit window is sent when it ends — and refreshed by the
  event timer 0x180x:5 in ms). Event-driven TPDOs are also sent once on entering
  operational. The payload is assembled from the OD at transmission time (no stale copy).
* EMCY (COB-ID 0x1014) on a sensor fault, with 0x1001 and 0x1003 (newest first, sub 0 =
  count) kept up to date, and the "error reset" EMCY (code 0x0000) when it clears; see
  :mod:`node_sim.emcy`. While a fault is active the decision is "absent" (−1) and flagged:
  0x6150:1 bit 0 (PV not valid), 0x1001 ≠ 0.
* ``silent`` (a dead node): no frame is sent and none is processed while it is set.

Threading: every entry point runs with the owning channel's lock held (the rig's notifier
thread or its scheduler thread); nodes never block.

Hot path (one SYNC, every node): the detector parameters (ζ, N_i, full scale, stuck count)
are cached as Python numbers and re-read from the OD after any write to it (SDO download,
:meth:`TaxelNode.configure`, NMT resets); the decision is the scalar twin of eqs 1-4
(:func:`local_decision_pm1`, equal to ``encoding.local_decision`` on every input the node
can see), the sampled values go straight into the OD data store with their EDS encodings,
and the TPDO payload is read from the data store - no canopen PDO or ODVariable call per
SYNC. The behaviour on the bus is the same as through canopen's ``get_data``/``encode_raw``.
"""

from __future__ import annotations

import copy
import math
import struct
import time

import canopen
from canopen.objectdictionary import ODVariable, datatypes
from canopen.sdo import SdoAbortedError

from taxel_net.scene import KIND_NAMES

from . import emcy as em
from . import od as odx
from .detector import (AI_STATUS_NEGATIVE_OVERLOAD, AI_STATUS_NOT_VALID, AI_STATUS_POSITIVE_OVERLOAD,
                       local_decision_pm1)
from .link import NodeLink, Scheduler
from .nmt import (INITIALISING, NMT_ENTER_PRE_OPERATIONAL, NMT_RESET_COMMUNICATION, NMT_RESET_NODE, NMT_START,
                  NMT_STOP, OPERATIONAL, PRE_OPERATIONAL, STATE_NAMES, STOPPED)
from .od import COB_29BIT, COB_INVALID
from .pdo import MAX_MAPPED, _TpdoConfig, _TpdoRuntime
from .sdo import (ABORT_COMMAND_SPECIFIER, ABORT_LENGTH_MISMATCH, ABORT_NOT_MAPPABLE, ABORT_PDO_LENGTH_EXCEEDED,
                  ABORT_SUBINDEX_NOT_IN_OD, ABORT_UNSUPPORTED_ACCESS, ABORT_VALUE_RANGE, ABORT_VALUE_TOO_HIGH,
                  ABORT_VALUE_TOO_LOW, SDO_ABORT, SDO_CCS_BLOCK_UPLOAD, SDO_CCS_DOWNLOAD, SDO_CCS_UPLOAD)
from .sync import SYNC_GENERATE


_REAL32 = struct.Struct("<f")


class _SdoLink:
    """The ``network`` the canopen SdoServer answers through: gated by the node's state."""

    def __init__(self, node: "TaxelNode"):
        self._node = node

    def send_message(self, can_id: int, data, remote: bool = False) -> None:
        self._node._send(can_id, bytes(data))


class TaxelNode:
    """One taxel's CANopen node twin (see module docstring).

    ``node_id`` 1..127; ``link`` gives the channel's ``send`` and scheduler; ``od`` defaults
    to the EDS imported for ``node_id``. Call :meth:`configure` with start-up values, then
    :meth:`power_on`. Entry points (:meth:`on_nmt`, :meth:`on_sdo_request`, :meth:`on_sync`)
    must be called with the channel lock held.
    """

    def __init__(self, node_id: int, link: NodeLink, od=None, eds_path=odx.EDS_PATH):
        self.node_id = node_id
        self.link = link
        self.od = od if od is not None else odx.load_od(node_id, eds_path)
        self._real_limits = odx.real_limits(eds_path)
        self.local = canopen.LocalNode(node_id, self.od)
        # LocalNode registers its NmtSlave's 0x1017 handler (which would start a python-can
        # periodic task per node); this layer produces the heartbeat itself.
        self.local._write_callbacks.clear()
        self.local.add_write_callback(self._on_sdo_write)
        self.local.sdo.network = _SdoLink(self)
        self.state = INITIALISING
        self.silent = False
        self._startup_store: dict[int, dict[int, bytes]] = {}
        # detector parameters as Python numbers (hot path), rebuilt after any OD write
        self._app_cfg: tuple[float, float, float, int] | None = None
        self._app_cfg_store: dict | None = None
        # EDS encodings of the values _sample writes (INTEGER8 u_i, REAL32 X_i, U8 status)
        self._u_bytes = {u: odx.variable(self.od, odx.LOCAL_DECISION, 0).encode_raw(u) for u in (1, -1)}
        self._pv_is_real32 = odx.variable(self.od, odx.AI_INPUT_PV, 1).data_type == datatypes.REAL32
        self._status_bytes: dict[int, bytes] = {}
        self._heartbeat = None
        self._tpdo_cfg: list[_TpdoConfig | None] = [None, None]
        self._tpdo_rt = [_TpdoRuntime(), _TpdoRuntime()]
        self._reset_application_state()
        self.frames_sent = 0
        self.last_cycle: int | None = None

    # ------------------------------------------------------------------ OD access
    def read(self, index: int, subindex: int = 0):
        """Current value of ``index:subindex`` decoded with its EDS data type."""
        var = odx.variable(self.od, index, subindex)
        return var.decode_raw(self.local.get_data(index, subindex))

    def _store(self, index: int, subindex: int, value) -> None:
        """Write an application-owned value straight into the OD data store."""
        var = odx.variable(self.od, index, subindex)
        self.local.data_store.setdefault(index, {})[subindex] = var.encode_raw(value)
        if index == odx.DETECTOR or index == odx.FAULT_DETECTION:
            self._app_cfg = None

    def _app_config(self) -> tuple[float, float, float, int]:
        """(ζ, N_i, full scale, stuck-sample count) of the OD as Python numbers, cached until
        the next OD write (SDO download, configure, _store) or data store swap (NMT resets)."""
        cfg = self._app_cfg
        if cfg is None or self._app_cfg_store is not self.local.data_store:
            cfg = (float(self.read(*odx.ZETA)), float(self.read(*odx.NOISE_ESTIMATE)),
                   float(self.read(*odx.FULL_SCALE)), int(self.read(*odx.STUCK_SAMPLES)))
            self._app_cfg = cfg
            self._app_cfg_store = self.local.data_store
        return cfg

    def configure(self, values: dict[tuple[int, int], object]) -> None:
        """Write start-up values (the node's stored parameters) into the OD, each checked by
        the same rules as an SDO download; a refused value raises ParameterError. Then they
        become the values NMT reset-node / reset-communication restore."""
        from taxel_net.errors import ParameterError

        for (index, subindex), value in values.items():
            var = odx.variable(self.od, index, subindex)
            data = var.encode_raw(value)
            try:
                self._check_write(index, subindex, var, data, startup=True)
            except SdoAbortedError as exc:
                raise ParameterError(f"node {self.node_id} 0x{index:04X}:{subindex}", value,
                                     f"refused by the node (SDO abort 0x{exc.code:08X})") from None
            self.local.data_store.setdefault(index, {})[subindex] = data
        self._startup_store = copy.deepcopy(self.local.data_store)
        self._tpdo_cfg = [None, None]
        self._app_cfg = None

    # ------------------------------------------------------------------ sending
    def _send(self, can_id: int, data: bytes) -> None:
        if self.silent:
            return
        self.link.send(can_id, data)
        self.frames_sent += 1

    def _send_emcy(self, code: int, register: int, fault_id: int = 0, reading: float = 0.0) -> None:
        if self.state not in (PRE_OPERATIONAL, OPERATIONAL):
            return
        cob = self.read(odx.COB_ID_EMCY)
        if cob & COB_INVALID:
            return
        r = reading if math.isfinite(reading) or math.isnan(reading) else math.copysign(3.4e38, reading)
        self._send(cob & 0x7FF, em.emcy_payload(code, register, fault_id, r))

    # ------------------------------------------------------------------ NMT
    def power_on(self) -> None:
        """INITIALISING → boot-up frame → PRE-OPERATIONAL, heartbeat started."""
        self._boot()

    def _boot(self) -> None:
        self._stop_all_timers()
        self.state = INITIALISING
        self._tpdo_cfg = [None, None]
        self._tpdo_rt = [_TpdoRuntime(), _TpdoRuntime()]
        self._send(0x700 + self.node_id, b"\x00")
        self.state = PRE_OPERATIONAL
        self._restart_heartbeat()

    def on_nmt(self, command: int) -> None:
        if self.silent or self.state == INITIALISING:
            return
        if command == NMT_START:
            if self.state != OPERATIONAL:
                self.state = OPERATIONAL
                self._enter_operational()
        elif command == NMT_STOP:
            self._leave_operational()
            self.state = STOPPED
        elif command == NMT_ENTER_PRE_OPERATIONAL:
            self._leave_operational()
            self.state = PRE_OPERATIONAL
        elif command == NMT_RESET_NODE:
            self.local.data_store = copy.deepcopy(self._startup_store)
            self._app_cfg = None
            self._reset_application_state()
            self._boot()
        elif command == NMT_RESET_COMMUNICATION:
            store = {i: s for i, s in self.local.data_store.items() if i not in odx.COMM_AREA}
            store.update({i: dict(s) for i, s in copy.deepcopy(self._startup_store).items()
                          if i in odx.COMM_AREA})
            self.local.data_store = store
            self._app_cfg = None
            self._reset_fault_state()
            self._boot()
        # unknown command specifiers are ignored (CiA 301)

    def _restart_heartbeat(self) -> None:
        if self._heartbeat is not None:
            self._heartbeat.cancel()
            self._heartbeat = None
        period_ms = self.read(odx.HEARTBEAT_PRODUCER)
        if period_ms > 0:
            self._schedule_heartbeat(time.monotonic() + period_ms / 1000.0, period_ms / 1000.0)

    def _schedule_heartbeat(self, when: float, period_s: float) -> None:
        def beat():
            if self.state != INITIALISING:
                self._send(0x700 + self.node_id, bytes([self.state]))
            # next beat one period after the planned time (no drift); after a beat that
            # came late by more than 10 % of the period, one period after now (no burst)
            now = time.monotonic()
            nxt = when + period_s if now - when <= 0.1 * period_s else now + period_s
            self._schedule_heartbeat(nxt, period_s)

        self._heartbeat = self.link.scheduler.call_at(when, beat)

    def _stop_all_timers(self) -> None:
        if self._heartbeat is not None:
            self._heartbeat.cancel()
            self._heartbeat = None
        self._leave_operational()

    # ------------------------------------------------------------------ SDO
    def on_sdo_request(self, data: bytes) -> None:
        if self.silent or self.state not in (PRE_OPERATIONAL, OPERATIONAL):
            return
        refusal = self._sdo_refusal(data)
        if refusal is not None:
            index, subindex = struct.unpack_from("<HB", data, 1)
            self._send(0x580 + self.node_id, struct.pack("<BHBL", SDO_ABORT, index, subindex, refusal))
            return
        self.local.sdo.on_request(0x600 + self.node_id, data, 0.0)

    def _sdo_refusal(self, data: bytes) -> int | None:
        """Abort code for the initiate requests canopen's SdoServer answers unlike a CiA 301
        server: a sub-index other than 0 of a VAR object (it serves the VAR instead of
        0x06090011) and a block upload the client did not allow to fall back to a normal
        upload (protocol switch threshold 0 or below the object's size: it answers with a
        normal upload anyway instead of 0x05040001; this node has no block transfer)."""
        ccs = data[0] & 0xE0
        initiate = ccs in (SDO_CCS_DOWNLOAD, SDO_CCS_UPLOAD) or \
            (ccs == SDO_CCS_BLOCK_UPLOAD and data[0] & 0x03 == 0)
        if not initiate:
            return None
        index, subindex = struct.unpack_from("<HB", data, 1)
        obj = self.od.get(index)
        if isinstance(obj, ODVariable) and subindex != 0:
            return ABORT_SUBINDEX_NOT_IN_OD
        if ccs == SDO_CCS_BLOCK_UPLOAD and obj is not None:
            protocol_switch_threshold = data[5]
            try:
                size = len(self.local.get_data(index, subindex))
            except KeyError:
                return None  # canopen answers 0x06020000 / 0x06090011
            if size > protocol_switch_threshold:
                return ABORT_COMMAND_SPECIFIER
        return None

    def _on_sdo_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """LocalNode write callback (runs before the value is stored): range checks raise
        SdoAbortedError with the CiA 301 abort code; then side effects of the new value."""
        self._check_write(index, subindex, od, bytes(data), startup=False)
        self._app_cfg = None  # stored right after this callback: re-read at the next SYNC
        if index == odx.ERROR_FIELD and subindex == 0:
            for sub in range(1, MAX_MAPPED + 1):
                self.local.data_store.get(odx.ERROR_FIELD, {}).pop(sub, None)
        if index in odx.TPDO_COMM or index in odx.TPDO_MAP:
            self._tpdo_cfg = [None, None]
            self._schedule_post_write(self._reconfigure_tpdos)
        if index == odx.HEARTBEAT_PRODUCER:
            self._schedule_post_write(self._restart_heartbeat)

    def _schedule_post_write(self, fn) -> None:
        # the value is stored right after the callback returns: act on it just after
        self.link.scheduler.call_at(0.0, fn)

    def _check_write(self, index: int, subindex: int, var: ODVariable, data: bytes, startup: bool) -> None:
        if var.data_type in datatypes.NUMBER_TYPES and 8 * len(data) != len(var):
            raise SdoAbortedError(ABORT_LENGTH_MISMATCH)
        value = var.decode_raw(data)
        if var.data_type in datatypes.FLOAT_TYPES:
            if not math.isfinite(value):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            low, high = self._real_limits.get((index, subindex), (-math.inf, math.inf))
            if value < low:
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
            if value > high:
                raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        elif isinstance(value, int):
            if var.min is not None and value < var.min:
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
            if var.max is not None and value > var.max:
                raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        if (index, subindex) == odx.TAXEL_KIND and value not in KIND_NAMES:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if index == odx.ERROR_FIELD and subindex == 0 and value != 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)  # only 0 (clear history) may be written
        if index == odx.COB_ID_SYNC and value & (SYNC_GENERATE | COB_29BIT):
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if index == odx.COB_ID_EMCY and value & COB_29BIT:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if index in odx.TPDO_COMM:
            self._check_tpdo_comm_write(odx.TPDO_COMM.index(index), subindex, value, startup)
        if index in odx.TPDO_MAP:
            self._check_tpdo_map_write(odx.TPDO_MAP.index(index), subindex, value, startup)

    def _check_tpdo_comm_write(self, pdo: int, subindex: int, value: int, startup: bool) -> None:
        comm = odx.TPDO_COMM[pdo]
        valid_now = not (self.read(comm, 1) & COB_INVALID)
        if subindex == 1:
            if value & COB_29BIT:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            if not startup and valid_now and not (value & COB_INVALID) \
                    and (value & 0x7FF) != (self.read(comm, 1) & 0x7FF):
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # CAN-ID changes only while not valid
        elif subindex == 2:
            if not (value <= 240 or value in (254, 255)):
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # 241-251 reserved, 252/253 RTR-only unsupported
        elif subindex in (3, 6):
            if not startup and valid_now:
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # CiA 301: not while the PDO is valid

    def _check_tpdo_map_write(self, pdo: int, subindex: int, value: int, startup: bool) -> None:
        comm, mapping = odx.TPDO_COMM[pdo], odx.TPDO_MAP[pdo]
        if not startup and not (self.read(comm, 1) & COB_INVALID):
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # mapping only while the PDO is not valid
        if subindex == 0:
            if value > MAX_MAPPED:
                raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
            bits = 0
            for sub in range(1, value + 1):
                entry = self.read(mapping, sub)
                bits += self._check_mappable(entry)
            if bits > 64:
                raise SdoAbortedError(ABORT_PDO_LENGTH_EXCEEDED)
        else:
            if not startup and self.read(mapping, 0) != 0:
                raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # CiA 301: set sub 0 to 0 first
            if value != 0:
                self._check_mappable(value)

    def _check_mappable(self, entry: int) -> int:
        index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        try:
            var = odx.variable(self.od, index, subindex)
            if isinstance(self.od[index], (canopen.objectdictionary.ODRecord,
                                           canopen.objectdictionary.ODArray)) \
                    and subindex not in self.od[index]:
                raise KeyError(subindex)
        except KeyError:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE) from None
        if not var.pdo_mappable or not var.readable or bits != len(var):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        return bits

    # ------------------------------------------------------------------ application
    def _reset_application_state(self) -> None:
        self._reset_fault_state()

    def _reset_fault_state(self) -> None:
        self.fault = em.FAULT_NONE
        self._last_raw: bytes | None = None
        self._same_count = 0

    def on_sync(self, cycle: int, reading: float, counter: int | None = None) -> None:
        """SYNC: sample X_i of ``cycle``, decide (eqs 1-4), update the OD, run the TPDOs."""
        if self.silent or self.state == INITIALISING:
            return
        self.last_cycle = cycle
        self._sample(float(reading))
        if self.state == OPERATIONAL:
            cfgs = self._tpdo_cfg
            for pdo in (0, 1):
                cfg = cfgs[pdo] or self._tpdo(pdo)
                if cfg.valid and cfg.mapping:
                    self._tpdo_on_sync(pdo, counter, cfg)

    def _sample(self, reading: float) -> None:
        zeta, noise, full_scale, stuck_after = self._app_config()
        raw = _REAL32.pack(reading)
        if raw == self._last_raw:
            self._same_count += 1
        else:
            self._same_count = 1
        self._last_raw = raw
        status = 0
        if not math.isfinite(reading) or abs(reading) >= full_scale:
            fault = em.FAULT_OPEN_CIRCUIT
            status = AI_STATUS_NOT_VALID
            if reading >= full_scale:
                status |= AI_STATUS_POSITIVE_OVERLOAD
            elif reading <= -full_scale:
                status |= AI_STATUS_NEGATIVE_OVERLOAD
        elif stuck_after > 0 and self._same_count >= stuck_after:
            fault = em.FAULT_STUCK
            status = AI_STATUS_NOT_VALID
        else:
            fault = em.FAULT_NONE
        if fault != self.fault:
            self._fault_changed(fault, reading)
        if fault == em.FAULT_NONE:
            decision = local_decision_pm1(reading, noise, zeta)  # eqs 1-4
        else:
            decision = -1  # faulted: "absent", flagged by 0x6150 and 0x1001
        # straight into the data store, EDS encodings (what _store / encode_raw would write)
        store = self.local.data_store
        (store.get(odx.LOCAL_DECISION) or store.setdefault(odx.LOCAL_DECISION, {}))[0] = self._u_bytes[decision]
        if self._pv_is_real32:
            (store.get(odx.AI_INPUT_PV) or store.setdefault(odx.AI_INPUT_PV, {}))[1] = raw
        else:
            self._store(odx.AI_INPUT_PV, 1, reading)
        status_raw = self._status_bytes.get(status)
        if status_raw is None:
            status_raw = self._status_bytes[status] = odx.variable(self.od, odx.AI_STATUS, 1).encode_raw(status)
        (store.get(odx.AI_STATUS) or store.setdefault(odx.AI_STATUS, {}))[1] = status_raw

    def _fault_changed(self, fault: int, reading: float) -> None:
        self.fault = fault
        if fault == em.FAULT_NONE:
            self._store(odx.ERROR_REGISTER, 0, 0)
            self._send_emcy(em.EMCY_NO_ERROR, 0)
            return
        code = em.FAULT_EMCY_CODE[fault]
        register = em.ERR_REG_SENSOR_FAULT
        self._store(odx.ERROR_REGISTER, 0, register)
        count = self.read(odx.ERROR_FIELD, 0)
        history = [self.read(odx.ERROR_FIELD, s) for s in range(1, count + 1)]
        history = [code | (fault << 16)] + history  # bits 16-31: manufacturer info (fault id)
        history = history[:MAX_MAPPED]
        for sub, entry in enumerate(history, start=1):
            self._store(odx.ERROR_FIELD, sub, entry)
        self._store(odx.ERROR_FIELD, 0, len(history))
        self._send_emcy(code, register, fault, reading)

    # ------------------------------------------------------------------ TPDOs
    def _tpdo(self, pdo: int) -> _TpdoConfig:
        cfg = self._tpdo_cfg[pdo]
        if cfg is None:
            comm, mapping = odx.TPDO_COMM[pdo], odx.TPDO_MAP[pdo]
            cob = self.read(comm, 1)
            entries = []
            for sub in range(1, self.read(mapping, 0) + 1):
                e = self.read(mapping, sub)
                entries.append((e >> 16, (e >> 8) & 0xFF, e & 0xFF))
            cfg = _TpdoConfig(
                valid=not (cob & COB_INVALID), can_id=cob & 0x7FF,
                transmission_type=self.read(comm, 2),
                inhibit_s=self.read(comm, 3) * 100e-6,
                event_timer_s=self.read(comm, 5) / 1000.0,
                sync_start=self.read(comm, 6), mapping=entries)
            self._tpdo_cfg[pdo] = cfg
        return cfg

    def _payload(self, cfg: _TpdoConfig) -> bytes:
        """The mapped objects' current bytes (what ``LocalNode.get_data`` returns: this node
        registers no read callback, so the data store, else the EDS value/default)."""
        if self.local._read_callbacks:  # someone added one: canopen's path
            return b"".join(self.local.get_data(i, s)[: bits // 8] for i, s, bits in cfg.mapping)
        store = self.local.data_store
        if len(cfg.mapping) == 1:
            i, s, bits = cfg.mapping[0]
            try:
                return store[i][s][: bits // 8]
            except KeyError:
                return self.local.get_data(i, s)[: bits // 8]
        parts = []
        for i, s, bits in cfg.mapping:
            try:
                parts.append(store[i][s][: bits // 8])
            except KeyError:
                parts.append(self.local.get_data(i, s)[: bits // 8])
        return b"".join(parts)

    def _transmit(self, pdo: int, cfg: _TpdoConfig, payload: bytes) -> None:
        rt = self._tpdo_rt[pdo]
        if not self.silent:  # _send, inlined (hot path)
            self.link.send(cfg.can_id, payload)
            self.frames_sent += 1
        rt.last_sent = payload
        self.link.mark_sent(rt)  # last_tx_time: now, or when the SYNC burst is sent
        if cfg.transmission_type >= 254:
            self._arm_event_timer(pdo, cfg)

    def _tpdo_on_sync(self, pdo: int, counter: int | None, cfg: _TpdoConfig) -> None:
        """A SYNC for a valid, mapped TPDO (``cfg`` = its current configuration)."""
        rt = self._tpdo_rt[pdo]
        tt = cfg.transmission_type
        if tt >= 254:
            self._event(pdo, cfg)
            return
        if tt == 0:
            payload = self._payload(cfg)
            if payload != rt.last_sent:
                self._transmit(pdo, cfg, payload)
            return
        if not rt.started:
            if cfg.sync_start and counter is not None and counter != cfg.sync_start:
                return
            rt.started = True
            rt.sync_count = tt - 1 if cfg.sync_start and counter is not None else 0
        rt.sync_count += 1
        if rt.sync_count >= tt:
            rt.sync_count = 0
            self._transmit(pdo, cfg, self._payload(cfg))

    def _event(self, pdo: int, cfg: _TpdoConfig, force: bool = False) -> None:
        rt = self._tpdo_rt[pdo]
        payload = self._payload(cfg)
        if not force and payload == rt.last_sent:
            return
        if rt.pending is not None:
            return  # already waiting for the inhibit time; it sends the data current then
        now = time.monotonic()
        earliest = rt.last_tx_time + cfg.inhibit_s
        if now >= earliest:
            self._transmit(pdo, cfg, payload)
        else:
            def deferred():
                rt.pending = None
                if self.state == OPERATIONAL:
                    c = self._tpdo(pdo)
                    if c.valid and c.transmission_type >= 254:
                        self._transmit(pdo, c, self._payload(c))

            rt.pending = self.link.scheduler.call_at(earliest, deferred)

    def _arm_event_timer(self, pdo: int, cfg: _TpdoConfig) -> None:
        rt = self._tpdo_rt[pdo]
        if rt.event_timer is not None:
            rt.event_timer.cancel()
            rt.event_timer = None
        if cfg.event_timer_s > 0:
            def refresh():
                rt.event_timer = None
                if self.state == OPERATIONAL:
                    c = self._tpdo(pdo)
                    if c.valid and c.transmission_type >= 254:
                        self._event(pdo, c, force=True)

            rt.event_timer = self.link.scheduler.call_later(cfg.event_timer_s, refresh)

    def _enter_operational(self) -> None:
        self._tpdo_rt = [_TpdoRuntime(), _TpdoRuntime()]
        for pdo in (0, 1):
            cfg = self._tpdo(pdo)
            if cfg.valid and cfg.mapping and cfg.transmission_type >= 254:
                self._event(pdo, cfg, force=True)

    def _leave_operational(self) -> None:
        for rt in self._tpdo_rt:
            for handle in (rt.pending, rt.event_timer):
                if handle is not None:
                    handle.cancel()
            rt.pending = rt.event_timer = None

    def _reconfigure_tpdos(self) -> None:
        """After an SDO write to 0x180x/0x1A0x: restart the event machinery with the new values."""
        self._tpdo_cfg = [None, None]
        if self.state != OPERATIONAL:
            return
        for pdo in (0, 1):
            rt = self._tpdo_rt[pdo]
            cfg = self._tpdo(pdo)
            if rt.event_timer is not None:
                rt.event_timer.cancel()
                rt.event_timer = None
            if cfg.valid and cfg.mapping and cfg.transmission_type >= 254:
                self._arm_event_timer(pdo, cfg)
            elif rt.pending is not None:
                rt.pending.cancel()
                rt.pending = None

    # ------------------------------------------------------------------ introspection
    @property
    def state_name(self) -> str:
        return STATE_NAMES[self.state]

    @property
    def decision(self) -> int:
        return self.read(odx.LOCAL_DECISION)

    def shutdown(self) -> None:
        self._stop_all_timers()
