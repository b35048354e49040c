"""The patch node twin: one CANopen node hosting the taxels of a patch (issue 14).

A skin patch puts many taxels behind one microcontroller: :class:`PatchNode` is that node, a
:class:`node_sim.node.TaxelNode` whose application and TPDOs handle ``n`` taxels (1..254, one
entry of each OD array per taxel) on the object dictionary of ``eds/taxel_patch.eds``
(:func:`load_patch_od`). The CiA 301 services are the one-taxel node's own modules - NMT and
boot-up (:mod:`node_sim.nmt`), heartbeat producer / consumer (:mod:`.heartbeat`), the SDO server
(:mod:`.sdo`, expedited and segmented on canopen's ``LocalNode``), SYNC consumer (:mod:`.sync`),
EMCY (:mod:`.emcy`) and the TPDO engine (:mod:`.pdo`, generalised to 85 TPDO pairs and, on CAN
FD, 64 mapping entries / 512 bits per PDO). What differs:

* :class:`PatchDetector` - the local detector of the chapter (eqs 1-4) over every taxel at once
  (numpy): ``u_i = +1 iff X_i - N_i >= zeta_i`` with ζ_i 0x2010:i, N_i 0x2011:i; the sensor-fault
  checks of the one-taxel node per taxel (open circuit: reading not finite or |X_i| >= full
  scale 0x2002:1; stuck: 0x2002:2 identical REAL32 samples in a row; a faulted taxel decides
  absent). The node's EMCY reports its fault state (0x5000 if any taxel is open, else 0x7300 if
  any is stuck; its manufacturer field: the fault id and the reading of the first faulted
  taxel) each time the set of faulted taxels changes, error reset when none is left; 0x2022
  holds the fault bits per taxel.
* :class:`PatchImage` - the process image the TPDOs and SDO uploads read: the packed decisions
  0x2020 (bit ``k % 8`` of sub ``k // 8 + 1`` for taxel ``k``, :func:`taxel_net.patches.pack`),
  the cycle tag 0x2021 (the counter byte of the sampling SYNC, 0 without), the fault bits
  0x2022, the readings as INTEGER8 / INTEGER16 counts of 0x2032 mV (0x2030 / 0x2031,
  :func:`taxel_net.patches.readings_to_counts`: NaN -> the most negative code, saturated
  beyond the range; computed only when mapped or read). They are served to canopen's
  ``LocalNode`` by a read callback, never copied into the data store per SYNC. Sub 0 of every
  patch array reads its number of entries for this node (``n``, or ``ceil(n / 8)`` for the
  packed bytes); a sub-index beyond it is refused (0x06090011) for reads, writes and mappings.
* :class:`PatchTpdoEngine` - compiles each mapping once (on a change) into byte ranges of the
  image (consecutive entries of one array become one slice), so a SYNC costs one ``join`` of
  a few slices per TPDO; on CAN FD the data are padded with 0 to the next valid FD length.

Start-up values (what :meth:`PatchNode.configure` gets from :func:`patch_startup_values`) make the
node send exactly the frames :func:`taxel_net.patches.devices` describes for the device.

Hot path: one SYNC is one call with the patch's readings (a numpy view of the rig's vector):
about ten numpy operations on arrays of ``n`` values, then the TPDOs - no per-taxel Python loop.
"""

from __future__ import annotations

from functools import lru_cache

import canopen
import numpy as np
from canopen.sdo import SdoAbortedError

from taxel_net import patches as P
from taxel_net.resources import patch_eds_path
from taxel_net.scene import KIND_NAMES, TAXEL_KINDS

from . import od as odx
from .emcy import FAULT_NONE, FAULT_OPEN_CIRCUIT, FAULT_STUCK
from .link import NodeLink
from .node import TaxelNode
from .pdo import TpdoEngine, _TpdoConfig
from .sdo import ABORT_NOT_MAPPABLE, ABORT_SUBINDEX_NOT_IN_OD, ABORT_VALUE_RANGE, ABORT_VALUE_TOO_LOW

PATCH_EDS_PATH = patch_eds_path()
PATCH_FAULTS = 0x2022            # ARRAY UNSIGNED8: sensor-fault bits, the layout of 0x2020
PARAMETER_ARRAYS = (P.PATCH_ZETA, P.PATCH_NOISE, P.PATCH_KIND, P.PATCH_X, P.PATCH_Y)
IMAGE_ARRAYS = (P.PATCH_DECISIONS, PATCH_FAULTS, P.PATCH_READINGS_I8, P.PATCH_READINGS_I16)
_BYTE_ARRAYS = (P.PATCH_DECISIONS, PATCH_FAULTS)          # one sub per 8 taxels
N_TPDOS = 85
FD_MAPPED, CLASSIC_MAPPED, FD_TPDOS = 64, 8, 16           # eds/make_patch_eds.py
TPDO_COMM = tuple(0x1800 + k for k in range(N_TPDOS))
TPDO_MAP = tuple(0x1A00 + k for k in range(N_TPDOS))


@lru_cache(maxsize=32)
def _import(path: str, mtime: float, node_id: int):
    return canopen.import_od(path, node_id)


def load_patch_od(node_id: int, eds_path=PATCH_EDS_PATH):
    """The patch node EDS imported for ``node_id`` (cached per file and node-ID: the import takes
    ~0.4 s, and the twins only read the dictionary - values live in each node's data store)."""
    if not isinstance(node_id, int) or not 1 <= node_id <= 127:
        from taxel_net.errors import ParameterError
        raise ParameterError("node_id", node_id, "CANopen node-ID must be an integer 1..127")
    path = odx.check_eds(eds_path)
    return _import(str(path), path.stat().st_mtime, node_id)


class PatchImage:
    """The process image of one patch node (module docstring): bytes per image object."""

    def __init__(self, n: int):
        self.n = n
        self.n_bytes = (n + 7) // 8
        self.tag = 0
        self.decisions = bytes(self.n_bytes)
        self.faults = bytes(self.n_bytes)
        self.readings: np.ndarray = np.full(n, np.nan)   # X_i (mV) of the last SYNC
        self.lsb_mv = 0.01
        self._counts: dict[int, bytes] = {}
        self._tpdo = {P.PATCH_READINGS_I8: P.Tpdo(0, 0, 0, n, P.ENC_INT8, False, 0, False),
                      P.PATCH_READINGS_I16: P.Tpdo(0, 0, 0, n, P.ENC_INT16, False, 0, False)}

    def update(self, readings: np.ndarray, decisions: bytes, faults: bytes, tag: int) -> None:
        self.readings = readings
        self.decisions = decisions
        self.faults = faults
        self.tag = tag
        self._counts = {}

    def counts(self, index: int) -> bytes:
        """0x2030 / 0x2031: the readings as packed counts (computed once per SYNC, when asked)."""
        data = self._counts.get(index)
        if data is None:
            counts, _ = P.readings_to_counts(self._tpdo[index], self.readings, self.lsb_mv)
            data = self._counts[index] = counts.tobytes()
        return data

    def data(self, index: int) -> bytes:
        """The bytes of image object ``index`` (sub 1 first)."""
        if index == P.PATCH_DECISIONS:
            return self.decisions
        if index == P.PATCH_CYCLE_TAG:
            return bytes((self.tag,))
        if index == PATCH_FAULTS:
            return self.faults
        return self.counts(index)

    def entries(self, index: int) -> int:
        """Sub 0 of a patch array for this node."""
        return self.n_bytes if index in _BYTE_ARRAYS else self.n

    @staticmethod
    def entry_bytes(index: int) -> int:
        return 2 if index == P.PATCH_READINGS_I16 else 1


class PatchDetector:
    """The local detectors of a patch node's taxels, vectorised (module docstring)."""

    def __init__(self, objects: odx.NodeObjects, image: PatchImage, on_fault):
        self._objects = objects
        self._local = objects.local
        self._image = image
        self._on_fault = on_fault
        self.n = image.n
        self._cfg = None
        self._cfg_store = None
        self.reset()

    def reset(self) -> None:
        """Forget the fault state (NMT reset node / reset communication)."""
        self.fault = FAULT_NONE
        self.faulted = np.zeros(self.n, dtype=bool)
        self._last_raw = np.full(self.n, -1, dtype=np.int64)   # no REAL32 pattern: first sample counts 1
        self._same = np.zeros(self.n, dtype=np.int64)

    def invalidate(self, index: int | None = None, subindex: int | None = None) -> None:
        self._cfg = None

    def config(self):
        """(ζ array, N array, full scale, stuck count, LSB) from the OD, cached until a write or a
        data store swap."""
        store = self._local.data_store
        if self._cfg is None or self._cfg_store is not store:
            read = self._objects.read
            zeta, noise = self._real32_array(P.PATCH_ZETA), self._real32_array(P.PATCH_NOISE)
            self._cfg = (zeta, noise, float(read(*odx.FULL_SCALE)), int(read(*odx.STUCK_SAMPLES)))
            self._image.lsb_mv = float(read(P.PATCH_RAW_LSB))
            self._cfg_store = store
        return self._cfg

    def _real32_array(self, index: int) -> np.ndarray:
        """Subs 1..n of a REAL32 array as float64, from the data store's bytes (EDS default where
        none is stored): one ``frombuffer``, not n decodes (NMT resets swap the store)."""
        local = self._local
        stored = local.data_store.get(index, {})
        raw = b"".join(stored.get(s) or local.get_data(index, s) for s in range(1, self.n + 1))
        return np.frombuffer(raw, dtype="<f4").astype(np.float64)

    def check_write(self, index: int, subindex: int, value, startup: bool) -> None:
        """SDO / start-up write to 0x2002, 0x2010-0x2014, 0x2032."""
        if index in PARAMETER_ARRAYS and subindex > self.n:
            raise SdoAbortedError(ABORT_SUBINDEX_NOT_IN_OD)      # no such taxel on this node
        if index == P.PATCH_KIND and value not in KIND_NAMES:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if ((index, subindex) == odx.FULL_SCALE or index == P.PATCH_RAW_LSB) and not value > 0:
            raise SdoAbortedError(ABORT_VALUE_TOO_LOW)

    def sample(self, readings, counter: int | None = None) -> None:
        """X of one SYNC for every taxel (``readings``: n values, mV): faults, decisions
        (eqs 1-4), process image."""
        zeta, noise, full_scale, stuck_after = self.config()
        x = np.asarray(readings, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            raw = x.astype("<f4").view("<u4").astype(np.int64)   # the REAL32 samples, as the one-taxel node
        same = self._same
        np.add(same, 1, out=same)
        same[raw != self._last_raw] = 1
        self._last_raw = raw
        with np.errstate(invalid="ignore"):
            open_circuit = ~(np.abs(x) < full_scale)            # NaN, ±inf, |X| >= full scale
            present = (x - noise) >= zeta                       # eqs 1-4; NaN compares False
        faulted = open_circuit
        if stuck_after > 0:
            faulted = open_circuit | (same >= stuck_after)
        if faulted.any() or self.fault != FAULT_NONE:
            self._faults_changed(faulted, open_circuit, x)
            present &= ~faulted
        self._image.update(x, np.packbits(present, bitorder="little").tobytes(),
                           np.packbits(faulted, bitorder="little").tobytes(), counter or 0)

    def _faults_changed(self, faulted: np.ndarray, open_circuit: np.ndarray, x: np.ndarray) -> None:
        old = self.faulted
        if np.array_equal(faulted, old):
            return
        self.faulted = faulted.copy()
        if not faulted.any():
            self.fault = FAULT_NONE
            self._on_fault(FAULT_NONE, 0.0)
            return
        new = faulted & ~old
        first = int(np.flatnonzero(new if new.any() else faulted)[0])   # the first newly faulted taxel
        self.fault = FAULT_OPEN_CIRCUIT if open_circuit[faulted].any() else FAULT_STUCK
        self._on_fault(self.fault, float(x[first]))


class PatchTpdoEngine(TpdoEngine):
    """TPDOs of a patch node: mappings compiled to slices of the process image."""

    def __init__(self, node: "PatchNode", *, fd: bool):
        super().__init__(node, node.nmt, node.objects, node.link, comm=TPDO_COMM, mapping=TPDO_MAP,
                         max_mapped=tuple(FD_MAPPED if fd and k < FD_TPDOS else CLASSIC_MAPPED
                                          for k in range(N_TPDOS)),
                         max_bits=8 * (P.FD_DATA_MAX if fd else P.CLASSIC_DATA_MAX), fd=fd)
        self._image = node.image

    def _compile(self, cfg: _TpdoConfig):
        """``(runs, padding)``: runs ``(index, start, stop)`` of image bytes, or ``(index,
        subindex, None)`` for another object (read from the OD at transmission)."""
        runs: list[list] = []
        image = self._image
        length = 0
        for index, subindex, bits in cfg.mapping:
            size = bits // 8
            length += size
            if index in IMAGE_ARRAYS:
                width = image.entry_bytes(index)
                start = (subindex - 1) * width
                if runs and runs[-1][0] == index and runs[-1][2] == start:
                    runs[-1][2] = start + width
                else:
                    runs.append([index, start, start + width])
            elif index == P.PATCH_CYCLE_TAG:
                runs.append([index, 0, 1])
            else:
                runs.append([index, subindex, None])
        padding = bytes(P.fd_length(length) - length) if self.fd and length <= P.FD_DATA_MAX else b""
        return tuple(tuple(r) for r in runs), padding

    def _payload(self, cfg: _TpdoConfig) -> bytes:
        runs, padding = cfg.plan
        data = self._image.data
        parts = [data(i)[a:b] if b is not None else self._objects.local.get_data(i, a) for i, a, b in runs]
        if padding:
            parts.append(padding)
        return b"".join(parts)

    def _check_mappable(self, entry: int) -> int:
        index, subindex = entry >> 16, (entry >> 8) & 0xFF
        if index in IMAGE_ARRAYS and not 1 <= subindex <= self._image.entries(index):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)               # no such taxel on this node
        return super()._check_mappable(entry)


class PatchNode(TaxelNode):
    """One patch node twin hosting ``n`` taxels (module docstring). ``fd``: its TPDOs are CAN
    FD frames (mappings of up to 64 entries / 512 bits). ``od`` defaults to the patch EDS
    imported for ``node_id`` (:func:`load_patch_od`)."""

    SCALAR_READING = False
    APPLICATION_OBJECTS = (odx.FAULT_DETECTION, *PARAMETER_ARRAYS, P.PATCH_RAW_LSB)

    def __init__(self, node_id: int, link: NodeLink, n: int, od=None, eds_path=PATCH_EDS_PATH, *, fd: bool = False):
        if not 1 <= n <= P.PATCH_TAXELS_MAX:
            from taxel_net.errors import ParameterError
            raise ParameterError("n", n, f"a patch node hosts 1..{P.PATCH_TAXELS_MAX} taxels")
        self.n = n
        self.image = PatchImage(n)
        if od is None:
            od = load_patch_od(node_id, eds_path)
        super().__init__(node_id, link, od, eds_path, fd=fd)
        self.local.add_read_callback(self._read_image)

    def configure(self, values) -> None:
        super().configure(values)
        self.detector.config()   # the arrays decoded now, not at the first SYNC

    def _new_detector(self):
        return PatchDetector(self.objects, self.image, self.emcy.fault_changed)

    def _new_pdo(self, fd: bool) -> TpdoEngine:
        return PatchTpdoEngine(self, fd=fd)

    def _read_image(self, index: int, subindex: int, od):
        """LocalNode read callback: the process image and the sub 0 counts of the patch arrays."""
        if index < P.PATCH_ZETA or index > P.PATCH_READINGS_I16:
            return None
        image = self.image
        if index in IMAGE_ARRAYS or index in PARAMETER_ARRAYS:
            count = image.entries(index)
            if subindex == 0:
                return count
            if subindex > count:
                raise SdoAbortedError(ABORT_SUBINDEX_NOT_IN_OD)
            if index in PARAMETER_ARRAYS:
                return None
            width = image.entry_bytes(index)
            return od.decode_raw(image.data(index)[(subindex - 1) * width: subindex * width])
        if index == P.PATCH_CYCLE_TAG:
            return image.tag
        return None

    # ------------------------------------------------------------------ introspection
    @property
    def decision(self) -> np.ndarray:
        """u_i of the last SYNC, ±1 per taxel (int8)."""
        bits = np.unpackbits(np.frombuffer(self.image.decisions, dtype=np.uint8), bitorder="little")[: self.n]
        return 2 * bits.astype(np.int8) - 1

    @property
    def faulted(self) -> np.ndarray:
        return self.detector.faulted


def patch_startup_values(scene, device: P.Device, identity_serial: int) -> dict[tuple[int, int], object]:
    """Start-up values of ``device`` (a patch of ``scene``, :func:`taxel_net.patches.devices`):
    its taxels' arrays, the communication parameters of ``scene.bus`` and the TPDOs the device
    describes (COB-ID, mapping: tag, then the array entries of its taxels; the other TPDOs
    keep the EDS defaults: not valid). In an order :meth:`TaxelNode.configure` accepts (mapping entries before sub 0)."""
    bus = scene.bus
    taxels = [scene.taxels[i] for i in device.taxels]
    values: dict[tuple[int, int], object] = {
        (odx.HEARTBEAT_PRODUCER, 0): int(bus.heartbeat_producer_ms),
        (odx.SYNC_OVERFLOW, 0): int(bus.sync_counter),
        (odx.IDENTITY, 4): identity_serial,
        (odx.SYNC_WINDOW, 0): int(bus.sync_window),
        (P.PATCH_RAW_LSB, 0): float(bus.raw_lsb_mv),
    }
    for sub, t in enumerate(taxels, start=1):
        values[(P.PATCH_ZETA, sub)] = float(t.zeta_mv)
        values[(P.PATCH_NOISE, sub)] = float(t.noise_mv)
        values[(P.PATCH_KIND, sub)] = TAXEL_KINDS[t.kind]
        if t.x is not None:
            values[(P.PATCH_X, sub)] = float(t.x)
        if t.y is not None:
            values[(P.PATCH_Y, sub)] = float(t.y)
    if any(t.noise_sigma_mv == 0 for t in taxels):
        values[odx.STUCK_SAMPLES] = 0   # a noiseless taxel repeats its readings legitimately
    for tpdo in device.tpdos:
        comm, mapping = TPDO_COMM[tpdo.number], TPDO_MAP[tpdo.number]
        values[(comm, 1)] = odx.COB_NO_RTR | tpdo.cob_id
        values[(comm, 2)] = int(bus.transmission_type)
        values[(comm, 3)] = int(bus.inhibit_time_100us)
        values[(comm, 5)] = int(bus.event_timer_ms)
        entries = tpdo_mapping(tpdo)
        for sub, entry in enumerate(entries, start=1):
            values[(mapping, sub)] = entry
        values[(mapping, 0)] = len(entries)
    return values


def tpdo_mapping(tpdo: P.Tpdo) -> list[int]:
    """The mapping entries (index << 16 | sub << 8 | bits) of a patch TPDO: the cycle tag when
    tagged, then its taxels' decision bytes / readings."""
    entries = [P.PATCH_CYCLE_TAG << 16 | 8] if tpdo.tagged else []
    if tpdo.encoding == P.ENC_BITS:
        first = tpdo.first // 8 + 1
        entries += [P.PATCH_DECISIONS << 16 | sub << 8 | 8 for sub in range(first, first + tpdo.payload_bytes)]
    elif tpdo.encoding in P.RAW_BYTES:
        index, bits = ((P.PATCH_READINGS_I8, 8) if tpdo.encoding == P.ENC_INT8 else (P.PATCH_READINGS_I16, 16))
        entries += [index << 16 | sub << 8 | bits for sub in range(tpdo.first + 1, tpdo.first + tpdo.count + 1)]
    else:
        raise ValueError(f"{tpdo.encoding}: not a patch encoding")
    return entries


__all__ = ["PatchNode", "PatchDetector", "PatchImage", "PatchTpdoEngine", "load_patch_od",
           "patch_startup_values", "tpdo_mapping", "PATCH_FAULTS", "PATCH_EDS_PATH"]
