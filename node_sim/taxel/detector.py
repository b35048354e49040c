"""The taxel node's application: the local detector of the chapter, eqs 1-4, with its analog input.

Chapter "Grip Force and Slip Analysis in Robotic Grasp: New Stochastic Paradigm Through
Sensor Data Fusion": each taxel i decides between H1 (object present) and H0 on its own
observation X_i and sends one decision u_i in the {-1,+1} tuple (sec. 2.1); eqs 1-4 are
that local test:

    Y_i = X_i - N_i                      (eq 4, N_i the taxel's noise estimate)
    u_i = +1  if Y_i >= ζ                (eqs 2-3, ζ the cut-off)
    u_i = -1  otherwise (a NaN reading compares False: absent)

:func:`local_decision_pm1` is that test for one scalar observation — the same IEEE-754
comparison as :func:`fusion_center.core.encoding.local_decision` (the vectorised form the
fusion centre uses; ``tests/test_node_fastpath.py`` checks they agree).

:class:`Detector` is what the node does with it on every SYNC (called by the SYNC consumer,
:mod:`node_sim.sync`): take X_i (mV) for the cycle, check it for sensor faults, decide, and
write the OD —

* u_i to 0x2000 (INTEGER8 +1/−1) and, tagged with the sampling SYNC's counter, to 0x2003
  (:func:`tagged_decision`: the cycle tag TPDO1 maps when the SYNC carries a counter), X_i to 0x6130:1 (CiA 404 AI input PV, REAL32 mV) and the
  CiA 404 AI status to 0x6150:1 (bit 0 PV not valid, bit 1 positive overload, bit 2 negative
  overload);
* parameters: ζ 0x2001:1 and N_i 0x2001:2 (mV), full scale 0x2002:1 and the stuck-sample count
  M 0x2002:2 (0 = off); kind/x/y 0x2001:3-5 describe the taxel (the kind must be one of the
  scene's kinds: SDO abort 0x06090030); a full scale ≤ 0 is refused with 0x06090032 (the
  node's own check: no REAL32 limit in the EDS, which objdictgen would refuse);
* faults: open circuit (reading not finite or |X| ≥ full scale: status "not valid" plus the
  overload bit of its sign) and stuck (M consecutive identical REAL32 samples). While a fault
  is active the decision is "absent" (−1), flagged by 0x6150:1 bit 0 and the EMCY producer
  (0x1001 ≠ 0, :mod:`node_sim.emcy`), which is told of every fault change.

Hot path: the parameters are cached as Python numbers and re-read from the OD after any write
to it (:meth:`Detector.invalidate`, called on SDO downloads and start-up values) or a swap of
the data store (NMT resets); the sampled values go straight into the data store with their
EDS encodings — no canopen ODVariable call per SYNC.
"""

from __future__ import annotations

import math
import struct
from typing import Callable

from canopen.objectdictionary import datatypes
from canopen.sdo import SdoAbortedError

from taxel_net.scene import KIND_NAMES

from ..emcy import FAULT_NONE, FAULT_OPEN_CIRCUIT, FAULT_STUCK
from ..od import (AI_INPUT_PV, AI_STATUS, FULL_SCALE, LOCAL_DECISION, NOISE_ESTIMATE, STUCK_SAMPLES, TAGGED_DECISION,
                 TAXEL_KIND, ZETA, NodeObjects)
from ..sdo import ABORT_VALUE_RANGE, ABORT_VALUE_TOO_LOW

AI_STATUS_NOT_VALID = 0x01
AI_STATUS_POSITIVE_OVERLOAD = 0x02
AI_STATUS_NEGATIVE_OVERLOAD = 0x04

_REAL32 = struct.Struct("<f")


TAG_BITS = 6          # 0x2003 bits 2-7: the SYNC counter modulo 64
TAG_MASK = (1 << TAG_BITS) - 1


def tagged_decision(decision: int, counter: int | None) -> int:
    """Object 0x2003 (UNSIGNED8): u_i in bits 0-1 as a 2-bit two's complement number (0b01 = +1,
    0b11 = −1, the low bits of INTEGER8 +1/−1) and, in bits 2-7, the counter of the SYNC the
    decision was sampled at modulo 64 (0 for a SYNC without counter).

    The fusion centre counts a tagged decision only in the cycle opened by a SYNC with the
    same counter modulo 64, so an answer to an earlier SYNC is never mixed into a later cycle
    (no extra bus bit: u_i needs 2 of the byte's 8)."""
    return ((counter or 0) & TAG_MASK) << 2 | (0b01 if decision > 0 else 0b11)


def local_decision_pm1(observation: float, noise: float, zeta: float) -> int:
    """Scalar local detector of one taxel, eqs 1-4, in the {-1,+1} tuple (``pm1``).

    Y = X - N (eq 4); u = +1 iff Y >= ζ (eqs 2-3), else -1; a NaN observation compares False
    and decides absent. The same IEEE-754 double comparison as
    :func:`fusion_center.core.encoding.local_decision` (``(x - n) >= z``), without its array
    conversions: for a node it costs ~0.1 µs instead of ~10 µs. It does not check ζ: the node's
    OD refuses a negative or non-finite ζ (SDO abort 0x06090032 / 0x06090030), which is the
    domain ``local_decision`` accepts; ``tests/test_node_fastpath.py`` checks both agree.
    """
    return 1 if observation - noise >= zeta else -1


class Detector:
    """One node's application (see module docstring): owns the cached parameters and the
    fault state. ``on_fault(fault, reading)`` is told of every fault change."""

    def __init__(self, objects: NodeObjects, on_fault: Callable[[int, float], None]):
        self._objects = objects
        self._local = objects.local
        self._on_fault = on_fault
        # detector parameters as Python numbers (hot path), rebuilt after any OD write
        self._cfg: tuple[float, float, float, int] | None = None
        self._cfg_store: dict | None = None
        # EDS encodings of the values sample() writes (INTEGER8 u_i, REAL32 X_i, U8 status)
        self._u_bytes = {u: objects.variable(LOCAL_DECISION, 0).encode_raw(u) for u in (1, -1)}
        # 0x2003 per u_i and counter modulo 64: 2 x 64 one-byte values
        tagged = objects.variable(TAGGED_DECISION, 0)
        self._tagged_bytes = {u: [tagged.encode_raw(tagged_decision(u, c)) for c in range(TAG_MASK + 1)]
                              for u in (1, -1)}
        self._pv_is_real32 = objects.variable(AI_INPUT_PV, 1).data_type == datatypes.REAL32
        self._status_bytes: dict[int, bytes] = {}
        self.reset()

    def reset(self) -> None:
        """Forget the fault state (NMT reset node / reset communication)."""
        self.fault = FAULT_NONE
        self._last_raw: bytes | None = None
        self._same_count = 0

    def invalidate(self, index: int | None = None, subindex: int | None = None) -> None:
        """The OD was written: re-read the parameters at the next SYNC."""
        self._cfg = None

    def config(self) -> tuple[float, float, float, int]:
        """(ζ, N_i, full scale, stuck-sample count) of the OD as Python numbers, cached until
        the next :meth:`invalidate` or data store swap (NMT resets)."""
        cfg = self._cfg
        store = self._local.data_store
        if cfg is None or self._cfg_store is not store:
            read = self._objects.read
            cfg = (float(read(*ZETA)), float(read(*NOISE_ESTIMATE)),
                   float(read(*FULL_SCALE)), int(read(*STUCK_SAMPLES)))
            self._cfg = cfg
            self._cfg_store = store
        return cfg

    def check_write(self, index: int, subindex: int, value, startup: bool) -> None:
        """SDO / start-up write to 0x2001 / 0x2002 (the detector configuration)."""
        if (index, subindex) == TAXEL_KIND and value not in KIND_NAMES:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if (index, subindex) == FULL_SCALE and not value > 0:
            # full scale > 0: checked here, not as an EDS LowLimit (a REAL32 limit that
            # objdictgen refuses and canopen drops)
            raise SdoAbortedError(ABORT_VALUE_TOO_LOW)

    def sample(self, reading: float, counter: int | None = None) -> None:
        """X_i of one SYNC (``counter``: its counter byte, None without): fault checks,
        decision (eqs 1-4), OD update."""
        store = self._local.data_store
        cfg = self._cfg
        if cfg is None or self._cfg_store is not store:
            cfg = self.config()
        zeta, noise, full_scale, stuck_after = cfg
        try:
            raw = _REAL32.pack(reading)
        except OverflowError:  # beyond REAL32: the sample is ±inf, as an IEEE conversion rounds it
            reading = math.copysign(math.inf, reading)
            raw = _REAL32.pack(reading)
        if raw == self._last_raw:
            self._same_count += 1
        else:
            self._same_count = 1
        self._last_raw = raw
        status = 0
        if not math.isfinite(reading) or abs(reading) >= full_scale:
            fault = FAULT_OPEN_CIRCUIT
            status = AI_STATUS_NOT_VALID
            if reading >= full_scale:
                status |= AI_STATUS_POSITIVE_OVERLOAD
            elif reading <= -full_scale:
                status |= AI_STATUS_NEGATIVE_OVERLOAD
        elif stuck_after > 0 and self._same_count >= stuck_after:
            fault = FAULT_STUCK
            status = AI_STATUS_NOT_VALID
        else:
            fault = FAULT_NONE
        if fault != self.fault:
            self.fault = fault
            self._on_fault(fault, reading)
        if fault == FAULT_NONE:
            decision = local_decision_pm1(reading, noise, zeta)  # eqs 1-4
        else:
            decision = -1  # faulted: "absent", flagged by 0x6150 and 0x1001
        # straight into the data store, EDS encodings (what NodeObjects.store / encode_raw would write)
        (store.get(LOCAL_DECISION) or store.setdefault(LOCAL_DECISION, {}))[0] = self._u_bytes[decision]
        (store.get(TAGGED_DECISION) or store.setdefault(TAGGED_DECISION, {}))[0] = \
            self._tagged_bytes[decision][counter & TAG_MASK if counter else 0]
        if self._pv_is_real32:
            (store.get(AI_INPUT_PV) or store.setdefault(AI_INPUT_PV, {}))[1] = raw
        else:
            self._objects.store(AI_INPUT_PV, 1, reading)
        status_raw = self._status_bytes.get(status)
        if status_raw is None:
            status_raw = self._status_bytes[status] = self._objects.variable(AI_STATUS, 1).encode_raw(status)
        (store.get(AI_STATUS) or store.setdefault(AI_STATUS, {}))[1] = status_raw
