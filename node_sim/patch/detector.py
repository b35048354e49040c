"""The local detectors of a patch node's taxels, vectorised (:class:`PatchDetector`, :func:`detect`).

The local detector of the chapter (eqs 1-4) over every taxel at once (numpy): ``u_i = +1 iff
X_i - N_i >= zeta_i`` with ζ_i 0x2010:i, N_i 0x2011:i; the sensor-fault checks of the one-taxel
node per taxel (open circuit: reading not finite or |X_i| >= full scale 0x2002:1; stuck: 0x2002:2
identical REAL32 samples in a row; a faulted taxel decides absent). The node's EMCY reports its
fault state (0x5000 if any taxel is open, else 0x7300 if any is stuck; its manufacturer field: the
fault id and the reading of the first faulted taxel) each time the set of faulted taxels changes,
error reset when none is left; 0x2022 holds the fault bits per taxel.

:func:`detect` is the detector of eqs 1-4 and the fault checks for any number of taxels: the one
implementation :meth:`PatchDetector.sample` runs for a node and
:class:`node_sim.patch.batch.PatchSyncBatch` for a channel's patch nodes at once.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from canopen.sdo import SdoAbortedError

from taxel_net import patches as P
from taxel_net.scene import KIND_NAMES

from .. import od as odx
from ..emcy import FAULT_NONE, FAULT_OPEN_CIRCUIT, FAULT_STUCK
from ..sdo import ABORT_SUBINDEX_NOT_IN_OD, ABORT_VALUE_RANGE, ABORT_VALUE_TOO_LOW
from .image import PatchImage
from .objects import PARAMETER_ARRAYS


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
    of a channel's patch nodes (:class:`node_sim.patch.batch.PatchSyncBatch`). The common case
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
        are done together instead (:class:`node_sim.patch.batch.PatchSyncBatch`: the same
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

