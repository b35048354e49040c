"""The CiA 402 state machine (node_sim.gripper.cia402) against the CiA 402-2 tables, typed in here
independently of the code: the command coding of the controlword (bit patterns as the profile prints
them), the transition table 0-16, the statusword coding of each state (also checked against
canopen's own BaseNode402 masks), the quick-stop, fault-reaction and abort-connection option codes.
Every controlword bit combination that matters (bits 0-3 and 7, with and without a bit-7 edge) is
tried in every state."""

from __future__ import annotations

import itertools

import pytest
from canopen.profiles.p402 import State402

from node_sim.gripper.cia402 import State, StateMachine

SOD, RTSO, SO, OE = "SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED"
QSA, FRA, FAULT, NRTSO = "QUICK STOP ACTIVE", "FAULT REACTION ACTIVE", "FAULT", "NOT READY TO SWITCH ON"

# CiA 402-2, controlword command coding: bits 7 3 2 1 0 ("r" = 0 -> 1 edge of bit 7)
COMMAND_CODING = {
    "shutdown": "0x110",
    "switch on": "00111",
    "switch on + enable operation": "01111",
    "disable voltage": "0xx0x",
    "quick stop": "0x01x",
    "disable operation": "00111",
    "enable operation": "01111",
    "fault reset": "rxxxx",
}

# CiA 402-2 transitions: (state, command) -> (transitions, next state); anything else: none
TRANSITIONS = {
    (SOD, "shutdown"): ([2], RTSO),
    (RTSO, "switch on"): ([3], SO),
    (RTSO, "switch on + enable operation"): ([3, 4], OE),
    (SO, "enable operation"): ([4], OE),
    (OE, "disable operation"): ([5], SO),
    (SO, "shutdown"): ([6], RTSO),
    (RTSO, "disable voltage"): ([7], SOD),
    (RTSO, "quick stop"): ([7], SOD),
    (OE, "shutdown"): ([8], RTSO),
    (OE, "disable voltage"): ([9], SOD),
    (SO, "disable voltage"): ([10], SOD),
    (SO, "quick stop"): ([10], SOD),
    (OE, "quick stop"): ([11], QSA),          # 0x605A = 2 (the default): stay until the ramp ends
    (QSA, "disable voltage"): ([12], SOD),
    (FAULT, "fault reset"): ([15], SOD),
}
# transition 16 (QUICK STOP ACTIVE -> OPERATION ENABLED, enable operation) only with 0x605A = 5..8

# CiA 402-2 statusword coding, bits 6 5 3 2 1 0 (x: not part of the state) and canopen's names
STATUS_CODING = {
    NRTSO: "0x0000", SOD: "1x0000", RTSO: "010001", SO: "010011", OE: "010111",
    QSA: "000111", FRA: "0x1111", FAULT: "0x1000",
}
STATUS_BITS = (6, 5, 3, 2, 1, 0)


def matches(pattern: str, bits: list[int]) -> bool:
    return all(p in "xr" or int(p) == b for p, b in zip(pattern, bits))


def commands_of(cw: int, edge: bool) -> set[str]:
    """The commands of COMMAND_CODING that controlword ``cw`` matches (``edge``: bit 7 rose)."""
    bits = [(cw >> b) & 1 for b in (7, 3, 2, 1, 0)]
    found = set()
    for name, pattern in COMMAND_CODING.items():
        if pattern[0] == "r":
            if bits[0] and edge:
                found.add(name)
        elif matches(pattern, bits):
            found.add(name)
    return found


def reach(state: str, quick_stop_option: int = 2) -> StateMachine:
    """A machine brought to ``state`` through the transitions the table allows (last controlword
    written with bit 7 = 0)."""
    m = StateMachine(quick_stop_option=quick_stop_option, fault_reaction_option=2)
    m.power_on()
    path = {SOD: [], RTSO: [0x06], SO: [0x06, 0x07], OE: [0x06, 0x07, 0x0F], QSA: [0x06, 0x07, 0x0F, 0x02]}
    if state in path:
        for cw in path[state]:
            m.command(cw)
    elif state == FRA:
        m.fault()
        m.command(0x00)
    elif state == FAULT:
        m.fault()
        m.stop_complete()
        m.command(0x00)
    assert m.state.label == state
    return m


def label(m: StateMachine) -> str:
    return m.state.label


def test_every_controlword_names_exactly_one_command_or_none():
    for cw, edge in itertools.product(range(0x100), (False, True)):
        names = commands_of(cw, edge)
        names -= {"disable operation", "switch on + enable operation"}   # same bits as switch on / enable
        if cw & 0x80:
            assert names == ({"fault reset"} if edge else set())
        else:
            assert len(names) == 1, (hex(cw), names)


@pytest.mark.parametrize("state", [SOD, RTSO, SO, OE, QSA, FRA, FAULT])
def test_transition_table_every_state_every_controlword(state):
    for cw in [b7 << 7 | low for b7 in (0, 1) for low in range(16)]:
        m = reach(state)
        taken = m.command(cw, fault_present=False)
        names = commands_of(cw, edge=bool(cw & 0x80))   # reach() left bit 7 at 0: a set bit 7 is an edge
        expected = [TRANSITIONS[(state, n)] for n in names if (state, n) in TRANSITIONS]
        if expected:
            # "switch on" and "switch on + enable operation" etc. share bits: one row applies
            assert len({tuple(t) for t, _ in expected}) == 1, (state, hex(cw), expected)
            transitions, after = expected[0]
        else:
            transitions, after = [], state
        assert (taken, label(m)) == (transitions, after), (state, hex(cw))


@pytest.mark.parametrize("state", [SOD, RTSO, SO, OE, QSA, FAULT])
def test_bit7_held_is_no_command(state):
    m = reach(state)
    m.command(0x80 | 0x06)            # the edge (a fault reset in FAULT)
    before = label(m)
    for low in range(16):
        assert m.command(0x80 | low) == [] and label(m) == before


def test_power_on_takes_transitions_0_and_1():
    m = StateMachine()
    assert m.state is None and m.statusword() == 0
    assert m.power_on() == [0, 1] and label(m) == SOD


@pytest.mark.parametrize("state", [SOD, RTSO, SO, OE, QSA, FRA, FAULT])
def test_statusword_coding_and_canopen_names(state):
    m = reach(state)
    sw = m.statusword()
    assert matches(STATUS_CODING[state], [(sw >> b) & 1 for b in STATUS_BITS]), (state, hex(sw))
    named = [name for name, (mask, value) in State402.SW_MASK.items() if sw & mask == value]
    assert named == [state]                     # BaseNode402.state reads the same state
    assert sw & 0x0200                          # bit 9 remote: the controlword is obeyed
    assert bool(sw & 0x0010) == (state in (RTSO, SO, OE, QSA, FRA))   # bit 4 voltage enabled


def test_drive_function_only_in_operation_enabled_quick_stop_and_fault_reaction():
    for state in (SOD, RTSO, SO, OE, QSA, FRA, FAULT):
        assert reach(state).drive_enabled == (state in (OE, QSA, FRA))


@pytest.mark.parametrize("option, quick_stop, after_stop, sixteen", [
    (0, [11, 12], [], False),      # disable drive function: through QUICK STOP ACTIVE at once
    (1, [11], [12], False),        # slow-down ramp, then SWITCH ON DISABLED
    (2, [11], [12], False),        # quick-stop ramp, then SWITCH ON DISABLED
    (5, [11], [], True),           # slow-down ramp, stay in QUICK STOP ACTIVE
    (6, [11], [], True),           # quick-stop ramp, stay
])
def test_quick_stop_option_codes(option, quick_stop, after_stop, sixteen):
    m = reach(OE, quick_stop_option=option)
    assert m.command(0x02) == quick_stop
    if option == 0:
        assert label(m) == SOD and m.ramp is None
        return
    assert label(m) == QSA and m.ramp == ("slow_down" if option in (1, 5) else "quick_stop")
    assert m.stop_complete() == after_stop
    assert label(m) == (SOD if after_stop else QSA) and m.ramp is None
    if not after_stop:
        assert m.command(0x0F) == ([16] if sixteen else []) and label(m) == OE


@pytest.mark.parametrize("option", [1, 2])
def test_transition_16_refused_during_and_after_a_ramp_to_switch_on_disabled(option):
    m = reach(OE, quick_stop_option=option)
    m.command(0x02)
    assert m.command(0x0F) == [] and label(m) == QSA


@pytest.mark.parametrize("option", [5, 6])
def test_transition_16_allowed_during_the_ramp(option):
    m = reach(OE, quick_stop_option=option)
    m.command(0x02)
    assert m.command(0x0F) == [16] and label(m) == OE and m.ramp is None


@pytest.mark.parametrize("option", [3, 4, 7, 8, -1, 9])
def test_unsupported_quick_stop_codes_refused(option):
    with pytest.raises(ValueError, match="quick stop option code"):
        StateMachine(quick_stop_option=option)


@pytest.mark.parametrize("state", [NRTSO, SOD, RTSO, SO, OE, QSA])
@pytest.mark.parametrize("option", [0, 1, 2])
def test_fault_from_every_state_and_the_fault_reaction(state, option):
    m = StateMachine(fault_reaction_option=option)
    if state == NRTSO:
        m.state = State.NOT_READY_TO_SWITCH_ON
    else:
        m = reach(state)
        m.fault_reaction_option = option
    if option == 0:
        assert m.fault() == [13, 14] and label(m) == FAULT
    else:
        assert m.fault() == [13] and label(m) == FRA and m.drive_enabled
        assert m.ramp == ("slow_down" if option == 1 else "quick_stop")
        for cw in range(0x100):                           # FAULT REACTION ACTIVE takes no command
            assert m.command(cw) == [] and label(m) == FRA
        assert m.stop_complete() == [14] and label(m) == FAULT
    assert m.fault() == [] and not m.drive_enabled        # no 13 while in FAULT


def test_fault_reset_needs_the_fault_gone_and_a_rising_edge():
    m = reach(FAULT)
    assert m.command(0x80, fault_present=True) == [] and label(m) == FAULT
    assert m.command(0x80, fault_present=False) == [] and label(m) == FAULT   # bit 7 held: no edge
    assert m.command(0x00) == []
    assert m.command(0x80) == [15] and label(m) == SOD


@pytest.mark.parametrize("state, option, transitions, after", [
    (OE, 0, [], OE), (OE, 1, [13], FRA), (OE, 2, [9], SOD), (OE, 3, [11], QSA),
    (SO, 2, [10], SOD), (SO, 3, [10], SOD), (RTSO, 3, [7], SOD), (SOD, 3, [], SOD), (QSA, 2, [12], SOD),
    (FAULT, 1, [], FAULT), (FAULT, 3, [], FAULT),
])
def test_abort_connection_option_codes(state, option, transitions, after):
    m = reach(state)
    assert m.abort_connection(option) == transitions and label(m) == after


def test_unsupported_abort_connection_and_fault_reaction_codes_refused():
    with pytest.raises(ValueError, match="abort connection"):
        reach(OE).abort_connection(4)
    with pytest.raises(ValueError, match="fault reaction"):
        StateMachine(fault_reaction_option=3)
