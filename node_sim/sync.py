"""SYNC consumer of the taxel node twin (CiA 301).

* COB-ID SYNC 0x1005: the CAN-ID the node consumes SYNC on (default 0x80). The node never
  produces SYNC: a write with bit 30 (generate) or bit 29 (29-bit ID) set is refused with
  SDO abort 0x06090030.
* Synchronous counter overflow value 0x1019: 0 = SYNC without a counter byte (DLC 0), 2..240 =
  SYNC carries a counter 1..value (DLC 1); 1 and 241..255 are refused (0x06090030). The
  channel (:mod:`node_sim.rig`) reads it to check the SYNC length and to count lost SYNCs
  from counter jumps; no overflow value is assumed. (No 0x1006 here, so it may be written in
  any state in which SDO is served.)
* What a SYNC triggers, in any NMT state but INITIALISING and never while the node is
  silent (a dead node): the application samples X_i of that cycle, checks it for sensor
  faults and decides u_i (eqs 1-4, :mod:`node_sim.taxel.detector`); then, in OPERATIONAL only,
  the TPDO engine (:mod:`node_sim.pdo`) runs the synchronous TPDOs (and the change check of
  the event-driven ones) with the SYNC's counter byte.
* The cycle number and counter of the last SYNC consumed.

The rig calls :meth:`SyncConsumer.on_sync` for every node of a channel on each SYNC (the
SYNC hot path): it holds its collaborators' bound methods, so a SYNC costs no lookups
through the node.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from canopen.sdo import SdoAbortedError

from .nmt import INITIALISING, OPERATIONAL, NmtSlave
from .od import COB_29BIT, COB_ID_SYNC, SYNC_OVERFLOW, NodeObjects
from .sdo import ABORT_VALUE_RANGE

if TYPE_CHECKING:
    from .node import TaxelNode

SYNC_GENERATE = 0x40000000    # 0x1005 bit 30: this node would produce SYNC (refused)


class SyncConsumer:
    """One node's SYNC consumer (see module docstring).

    ``sample(reading, counter)`` is the application's per-SYNC step, ``tpdos_on_sync(counter)`` the
    TPDO engine's; ``node`` is asked only whether it is silent.
    """

    def __init__(self, node: "TaxelNode", nmt: NmtSlave, objects: NodeObjects,
                 sample: Callable[[float], None], tpdos_on_sync: Callable[[int | None], None],
                 scalar: bool = True):
        self._node = node
        self._scalar = scalar  # False: the readings are an array (a patch node's taxels), passed as given
        self._nmt = nmt
        self._objects = objects
        self._sample = sample
        self._tpdos_on_sync = tpdos_on_sync
        self.last_cycle: int | None = None
        self.last_counter: int | None = None

    @property
    def cob_id(self) -> int:
        """The 11-bit CAN-ID of SYNC (0x1005 now)."""
        return self._objects.read(COB_ID_SYNC) & 0x7FF

    @property
    def overflow(self) -> int:
        """0x1019 now: the SYNC counter's overflow value (0: SYNC without counter)."""
        return self._objects.read(SYNC_OVERFLOW)

    def check_write(self, index: int, subindex: int, value, startup: bool) -> None:
        """SDO / start-up write to 0x1005 or 0x1019 (see module docstring)."""
        if index == SYNC_OVERFLOW:
            if not (value == 0 or 2 <= value <= 240):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif value & (SYNC_GENERATE | COB_29BIT):
            raise SdoAbortedError(ABORT_VALUE_RANGE)

    def on_sync(self, cycle: int, reading: float, counter: int | None = None) -> None:
        """SYNC ``cycle`` (``counter``: its counter byte, None without): sample ``reading``
        = X_i of that cycle, decide (eqs 1-4), update the OD, run the TPDOs."""
        if self._node.silent:
            return
        state = self._nmt.state
        if state == INITIALISING:
            return
        self.last_cycle = cycle
        self.last_counter = counter
        self._sample(float(reading) if self._scalar else reading, counter)
        if state == OPERATIONAL:
            self._tpdos_on_sync(counter)
