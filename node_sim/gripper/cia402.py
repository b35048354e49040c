"""The CiA 402 drive state machine (CiA 402-2 / IEC 61800-7-201, "power drive system" FSA), with no CAN.

Controlword 0x6040 in -> state, statusword 0x6041 bits out. Pure: no object dictionary, no bus, no
time; the drive (:mod:`node_sim.gripper.drive`) feeds it controlwords and events and asks it what
its power stage may do. Every method returns the transitions it took (the CiA 402 numbers), so a
test can follow the machine transition by transition.

States and their statusword bits (bits 0-3, 5, 6; ``x`` = not part of the state):

==========================  ===================  ===================================================
state                       statusword           drive function
==========================  ===================  ===================================================
NOT READY TO SWITCH ON      ``x0xx 0000``        off (self-test, left automatically: transition 1)
SWITCH ON DISABLED          ``x1xx 0000``        off
READY TO SWITCH ON          ``x01x 0001``        off
SWITCHED ON                 ``x01x 0011``        off (power stage on, no torque)
OPERATION ENABLED           ``x01x 0111``        on: follows the set-points
QUICK STOP ACTIVE           ``x00x 0111``        on: the quick-stop reaction (0x605A)
FAULT REACTION ACTIVE       ``x0xx 1111``        on: the fault reaction (0x605E)
FAULT                       ``x0xx 1000``        off
==========================  ===================  ===================================================

Commands (controlword bits 7, 3, 2, 1, 0; bit 2 is *quick stop*, active low):

* disable voltage ``0 x x 0 x`` -> transitions 7, 9, 10, 12;
* quick stop ``0 x 0 1 x`` -> 7, 10, 11;
* shutdown ``0 x 1 1 0`` -> 2, 6, 8;
* switch on ``0 0 1 1 1`` -> 3; the same bits are *disable operation* in OPERATION ENABLED -> 5;
* enable operation ``0 1 1 1 1`` -> 4, 16; in READY TO SWITCH ON it is *switch on + enable
  operation*: 3 followed by 4 (CiA 402's automatic transition after SWITCHED ON);
* fault reset: a 0 -> 1 edge of bit 7 -> 15 (in FAULT, once the fault is gone). While bit 7 is 1
  no other command is evaluated.

Automatic transitions: 0 (power on -> NOT READY TO SWITCH ON), 1 (-> SWITCH ON DISABLED after the
self-test), 13 (a fault, from any state but FAULT REACTION ACTIVE / FAULT), 14 (fault reaction
done -> FAULT), 12 (quick stop done with option codes 1 and 2 -> SWITCH ON DISABLED).

Quick stop option code 0x605A (:data:`QUICK_STOP_OPTIONS`): 0 disable the drive function at once
(transitions 11 and 12 together); 1 / 2 stop on the slow-down / quick-stop ramp, then 12;
5 / 6 the same ramps, then stay in QUICK STOP ACTIVE, from where *enable operation* returns to
OPERATION ENABLED (transition 16: only with codes 5-8, CiA 402). Codes 3, 4, 7, 8 (stop on the
current / voltage limit) are not supported.

Fault reaction option code 0x605E (:data:`FAULT_REACTION_OPTIONS`): 0 disable the drive function at
once (13 and 14 together), 1 / 2 the slow-down / quick-stop ramp, then 14.

Abort connection option code 0x6007 (:data:`ABORT_CONNECTION_OPTIONS`, :meth:`StateMachine.abort_connection`):
0 no action, 1 fault (transition 13), 2 the *disable voltage* command, 3 the *quick stop* command.

The ramps themselves are the drive's: while :attr:`StateMachine.ramp` is ``"slow_down"`` or
``"quick_stop"`` the drive ramps its output to zero and then calls :meth:`StateMachine.stop_complete`.
"""

from __future__ import annotations

import enum


class State(enum.Enum):
    """A CiA 402 state; the value is its statusword bits 0-3, 5, 6 (the others 0)."""

    NOT_READY_TO_SWITCH_ON = 0x0000
    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0021
    SWITCHED_ON = 0x0023
    OPERATION_ENABLED = 0x0027
    QUICK_STOP_ACTIVE = 0x0007
    FAULT_REACTION_ACTIVE = 0x000F
    FAULT = 0x0008

    @property
    def label(self) -> str:
        """The name CiA 402 (and canopen's ``BaseNode402.state``) gives it."""
        return self.name.replace("_", " ")


class Command(enum.Enum):
    NONE = "none"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"               # = disable operation in OPERATION ENABLED
    ENABLE_OPERATION = "enable operation"
    FAULT_RESET = "fault reset"


# controlword bits
CW_SWITCH_ON = 0x0001
CW_ENABLE_VOLTAGE = 0x0002
CW_QUICK_STOP = 0x0004            # active low: 0 = quick stop
CW_ENABLE_OPERATION = 0x0008
CW_FAULT_RESET = 0x0080
CW_HALT = 0x0100

# statusword bits beyond the state
SW_VOLTAGE_ENABLED = 0x0010
SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_INTERNAL_LIMIT = 0x0800
SW_STATE_MASK = 0x006F

QUICK_STOP_OPTIONS = {0: "disable drive function", 1: "slow down ramp, then switch on disabled",
                      2: "quick stop ramp, then switch on disabled", 5: "slow down ramp, stay in quick stop active",
                      6: "quick stop ramp, stay in quick stop active"}
FAULT_REACTION_OPTIONS = {0: "disable drive function", 1: "slow down ramp", 2: "quick stop ramp"}
ABORT_CONNECTION_OPTIONS = {0: "no action", 1: "fault", 2: "disable voltage command", 3: "quick stop command"}

_RAMPS = {1: "slow_down", 2: "quick_stop", 5: "slow_down", 6: "quick_stop"}
_POWERED = (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)
_VOLTAGE = (State.READY_TO_SWITCH_ON, State.SWITCHED_ON) + _POWERED


def decode(controlword: int, previous: int = 0) -> Command:
    """The command ``controlword`` gives after ``previous`` (the last one evaluated; bit 7's edge)."""
    if controlword & CW_FAULT_RESET:
        return Command.NONE if previous & CW_FAULT_RESET else Command.FAULT_RESET
    if not controlword & CW_ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not controlword & CW_QUICK_STOP:
        return Command.QUICK_STOP
    if not controlword & CW_SWITCH_ON:
        return Command.SHUTDOWN
    return Command.ENABLE_OPERATION if controlword & CW_ENABLE_OPERATION else Command.SWITCH_ON


class StateMachine:
    """One drive's CiA 402 state machine (see module docstring). Starts before power-on (no state:
    :attr:`state` is None until :meth:`power_on`)."""

    def __init__(self, quick_stop_option: int = 2, fault_reaction_option: int = 2):
        self.state: State | None = None
        self.quick_stop_option = quick_stop_option
        self.fault_reaction_option = fault_reaction_option
        self.ramp: str | None = None      # "slow_down" / "quick_stop": a stop ramp in progress
        self._previous = 0                # the last controlword evaluated (bit 7's edge)

    # -- option codes
    @property
    def quick_stop_option(self) -> int:
        return self._quick_stop_option

    @quick_stop_option.setter
    def quick_stop_option(self, value: int) -> None:
        if value not in QUICK_STOP_OPTIONS:
            raise ValueError(f"quick stop option code {value} not supported (supported: {sorted(QUICK_STOP_OPTIONS)})")
        self._quick_stop_option = value

    @property
    def fault_reaction_option(self) -> int:
        return self._fault_reaction_option

    @fault_reaction_option.setter
    def fault_reaction_option(self, value: int) -> None:
        if value not in FAULT_REACTION_OPTIONS:
            raise ValueError(f"fault reaction option code {value} not supported "
                             f"(supported: {sorted(FAULT_REACTION_OPTIONS)})")
        self._fault_reaction_option = value

    # -- what the power stage may do
    @property
    def drive_enabled(self) -> bool:
        """The drive function is on (torque may be produced): OPERATION ENABLED, QUICK STOP ACTIVE,
        FAULT REACTION ACTIVE."""
        return self.state in _POWERED

    @property
    def follows_set_points(self) -> bool:
        return self.state is State.OPERATION_ENABLED

    def statusword(self) -> int:
        """Bits 0-6 and 9 (remote: the controlword is obeyed) of the statusword."""
        if self.state is None:
            return 0
        return self.state.value | (SW_VOLTAGE_ENABLED if self.state in _VOLTAGE else 0) | SW_REMOTE

    # -- events
    def power_on(self) -> list[int]:
        """Power on / reset application: transitions 0 and 1 (the self-test passes at once)."""
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.ramp = None
        self._previous = 0
        self.state = State.SWITCH_ON_DISABLED
        return [0, 1]

    def command(self, controlword: int, fault_present: bool = False) -> list[int]:
        """Evaluate ``controlword`` (written by the master); ``fault_present``: the cause of a FAULT
        is still there (a fault reset then does nothing)."""
        command = decode(controlword, self._previous)
        self._previous = controlword
        return self.apply(command, fault_present)

    def apply(self, command: Command, fault_present: bool = False) -> list[int]:
        """Carry out ``command`` in the present state (an abort-connection reaction uses this
        without a controlword)."""
        s = self.state
        C, S = Command, State
        if s is S.SWITCH_ON_DISABLED:
            if command is C.SHUTDOWN:
                return self._go(S.READY_TO_SWITCH_ON, 2)
        elif s is S.READY_TO_SWITCH_ON:
            if command is C.SWITCH_ON:
                return self._go(S.SWITCHED_ON, 3)
            if command is C.ENABLE_OPERATION:
                return self._go(S.SWITCHED_ON, 3) + self._go(S.OPERATION_ENABLED, 4)
            if command in (C.DISABLE_VOLTAGE, C.QUICK_STOP):
                return self._go(S.SWITCH_ON_DISABLED, 7)
        elif s is S.SWITCHED_ON:
            if command is C.ENABLE_OPERATION:
                return self._go(S.OPERATION_ENABLED, 4)
            if command is C.SHUTDOWN:
                return self._go(S.READY_TO_SWITCH_ON, 6)
            if command in (C.DISABLE_VOLTAGE, C.QUICK_STOP):
                return self._go(S.SWITCH_ON_DISABLED, 10)
        elif s is S.OPERATION_ENABLED:
            if command is C.SWITCH_ON:
                return self._go(S.SWITCHED_ON, 5)
            if command is C.SHUTDOWN:
                return self._go(S.READY_TO_SWITCH_ON, 8)
            if command is C.DISABLE_VOLTAGE:
                return self._go(S.SWITCH_ON_DISABLED, 9)
            if command is C.QUICK_STOP:
                taken = self._go(S.QUICK_STOP_ACTIVE, 11)
                option = self.quick_stop_option
                if option == 0:
                    return taken + self._go(S.SWITCH_ON_DISABLED, 12)
                self.ramp = _RAMPS[option]
                return taken
        elif s is S.QUICK_STOP_ACTIVE:
            if command is C.DISABLE_VOLTAGE:
                return self._go(S.SWITCH_ON_DISABLED, 12)
            if command is C.ENABLE_OPERATION and self.quick_stop_option >= 5:
                return self._go(S.OPERATION_ENABLED, 16)
        elif s is S.FAULT:
            if command is C.FAULT_RESET and not fault_present:
                return self._go(S.SWITCH_ON_DISABLED, 15)
        return []

    def fault(self) -> list[int]:
        """A fault occurred: transition 13 (and 14 at once with fault reaction option 0)."""
        if self.state in (None, State.FAULT_REACTION_ACTIVE, State.FAULT):
            return []
        taken = self._go(State.FAULT_REACTION_ACTIVE, 13)
        if self.fault_reaction_option == 0:
            return taken + self._go(State.FAULT, 14)
        self.ramp = _RAMPS[self.fault_reaction_option]
        return taken

    def stop_complete(self) -> list[int]:
        """The drive finished the stop ramp: transition 14 (fault reaction) or 12 (quick stop with
        option codes 1, 2); with codes 5, 6 the drive stays in QUICK STOP ACTIVE."""
        if self.ramp is None:
            return []
        self.ramp = None
        if self.state is State.FAULT_REACTION_ACTIVE:
            return self._go(State.FAULT, 14)
        if self.state is State.QUICK_STOP_ACTIVE and self.quick_stop_option in (1, 2):
            return self._go(State.SWITCH_ON_DISABLED, 12)
        return []

    def abort_connection(self, option: int) -> list[int]:
        """The connection to the master is lost (0x6007 = ``option``): no action, fault, the
        disable voltage or the quick stop command."""
        if option not in ABORT_CONNECTION_OPTIONS:
            raise ValueError(f"abort connection option code {option} not supported "
                             f"(supported: {sorted(ABORT_CONNECTION_OPTIONS)})")
        if option == 1:
            return self.fault()
        if option == 2:
            return self.apply(Command.DISABLE_VOLTAGE)
        if option == 3:
            return self.apply(Command.QUICK_STOP)
        return []

    def _go(self, state: State, transition: int) -> list[int]:
        self.state = state
        if state not in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            self.ramp = None
        return [transition]
