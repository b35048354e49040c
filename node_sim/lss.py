"""LSS slave of the taxel node twin (CiA 305 Layer Setting Services).

The LSS address of a node is its identity object 0x1018 (vendor-ID, product code, revision
number, serial number). The master sends on COB-ID 0x7E5, slaves answer on 0x7E4, always
8 bytes (a request of another length is ignored). The slave's finite state automaton has two
states, *waiting* and *configuration*; what each allows (CiA 305 §4.2, as in
CANopenNode's ``CO_LSSslave.c``):

========================================  =======  =============  ===============================
service (command specifier)               waiting  configuration  answer
========================================  =======  =============  ===============================
switch state global (0x04)                yes      yes            none
switch state selective (0x40-0x43)        yes      no             0x44 when all four match
configure node-ID (0x11)                  no       yes            0x11, error 0 / 1 (not 1..127, 0xFF)
configure bit timing (0x13)               no       yes            0x13, error 0 / 1 (not supported)
activate bit timing (0x15)                no       yes            none
store configuration (0x17)                no       yes            0x17, error 0
inquire vendor/product/revision/serial    no       yes            0x5A-0x5D + the 32-bit number
inquire node-ID (0x5E)                    no       yes            0x5E + the active node-ID
identify remote slave (0x46-0x4B)         yes      yes            0x4F when vendor, product match
                                                                  and revision, serial in range
identify non-configured remote (0x4C)     yes      yes            0x50 if non-configured
LSS Fastscan (0x51)                       yes      no             0x4F, non-configured slaves only
========================================  =======  =============  ===============================

Node-IDs (CiA 305 §5.2): the *active* node-ID is the one the node uses on the bus (0xFF:
non-configured — the node takes part in LSS only: no boot-up, no NMT, no SDO, no PDO);
configure node-ID sets the *pending* one (1..127, or 0xFF to make the node non-configured);
store configuration makes the pending node-ID and bit timing the *stored* ones (the node's
non-volatile memory). The pending node-ID becomes active

* at switch state global to waiting, if the node was non-configured (it then starts: NMT
  reset communication, boot-up under its new node-ID, as CANopenNode does);
* at NMT reset communication (:meth:`LssSlave.on_reset`);
* at NMT reset node (reset application) the stored node-ID becomes pending, then active.

Fastscan (CiA 305 §6.5): a request with BitChecked 0x80 resets every non-configured slave's
scan position to the vendor-ID and all of them answer; otherwise a slave whose position is
LSSSub answers iff its LSS number LSSSub equals IDNumber in bits BitChecked..31, moves to
LSSNext, and with BitChecked 0 and LSSNext < LSSSub (the whole address matched) enters the
configuration state.

Bit timing: the CiA 301 table (index 0 = 1000, 1 = 800, 2 = 500, 3 = 250, 4 = 125, 6 = 50,
7 = 20, 8 = 10 kbit/s; 5 is reserved and 9, automatic detection, is not supported, as in
CANopenNode), limited to the rates the device supports (the EDS's ``BaudRate_*`` entries, as
the rig passes them: 125, 250, 500 and 1000 kbit/s). Activation makes the pending rate the active one (:attr:`LssSlave.bit_rate`)
after the switch delay; the slave answers no LSS request until a second delay has passed.
The twin's python-can bus keeps the rate it was opened with (a virtual bus has none): the
rate is bookkeeping, what a real node would switch to.

:class:`LssSlave` holds one device's LSS state; it outlives the :class:`node_sim.TaxelNode`
that runs under a node-ID (the rig creates a new one when the node-ID changes, as a CANopen
stack re-initialises its communication objects). :func:`answer_all` hands one request to
every slave of a channel.
"""

from __future__ import annotations

import struct
import time
from typing import Callable, Iterable

LSS_MASTER_COB = 0x7E5   # master -> slaves
LSS_SLAVE_COB = 0x7E4    # slave -> master

WAITING = 0x00
CONFIGURATION = 0x01
UNCONFIGURED = 0xFF      # node-ID of a non-configured node

# command specifiers (CiA 305; the names of canopen.lss)
CS_SWITCH_STATE_GLOBAL = 0x04
CS_CONFIGURE_NODE_ID = 0x11
CS_CONFIGURE_BIT_TIMING = 0x13
CS_ACTIVATE_BIT_TIMING = 0x15
CS_STORE_CONFIGURATION = 0x17
CS_SWITCH_STATE_SELECTIVE = range(0x40, 0x44)     # vendor, product, revision, serial
CS_SWITCH_STATE_SELECTIVE_RESPONSE = 0x44
CS_IDENTIFY_REMOTE_SLAVE = range(0x46, 0x4C)      # vendor, product, rev low/high, serial low/high
CS_IDENTIFY_NON_CONFIGURED_REMOTE_SLAVE = 0x4C
CS_IDENTIFY_SLAVE = 0x4F
CS_IDENTIFY_NON_CONFIGURED_SLAVE = 0x50
CS_FAST_SCAN = 0x51
CS_INQUIRE_IDENTITY = range(0x5A, 0x5E)           # vendor, product, revision, serial
CS_INQUIRE_NODE_ID = 0x5E

FASTSCAN_CONFIRM = 0x80  # BitChecked: reset, every non-configured slave answers

# CiA 301 bit timing table: index -> bit/s (5 reserved, 9 automatic detection: not supported)
BIT_TIMING_TABLE = {0: 1_000_000, 1: 800_000, 2: 500_000, 3: 250_000, 4: 125_000,
                    6: 50_000, 7: 20_000, 8: 10_000}

ERROR_NONE = 0
ERROR_OUT_OF_RANGE = 1   # configure node-ID / bit timing: value not supported

_U32 = struct.Struct("<I")


def _answer(cs: int, *payload: int) -> bytes:
    return bytes((cs, *payload)).ljust(8, b"\x00")


class LssSlave:
    """One device's LSS slave (see module docstring).

    ``identity``: (vendor-ID, product code, revision number, serial number), the node's
    0x1018:1-4. ``node_id``: the node-ID it powers on with (active, pending and stored; 0xFF:
    non-configured). ``bit_rate``: the bit rate it powers on with (bit/s); ``bit_rates``: those
    configure bit timing accepts (None: every rate of the table). ``activate(node_id)``
    is called when a non-configured slave gets its node-ID at switch state global (the owner
    starts the node). ``call_later(delay_s, fn)`` schedules the bit-timing switch (None: at
    once). Entry points run with the channel lock held.
    """

    def __init__(self, identity: tuple[int, int, int, int], node_id: int = UNCONFIGURED,
                 bit_rate: int | None = None, *, bit_rates: Iterable[int] | None = None,
                 activate: Callable[[int], None] | None = None,
                 call_later: Callable[[float, Callable[[], None]], object] | None = None):
        if len(identity) != 4:
            raise ValueError("identity: (vendor-ID, product code, revision number, serial number)")
        self.address = tuple(int(v) & 0xFFFFFFFF for v in identity)
        self.active_node_id = self.pending_node_id = self.stored_node_id = int(node_id)
        self.bit_rate = self.pending_bit_rate = self.stored_bit_rate = bit_rate
        self.bit_rates = frozenset(BIT_TIMING_TABLE.values() if bit_rates is None else bit_rates)
        self.state = WAITING
        self._activate = activate
        self._call_later = call_later
        self._selection: list[int | None] = [None] * 4
        self._identify: list[int | None] = [None] * 6
        self._fastscan_sub = 0
        self._quiet_until = 0.0

    # ------------------------------------------------------------------ state
    @property
    def configured(self) -> bool:
        """A valid active node-ID (1..127)."""
        return self.active_node_id != UNCONFIGURED

    @property
    def non_configured(self) -> bool:
        """Takes part in Fastscan and answers "identify non-configured": no node-ID, none pending."""
        return self.active_node_id == UNCONFIGURED and self.pending_node_id == UNCONFIGURED

    @property
    def switching(self) -> bool:
        """Within the two switch delays of an activate bit timing: no LSS answer."""
        return time.monotonic() < self._quiet_until

    def on_reset(self, application: bool) -> int:
        """NMT reset communication (``application`` False) or reset node (True): the stored
        node-ID becomes pending on a reset node, then the pending one active; the automaton
        restarts in the waiting state. Returns the active node-ID."""
        if application:
            self.pending_node_id = self.stored_node_id
        self.active_node_id = self.pending_node_id
        self._restart()
        return self.active_node_id

    def _restart(self) -> None:
        self.state = WAITING
        self._selection = [None] * 4
        self._identify = [None] * 6
        self._fastscan_sub = 0

    # ------------------------------------------------------------------ requests
    def on_request(self, data: bytes) -> bytes | None:
        """One frame of the LSS master (0x7E5); the 8-byte answer (0x7E4) or None."""
        if len(data) != 8 or (self._quiet_until and self.switching):
            return None
        cs = data[0]
        if cs == CS_SWITCH_STATE_GLOBAL:
            self._switch_global(data[1])
            return None
        if cs in CS_IDENTIFY_REMOTE_SLAVE:
            return self._identify_remote(cs - CS_IDENTIFY_REMOTE_SLAVE.start, _U32.unpack_from(data, 1)[0])
        if cs == CS_IDENTIFY_NON_CONFIGURED_REMOTE_SLAVE:
            return _answer(CS_IDENTIFY_NON_CONFIGURED_SLAVE) if self.non_configured else None
        if self.state == WAITING:
            if cs in CS_SWITCH_STATE_SELECTIVE:
                return self._select(cs - CS_SWITCH_STATE_SELECTIVE.start, _U32.unpack_from(data, 1)[0])
            if cs == CS_FAST_SCAN:
                return self._fast_scan(_U32.unpack_from(data, 1)[0], data[5], data[6], data[7])
            return None
        # configuration state
        if cs == CS_CONFIGURE_NODE_ID:
            node_id = data[1]
            if 1 <= node_id <= 127 or node_id == UNCONFIGURED:
                self.pending_node_id = node_id
                return _answer(cs, ERROR_NONE)
            return _answer(cs, ERROR_OUT_OF_RANGE)
        if cs == CS_CONFIGURE_BIT_TIMING:
            selector, index = data[1], data[2]
            if selector == 0 and BIT_TIMING_TABLE.get(index) in self.bit_rates:
                self.pending_bit_rate = BIT_TIMING_TABLE[index]
                return _answer(cs, ERROR_NONE)
            return _answer(cs, ERROR_OUT_OF_RANGE)
        if cs == CS_ACTIVATE_BIT_TIMING:
            self._activate_bit_timing(data[1] | data[2] << 8)
            return None
        if cs == CS_STORE_CONFIGURATION:
            self.stored_node_id = self.pending_node_id
            self.stored_bit_rate = self.pending_bit_rate
            return _answer(cs, ERROR_NONE)
        if cs in CS_INQUIRE_IDENTITY:
            return bytes((cs,)) + _U32.pack(self.address[cs - CS_INQUIRE_IDENTITY.start]) + b"\x00\x00\x00"
        if cs == CS_INQUIRE_NODE_ID:
            return _answer(cs, self.active_node_id)
        return None

    def _switch_global(self, mode: int) -> None:
        if mode == WAITING:
            start = (self.state == CONFIGURATION and self.active_node_id == UNCONFIGURED
                     and self.pending_node_id != UNCONFIGURED)
            self.state = WAITING
            self._selection = [None] * 4
            if start:
                self.active_node_id = self.pending_node_id
                if self._activate is not None:
                    self._activate(self.active_node_id)
        elif mode == CONFIGURATION:
            self.state = CONFIGURATION

    def _select(self, part: int, value: int) -> bytes | None:
        self._selection[part] = value
        if part < 3:
            return None
        selection, self._selection = self._selection, [None] * 4
        if tuple(selection) == self.address:
            self.state = CONFIGURATION
            return _answer(CS_SWITCH_STATE_SELECTIVE_RESPONSE)
        return None

    def _identify_remote(self, part: int, value: int) -> bytes | None:
        self._identify[part] = value
        if part < 5:
            return None
        vendor, product, rev_low, rev_high, serial_low, serial_high = self._identify
        self._identify = [None] * 6
        if None in (vendor, product, rev_low, rev_high, serial_low):
            return None
        a = self.address
        if vendor == a[0] and product == a[1] and rev_low <= a[2] <= rev_high and serial_low <= a[3] <= serial_high:
            return _answer(CS_IDENTIFY_SLAVE)
        return None

    def _fast_scan(self, id_number: int, bit_checked: int, lss_sub: int, lss_next: int) -> bytes | None:
        if not self.non_configured or lss_sub > 3 or lss_next > 3:
            return None
        if bit_checked == FASTSCAN_CONFIRM:
            self._fastscan_sub = 0
            return _answer(CS_IDENTIFY_SLAVE)
        if bit_checked > 31 or self._fastscan_sub != lss_sub:
            return None
        mask = (0xFFFFFFFF << bit_checked) & 0xFFFFFFFF
        if self.address[lss_sub] & mask != id_number & mask:
            return None
        self._fastscan_sub = lss_next
        if bit_checked == 0 and lss_next < lss_sub:
            self.state = CONFIGURATION  # the whole LSS address matched
        return _answer(CS_IDENTIFY_SLAVE)

    def _activate_bit_timing(self, delay_ms: int) -> None:
        delay = delay_ms / 1000.0
        self._quiet_until = time.monotonic() + 2 * delay

        def switch() -> None:
            self.bit_rate = self.pending_bit_rate

        if self._call_later is None or delay == 0:
            switch()
        else:
            self._call_later(delay, switch)


def answer_all(slaves: Iterable[LssSlave], data: bytes) -> list[bytes]:
    """One request of the LSS master to every slave of a channel: their distinct answers, in
    order. Several slaves answering the same 8 bytes at once put one frame on a CAN bus
    (identical frames win the arbitration together and are acknowledged as one), so an answer
    given by several slaves is sent once, as on a real bus."""
    answers: list[bytes] = []
    for slave in slaves:
        answer = slave.on_request(data)
        if answer is not None and answer not in answers:
            answers.append(answer)
    return answers
