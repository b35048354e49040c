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
* :class:`PatchTpdoEngine` - compiles each mapping once (on a change) into a function of byte
  ranges of the image (consecutive entries of one array become one slice), so a SYNC costs one
  ``join`` of a few slices per TPDO (the tag and the packed decisions: one concatenation); on
  CAN FD the data are padded with 0 to the next valid FD length. TPDOs all sent on every SYNC
  (transmission type 1) leave in one call to the link.

Start-up values (what :meth:`PatchNode.configure` gets from :func:`patch_startup_values`) make the
node send exactly the frames :func:`taxel_net.patches.devices` describes for the device.

:func:`detect` is the detector of eqs 1-4 and the fault checks for any number of taxels: the
one implementation :meth:`PatchDetector.sample` runs for a node and
:class:`node_sim.patch_batch.PatchSyncBatch` for a channel's patch nodes at once.
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
    path = odx.check_eds(eds_path, reference=PATCH_EDS_PATH)
    return _import(str(path), path.stat().st_mtime, node_id)


_ONE_BYTE = tuple(bytes((v,)) for v in range(256))


class PatchImage:
    """The process image of one patch node (module docstring): bytes per image object."""

    def __init__(self, n: int):
        self.n = n
        self.n_bytes = (n + 7) // 8
        self.tag = 0
        self.tag_byte = _ONE_BYTE[0]     # 0x2021 as its one data byte
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
        self.tag_byte = _ONE_BYTE[tag]
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
            return self.tag_byte
        if index == PATCH_FAULTS:
            return self.faults
        return self.counts(index)

    def entries(self, index: int) -> int:
        """Sub 0 of a patch array for this node."""
        return self.n_bytes if index in _BYTE_ARRAYS else self.n

    @staticmethod
    def entry_bytes(index: int) -> int:
        return 2 if index == P.PATCH_READINGS_I16 else 1


NEVER_STUCK = np.iinfo(np.int64).max     # the stuck limit of a taxel whose 0x2002:2 is 0 (check off)


def stuck_limit(stuck_samples: int) -> int:
    """The run length of identical REAL32 samples at which a taxel is stuck: 0x2002:2, or
    :data:`NEVER_STUCK` when it is 0 (the check is off)."""
    return stuck_samples if stuck_samples > 0 else NEVER_STUCK


@lru_cache(maxsize=64)
def _constant(n: int, value) -> np.ndarray:
    """A read-only array of ``n`` times ``value`` (its dtype), shared: the run lengths of
    taxels that did not repeat their sample (1) and the fault bits of taxels that are fine."""
    array = np.full(n, value)
    array.flags.writeable = False
    return array


def detect(x: np.ndarray, zeta, noise, full_scale, stuck_after, stuck_min: int, last_raw: np.ndarray,
           same: np.ndarray, valid: np.ndarray | None = None):
    """The local detectors and sensor-fault checks of taxels with readings ``x`` (mV, float64),
    one SYNC: ``(raw, same, open_circuit, faulted, present, any_faulted)``.

    ``raw``: the REAL32 bit patterns of ``x`` (uint32; ``last_raw`` holds those of the previous
    sample); ``same``: how many identical patterns in a row, the one of this SYNC included
    (``same`` in: the counts before it, 0 before the first sample). ``open_circuit``: X_i not
    finite or |X_i| >= full scale (0x2002:1); ``faulted``: open circuit, or stuck (``same``
    reached ``stuck_after``, :func:`stuck_limit` of 0x2002:2; ``stuck_min``: its smallest
    value). ``present``: u_i = +1, i.e. Y_i = X_i - N_i >= zeta_i (eqs 1-4: Y = X - N, eq 4;
    u = +1 iff Y >= zeta, eqs 2-3; a NaN compares False) and the taxel not faulted (a faulted
    taxel decides absent). ``valid`` (optional): False for entries that are no taxel (padding):
    absent, not faulted. ``any_faulted``: some taxel is faulted.

    ``zeta``, ``noise`` (per taxel; None: every N_i is 0, Y_i = X_i exactly), ``full_scale``
    (a float or one value per taxel) and ``stuck_after`` (a number or one value per taxel)
    broadcast against ``x``: one node (:meth:`PatchDetector.sample`) or the concatenated taxels
    of a channel's patch nodes (:class:`node_sim.patch_batch.PatchSyncBatch`). The common case
    - no repeated sample, every reading in range - costs about ten numpy calls; then ``same``,
    ``open_circuit`` and ``faulted`` are shared read-only arrays (never written in place).
    Floating-point warnings (a reading beyond REAL32, inf - inf) are silenced only when a
    reading is out of range."""
    n = len(x)
    in_range = np.abs(x) < full_scale                        # False: NaN, +-inf, |X| >= full scale
    all_in_range = np.count_nonzero(in_range) == n           # (count_nonzero: a third of all()'s cost)
    if all_in_range:   # finite readings below full scale (a REAL32): no floating-point warning
        raw = x.astype("<f4").view("<u4")
        present = (x >= zeta) if noise is None else (x - noise) >= zeta   # eqs 1-4
    else:
        with np.errstate(over="ignore", invalid="ignore"):    # beyond REAL32, inf - inf
            raw = x.astype("<f4").view("<u4")
            present = (x >= zeta) if noise is None else (x - noise) >= zeta
    repeated = raw == last_raw
    if np.count_nonzero(repeated):
        same = same * repeated
        same += 1
        stuck = same >= stuck_after
    else:
        same = _constant(n, 1)
        stuck = same >= stuck_after if stuck_min <= 1 else None
    if valid is not None:
        present &= valid
    if stuck is None and all_in_range:
        no_fault = _constant(n, False)
        return raw, same, no_fault, no_fault, present, False
    open_circuit = ~in_range
    faulted = open_circuit | stuck if stuck is not None else open_circuit.copy()
    if valid is not None:
        faulted &= valid
    present &= ~faulted
    return raw, same, open_circuit, faulted, present, np.count_nonzero(faulted) > 0


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
        self._last_raw = np.zeros(self.n, dtype=np.uint32)   # REAL32 patterns of the last sample
        self._same = np.zeros(self.n, dtype=np.int64)         # 0: the first sample counts 1
        self._no_faults = bytes(self._image.n_bytes)

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
        (eqs 1-4, :func:`detect`), process image. A channel's patch nodes sampling the same SYNC
        are done together instead (:class:`node_sim.patch_batch.PatchSyncBatch`: the same
        :func:`detect`)."""
        zeta, noise, full_scale, stuck_after = self.config()
        x = np.asarray(readings, dtype=np.float64)
        limit = stuck_limit(stuck_after)
        raw, same, open_circuit, faulted, present, any_faulted = detect(
            x, zeta, noise, full_scale, limit, limit, self._last_raw, self._same)
        self.record(x, raw, same, np.packbits(present, bitorder="little").tobytes(), counter,
                    faulted, open_circuit, any_faulted)

    def record(self, x: np.ndarray, raw: np.ndarray, same: np.ndarray, decisions: bytes,
               counter: int | None, faulted: np.ndarray | None, open_circuit: np.ndarray | None,
               any_faulted: bool, faults: bytes | None = None) -> None:
        """What :func:`detect` made of this node's readings ``x`` becomes its state: the REAL32
        samples and run lengths of the stuck check, the fault state (EMCY on a change,
        :meth:`_faults_changed`) and the process image (``decisions``: the packed bits of
        0x2020; ``faults``: those of 0x2022, packed here from ``faulted`` when not given).
        ``faulted`` / ``open_circuit`` may be None when no taxel is faulted and the node had
        no fault."""
        self._last_raw = raw
        self._same = same
        if any_faulted or self.fault != FAULT_NONE:
            self._faults_changed(faulted, open_circuit, x)
        if faults is None:
            faults = np.packbits(faulted, bitorder="little").tobytes() if any_faulted else self._no_faults
        self._image.update(x, decisions, faults, counter or 0)

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
        self._every_sync = self._tagged_decisions = None   # what _activate finds
        self._every_sync_runtimes: tuple = ()

    def _activate(self):
        active = super()._activate()
        # every active TPDO synchronous, sent on every SYNC (transmission type 1, no SYNC start
        # value): on_sync sends them without the general per-TPDO bookkeeping, which leaves
        # them started with their SYNC count at 0 after every SYNC - as here
        every_sync = bool(active) and all(cfg.transmission_type == 1 and not cfg.sync_start for _, cfg, _ in active)
        self._every_sync = tuple((cfg.can_id, cfg.plan, rt) for _, cfg, rt in active) if every_sync else None
        self._every_sync_runtimes = tuple(rt for _, _, rt in active)
        # and each the cycle tag and a range of packed decisions (classic): (can_id, start, stop)
        self._tagged_decisions = (tuple((cfg.can_id, *cfg.plan.tagged_decisions) for _, cfg, _ in active)
                                  if every_sync and not self.fd
                                  and all(hasattr(cfg.plan, "tagged_decisions") for _, cfg, _ in active)
                                  else None)
        if every_sync:
            for rt in self._every_sync_runtimes:
                rt.started = True
                rt.sync_count = 0
        return active

    def on_sync(self, counter: int | None) -> None:
        """A SYNC in OPERATIONAL for a live node: :meth:`TpdoEngine.on_sync`, or when every
        active TPDO is sent on every SYNC, their frames in one :meth:`NodeLink.send_all`
        (the same frames and run-time state)."""
        if self._active is None:
            self._activate()
        every_sync = self._every_sync
        if every_sync is None:
            super().on_sync(counter)
            return
        tagged = self._tagged_decisions
        if tagged is not None:
            image = self._image
            tag, decisions = image.tag_byte, image.decisions
            frames = [(can_id, tag + decisions[first:stop]) for can_id, first, stop in tagged]
            for (_, payload), rt in zip(frames, self._every_sync_runtimes):
                rt.last_sent = payload
        else:
            frames = []
            fd = self.fd
            for can_id, payload_of, rt in every_sync:
                payload = payload_of()
                rt.last_sent = payload
                frames.append((can_id, payload, True) if fd else (can_id, payload))
        self._link.send_all(frames, self._every_sync_runtimes)
        self.frames_sent += len(frames)

    def _compile(self, cfg: _TpdoConfig):
        """The payload of ``cfg`` as a function of no argument: byte ranges of the image
        (consecutive entries of one array: one range) and other objects (read from the OD at
        transmission), joined, then the FD padding; the cycle tag and one range of packed
        decisions (the rig's patch TPDOs) is one concatenation."""
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
        kinds = [r[0] for r in runs]
        if not padding and kinds == [P.PATCH_CYCLE_TAG, P.PATCH_DECISIONS]:
            first, stop = runs[1][1], runs[1][2]

            def tagged_decisions() -> bytes:
                return image.tag_byte + image.decisions[first:stop]

            tagged_decisions.tagged_decisions = (first, stop)   # what on_sync sends without the call
            return tagged_decisions
        if not padding and kinds == [P.PATCH_DECISIONS]:
            first, stop = runs[0][1], runs[0][2]
            return lambda: image.decisions[first:stop]
        runs = tuple(tuple(r) for r in runs)
        data = image.data
        local = self._objects.local

        def payload() -> bytes:
            parts = [data(i)[a:b] if b is not None else local.get_data(i, a) for i, a, b in runs]
            if padding:
                parts.append(padding)
            return b"".join(parts)

        return payload

    def _payload(self, cfg: _TpdoConfig) -> bytes:
        return cfg.plan()

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


__all__ = ["PatchNode", "PatchDetector", "PatchImage", "PatchTpdoEngine", "detect", "load_patch_od",
           "patch_startup_values", "tpdo_mapping", "PATCH_FAULTS", "PATCH_EDS_PATH"]
