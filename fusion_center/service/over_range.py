"""Readings clipped at the limit code of a packed raw patch TPDO, as the nodes report them.

A patch node in raw mode sends X_i as INTEGER8 / INTEGER16 counts (:mod:`taxel_net.patches`); a
reading beyond that range is sent as the limit code, which the centre cannot tell from a
genuine reading. The node reports it as CiA 301 / CiA 404 devices report an analog input over
range: EMCY ``0x3000`` (:data:`taxel_net.patches.EMCY_INPUT_OVER_RANGE`, error register bits 0
and 2, the manufacturer field naming the first taxel over range and its TPDO) on the rising
edge, before the TPDOs of that SYNC, and the error reset ``0x0000`` (bit 2 clear) when every
mapped reading is back in range; its AI status array 0x2033 says which taxels, by SDO
(docs/node-twins.md).

:class:`OverRangeTracker` follows those EMCYs cycle by cycle (a closed cycle's ``emcy``: every
EMCY since the previous one, in bus order): a node is over range from its EMCY 0x3000 until an
EMCY of its own says otherwise (the error register of every EMCY is the node's 0x1001: bit 2
clear, e.g. the error reset), until the centre resets it (NMT reset: its error state starts
afresh), or until it boots by itself (its boot-up message, a closed cycle's ``bootups``: a
node that restarted - a watchdog, a power cycle - starts its error state afresh too, and one
that came back in range would never send the error reset of an EMCY it no longer remembers).
An over-range EMCY of the same cycle after the boot-up flags it again; one before it is
counted, not applied - one stamped the same microsecond as the boot-up counts as before it (the
stream's clock never goes back: a frame stamped earlier takes the last one's time, so an EMCY
then its boot-up can share a stamp, while a node's next over-range EMCY needs an NMT start and a
SYNC after its boot-up). A node that is lost (heartbeat consumer time expired) stays over range:
a node heard again without a boot-up resumes in its NMT state with its error state as it was
(it sends the EMCY 0x3000 on the rising edge only, so it says nothing more while still over
range), and a missing node's records are degraded anyway. A boot-up clears the flag whatever its
stamp, even one stamped before the EMCY 0x3000 that set it: each assembler process of
``run --assemblers`` counts t_us from its own first frame (a node's boot-up that is a process's
first frame is t_us 0 in every process), so stamps of different processes are not comparable;
a duplicate or replayed part never brings an old boot-up here (:mod:`.cycle_merger` carries a
late part's events only when its cycle is newer than its group's last part). A record of a
cycle in which some node is over range lists those nodes in ``over_range_nodes``: its raw-mode
results (the nodes' decisions computed centrally, the centralised tests, the forces) came from
clipped readings.
The EMCYs are counted per node (the run summary's ``over_range``). Pure: a function of the
closed cycles, so a replay gives the same records.
"""

from __future__ import annotations

from collections import Counter

from taxel_net.patches import EMCY_INPUT_OVER_RANGE, ERR_REG_VOLTAGE

from .cycle_records import STATE_RESETTING, ClosedCycle
from .decoder import STATE_BOOTUP

_RESTARTED = (STATE_RESETTING, STATE_BOOTUP)


class OverRangeTracker:
    """Which patch nodes report readings over range (module docstring). ``labels``: the node
    label of every device (``pipeline.node_labels`` order)."""

    def __init__(self, labels: list):
        self.labels = list(labels)
        self.index = {label: i for i, label in enumerate(labels)}
        self.active: set = set()          # node labels over range now
        self.emcy: Counter = Counter()    # node label -> over-range EMCYs (rising edges) heard

    def reset(self) -> None:
        self.active.clear()
        self.emcy.clear()

    def update(self, closed: ClosedCycle) -> list:
        """The cycle's boot-ups and EMCYs applied, restarted nodes forgotten (not lost ones:
        module docstring): the labels of the nodes over range in this cycle (device order)."""
        active = self.active
        booted = None
        if closed.bootups:  # restarted by itself: its error state starts afresh at its boot-up
            booted = {self.labels[d]: t_us for d, t_us in closed.bootups if d < len(self.labels)}
            active.difference_update(booted)
        for e in closed.emcy:
            if e.code == EMCY_INPUT_OVER_RANGE:
                self.emcy[e.node] += 1
            if booted is not None and e.t_us <= booted.get(e.node, -1 << 63):
                continue  # sent before its restart (or at its stamp: below), superseded
            if e.code == EMCY_INPUT_OVER_RANGE:
                active.add(e.node)
            elif not e.register & ERR_REG_VOLTAGE:
                active.discard(e.node)
        if not active:
            return []
        devices = closed.devices
        if devices is not None:
            for label in list(active):
                i = self.index.get(label)
                if i is not None and int(devices.states[i]) in _RESTARTED:
                    active.discard(label)
        index = self.index
        return sorted(active, key=lambda label: index.get(label, len(index)))
