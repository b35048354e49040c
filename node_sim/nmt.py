"""NMT slave of the taxel node twin (CiA 301): the node's NMT state and its transitions.

* power-on / reset: INITIALISING → boot-up frame ``0x700+id [0x00]`` → PRE-OPERATIONAL;
* start (0x01) → OPERATIONAL; stop (0x02) → STOPPED; enter pre-operational (0x80) →
  PRE-OPERATIONAL;
* reset node (0x81): the whole OD back to the start-up values; reset communication (0x82):
  only 0x1000-0x1FFF back; both send a new boot-up and return to PRE-OPERATIONAL;
* unknown command specifiers are ignored; nothing is processed while INITIALISING.

What a state allows is decided by the service concerned, reading :attr:`NmtSlave.state`:
SDO is served in PRE-OPERATIONAL and OPERATIONAL only (:mod:`node_sim.sdo`), EMCY is sent in
the same states (:mod:`.emcy`), TPDOs run in OPERATIONAL only (:mod:`.pdo`), in STOPPED only
NMT and heartbeat (:mod:`.heartbeat`, state byte = :attr:`NmtSlave.state`) are alive.

:class:`NmtSlave` owns the state; what the other services do on a transition is given to it
as hooks by the node that composes them (:class:`node_sim.node.TaxelNode`).
"""

from __future__ import annotations

from typing import Callable

# NMT states (heartbeat state byte, CiA 301)
INITIALISING = 0x00
STOPPED = 0x04
OPERATIONAL = 0x05
PRE_OPERATIONAL = 0x7F
STATE_NAMES = {INITIALISING: "INITIALISING", STOPPED: "STOPPED", OPERATIONAL: "OPERATIONAL",
               PRE_OPERATIONAL: "PRE-OPERATIONAL"}

# NMT command specifiers
NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82

BOOT_UP_BASE = 0x700  # boot-up and heartbeat: 0x700 + node-ID

Hook = Callable[[], None]


def _nothing() -> None:
    pass


class NmtSlave:
    """The NMT state machine of one node (see module docstring).

    ``send(can_id, data)`` sends the boot-up. Hooks (each called with the channel lock held):
    ``before_boot`` (stop the node's timers, forget its TPDO state), ``after_boot`` (now in
    PRE-OPERATIONAL: start the heartbeat), ``enter_operational`` / ``leave_operational``
    (start / stop the TPDOs), ``reset_node`` / ``reset_communication`` (restore the OD before
    the new boot-up).
    """

    def __init__(self, node_id: int, send: Callable[[int, bytes], None], *,
                 before_boot: Hook = _nothing, after_boot: Hook = _nothing,
                 enter_operational: Hook = _nothing, leave_operational: Hook = _nothing,
                 reset_node: Hook = _nothing, reset_communication: Hook = _nothing):
        self.node_id = node_id
        self.state = INITIALISING
        self._send = send
        self._before_boot = before_boot
        self._after_boot = after_boot
        self._enter_operational = enter_operational
        self._leave_operational = leave_operational
        self._reset_node = reset_node
        self._reset_communication = reset_communication

    @property
    def state_name(self) -> str:
        return STATE_NAMES[self.state]

    def boot(self) -> None:
        """INITIALISING → boot-up frame → PRE-OPERATIONAL (power-on and both resets)."""
        self._before_boot()
        self.state = INITIALISING
        self._send(BOOT_UP_BASE + self.node_id, b"\x00")
        self.state = PRE_OPERATIONAL
        self._after_boot()

    def on_command(self, command: int) -> None:
        """An NMT command addressed to this node (or broadcast)."""
        if self.state == INITIALISING:
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
            self._reset_node()
            self.boot()
        elif command == NMT_RESET_COMMUNICATION:
            self._reset_communication()
            self.boot()
        # unknown command specifiers are ignored (CiA 301)
