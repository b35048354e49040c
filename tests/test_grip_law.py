"""The grip-force law (fusion_center.core.grip_law): its safety rules as properties over random
sequences of findings (hypothesis), and its trajectories against closed forms written here from the
rules of the module docstring (not from the code's output)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion_center.core.grip_law import TIME_EPS_S, GripCommand, GripFindings, GripParams, GripState, grip_step
from taxel_net.errors import ParameterError

DT = 0.01


@st.composite
def params(draw):
    min_n = draw(st.floats(0.0, 5.0))
    max_n = draw(st.floats(min_n + 0.1, 200.0))
    grasp_n = draw(st.floats(max(min_n, 0.01), max_n))
    relax = draw(st.floats(0.0, 5.0))
    return GripParams(grasp_n=grasp_n, min_n=min_n, max_n=max_n,
                      raise_fraction=draw(st.floats(0.0, 3.0)), raise_n=draw(st.floats(0.01, 5.0)),
                      settle_s=draw(st.floats(0.0, 0.2)), margin=draw(st.floats(0.0, 1.0)),
                      relax_delay_s=draw(st.floats(0.0, 2.0)), return_delay_s=draw(st.floats(0.0, 1.0)),
                      relax_per_s=relax, return_per_s=draw(st.floats(relax, 20.0)),
                      probe_headroom=draw(st.floats(1.0, 3.0)),
                      safety_factor=draw(st.floats(1.0, 3.0)), mu=draw(st.floats(0.05, 1.5)),
                      open_n=draw(st.floats(0.1, 50.0)), presence_cycles=draw(st.integers(1, 4)))


finding = st.builds(
    GripFindings,
    task=st.sampled_from(("open", "close", "close", "close", "release")),
    present=st.sampled_from((True, True, True, False, None)),
    slip=st.booleans(),
    degraded=st.booleans(),
    least_hold_n=st.one_of(st.none(), st.floats(0.0, 300.0), st.just(float("nan")), st.just(float("inf"))),
    dt_s=st.just(DT),
    actual_n=st.one_of(st.none(), st.floats(0.0, 300.0), st.just(float("nan"))),
    slip_new=st.sampled_from((None, True, False)))


def run(p: GripParams, seq, state: GripState | None = None):
    """The law over ``seq``: [(findings, state before, command, state after), ...]."""
    state = state or GripState()
    out = []
    for f in seq:
        cmd, new = grip_step(p, state, f)
        out.append((f, state, cmd, new))
        state = new
    return out


@settings(max_examples=300, deadline=None)
@given(params(), st.lists(finding, min_size=1, max_size=120))
def test_safety_rules_hold_on_any_sequence(p, seq):
    for f, before, cmd, after in run(p, seq):
        assert isinstance(cmd, GripCommand) and math.isfinite(cmd.force_n)
        # never above max_n; the jaws open (a negative command) only on the task's release
        assert cmd.force_n <= p.max_n + 1e-12
        if f.task == "release":
            assert cmd.force_n == -p.open_n and after.phase == "release"
        else:
            assert cmd.force_n >= 0.0
        assert after.command_n == (cmd.force_n if f.task != "release" else after.command_n)
        holding = before.phase in ("grasp", "hold") and f.task == "close"
        if holding:
            # held: never lower on a degraded, absent or undecided cycle; never below min_n
            if f.degraded or not f.present:
                assert cmd.force_n >= min(before.command_n, p.max_n)
            assert cmd.force_n >= min(p.min_n, p.max_n) - 1e-12
            # a slip never lowers the command; an episode's first raises it, and a later one whose
            # last raise has settled raises it on new evidence only (not on a flag held from before)
            if f.slip:
                assert cmd.force_n >= min(before.command_n, p.max_n)
                onset = math.isinf(before.since_raise_s) or before.quiet_s >= p.return_delay_s - TIME_EPS_S
                first = onset or not before.episode_raised          # the episode's first raise is still to come
                settled = before.raise_pending_n == 0 and before.since_raise_s + f.dt_s >= p.settle_s - TIME_EPS_S
                if settled and (first or f.slip_new is not False):
                    want = max(before.command_n * (1 + p.raise_fraction), before.command_n + p.raise_n)
                    assert cmd.force_n >= min(want, p.max_n) - 1e-9
                    assert "slip_raise" in cmd.flags and after.episode_raised
                if f.slip_new is False and not first:
                    assert "slip_raise" not in cmd.flags
                # no raise while the last one is on its way: the drive's force still rising toward it
                a = f.actual_n
                if (before.raise_pending_n > 0 and a is not None and math.isfinite(a) and before.actual_n is not None
                        and before.actual_n < a < 0.95 * before.raise_pending_n):
                    assert "slip_raise" not in cmd.flags and after.raise_pending_n == before.raise_pending_n
            else:
                # the fall per cycle is bounded: at most return_per_s of the command per second
                assert cmd.force_n >= before.command_n * (1 - p.return_per_s * f.dt_s) - 1e-9
                if before.learned_n == 0:
                    assert cmd.force_n >= before.command_n * (1 - p.relax_per_s * f.dt_s) - 1e-9
                    if f.least_hold_n is None and before.command_n * p.probe_headroom > p.max_n:
                        assert cmd.force_n >= before.command_n                 # no probe near max_n
            # raw mode: at least the safety factor times eq 26a's bound (capped by max_n)
            least = f.least_hold_n
            if least is not None and math.isfinite(least) and least > 0:
                assert cmd.force_n >= min(p.safety_factor * least, p.max_n) - 1e-9
            # decision mode: a learned floor is kept (capped by max_n) and never falls; raw mode's
            # gives way only to the measured target, and by at most relax_per_s dt of itself
            raw = least is not None and math.isfinite(least) and least > 0
            if not raw:
                assert after.learned_n >= before.learned_n
                if not f.slip:
                    assert cmd.force_n >= min(before.learned_n, p.max_n) - 1e-9
            else:
                assert after.learned_n >= min(before.learned_n, max(p.min_n, p.safety_factor * least)) - 1e-9
                assert after.learned_n >= before.learned_n * (1 - p.relax_per_s * f.dt_s) - 1e-9
        if before.phase == "open" and f.task != "release":
            grasped = f.task == "close" and after.present_run >= p.presence_cycles
            assert (cmd.force_n > 0) == grasped
            assert after.phase == ("grasp" if grasped else "open")


@settings(max_examples=200, deadline=None)
@given(params(), st.lists(finding, min_size=1, max_size=60))
def test_pure_and_deterministic(p, seq):
    a = [(c, s) for _, _, c, s in run(p, seq)]
    b = [(c, s) for _, _, c, s in run(p, seq)]
    assert a == b


@settings(max_examples=200, deadline=None)
@given(params(), st.integers(1, 200))
def test_held_object_is_never_let_go_without_release(p, cycles):
    """Whatever the findings say while the task is close (absent, degraded, no slip for ever), a
    grasped object keeps a positive command."""
    state = GripState(phase="hold", command_n=p.max_n)
    for k in range(cycles):
        f = GripFindings(task="close", present=(None, False, True)[k % 3], slip=False, degraded=k % 5 == 0)
        cmd, state = grip_step(p, state, f)
        assert cmd.force_n >= min(p.min_n, p.max_n)
        assert cmd.force_n > 0 or p.min_n == 0


# ------------------------------------------------------------------ closed forms

P = GripParams(grasp_n=10.0, min_n=1.0, max_n=40.0, raise_fraction=1.0, raise_n=0.5, settle_s=0.06, margin=0.2,
               relax_delay_s=1.0, return_delay_s=0.2, relax_per_s=0.5, probe_headroom=1.7, return_per_s=3.0,
               safety_factor=1.2, mu=0.5, open_n=10.0, presence_cycles=2)


def close(present=True, slip=False, least=None, degraded=False):
    return GripFindings(task="close", present=present, slip=slip, degraded=degraded, least_hold_n=least, dt_s=DT)


def test_grasp_on_presence_then_probe_down_geometrically():
    """Decision mode, no slip: open until presence_cycles H1 in a row, then grasp_n; held for
    relax_delay_s (100 cycles after the grasp), then each cycle x (1 - relax_per_s dt): after n
    more cycles grasp_n (1 - 0.005)^n, never below min_n."""
    state = GripState()
    cmd, state = grip_step(P, state, close(present=True))
    assert cmd.force_n == 0.0 and state.phase == "open"
    cmd, state = grip_step(P, state, close(present=None))          # undecided breaks the run
    assert cmd.force_n == 0.0
    cmd, state = grip_step(P, state, close(present=True))
    cmd, state = grip_step(P, state, close(present=True))
    assert cmd.force_n == 10.0 and state.phase == "grasp" and cmd.flags == ("grasp",)
    forces = []
    for _ in range(300):
        cmd, state = grip_step(P, state, close())
        forces.append(cmd.force_n)
    assert state.phase == "hold"
    # quiet_s reaches relax_delay_s (1.0 s) at the 100th cycle after the grasp
    assert forces[:99] == [10.0] * 99
    for n in range(99, 300):
        assert forces[n] == pytest.approx(10.0 * (1 - 0.5 * DT) ** (n - 98), rel=1e-12)
    state = replace(state, command_n=1.001)
    cmd, state = grip_step(P, state, close())
    assert cmd.force_n == 1.0                                       # min_n


def test_no_probe_where_a_slip_could_not_be_stopped_below_max_n():
    """max_n 15 N, probe_headroom 1.7: from 10 N no probe (1.7 x 10 > 15); from 8.5 N it probes
    (1.7 x 8.5 = 14.45 <= 15)."""
    p = replace(P, max_n=15.0)
    for start, probes in ((10.0, False), (8.5, True)):
        state = GripState(phase="hold", command_n=start, quiet_s=5.0)
        cmd, _ = grip_step(p, state, close())
        assert (cmd.force_n < start) == probes
        if probes:
            assert cmd.force_n == pytest.approx(start * (1 - 0.5 * DT))


def test_slip_raises_once_per_settle_teaches_the_floor_and_returns_to_it():
    """A slip at 8 N: the floor 1.2 x 8 = 9.6 N, the command 2 x 8 = 16 N; slipping cycles within
    settle_s (60 ms) do not raise again, the 6th one does (32 N); return_delay_s (0.2 s: 20
    cycles) after the last slip the command falls by 3 % a cycle down to the floor and stays."""
    state = GripState(phase="hold", command_n=8.0, quiet_s=5.0)
    cmd, state = grip_step(P, state, close(slip=True))
    assert cmd.force_n == 16.0 and state.learned_n == pytest.approx(9.6) and "slip_onset" in cmd.flags
    for k in range(1, 6):                                             # 10..50 ms after the raise
        cmd, state = grip_step(P, state, close(slip=True))
        assert cmd.force_n == 16.0 and "slip_raise" not in cmd.flags
    cmd, state = grip_step(P, state, close(slip=True))                # 60 ms: raise again
    assert cmd.force_n == 32.0 and state.learned_n == pytest.approx(9.6)
    cmd, state = grip_step(P, state, close())
    assert "stuck" in cmd.flags
    forces = [cmd.force_n]
    for _ in range(200):
        cmd, state = grip_step(P, state, close())
        forces.append(cmd.force_n)
    # quiet_s >= 0.2 s from the 20th quiet cycle on (index 19 of forces)
    assert forces[:19] == [32.0] * 19
    expected = 32.0
    for f in forces[19:]:
        expected = max(9.6, expected * (1 - 3.0 * DT))
        assert f == pytest.approx(expected, rel=1e-12)
    assert forces[-1] == pytest.approx(9.6)


def _raises_after(state, actuals):
    """The cycles (1, 2, ...) after ``state`` whose slipping findings, with the drive's force
    ``actuals[k - 1]`` (None: not known), raise the command; and the raised commands."""
    out = []
    for k, actual in enumerate(actuals, 1):
        cmd, state = grip_step(P, state, replace(close(slip=True), actual_n=actual))
        if "slip_raise" in cmd.flags:
            out.append((k, cmd.force_n))
    return out


def test_a_raise_settles_from_when_the_drive_delivered_it():
    """With the drive's force known (findings.actual_n), settle_s counts from the cycle the force
    reached 95 % of the raise (or stopped rising: the drive delivers no more), not from the send: a
    slip at 8 N raises to 16 N; the drive (5 N a cycle from the next SYNC) shows 13 N, then 16 N
    (arrived, cycle 2); slipping cycles go on: the next raise is 60 ms after the arrival (cycle 8),
    where without the drive's force it came 60 ms after the send (cycle 6)."""
    start = GripState(phase="hold", command_n=8.0, quiet_s=5.0, actual_n=8.0)
    cmd, state = grip_step(P, start, replace(close(slip=True), actual_n=8.0))
    assert cmd.force_n == 16.0 and "slip_raise" in cmd.flags and state.raise_pending_n == 16.0
    assert _raises_after(state, [13.0, 16.0] + [16.0] * 7)[0] == (8, 32.0)
    # 15.2 N is 95 % of 16 N: arrived at cycle 2 as well
    assert _raises_after(state, [13.0, 15.2] + [15.2] * 7)[0] == (8, 32.0)
    # a drive that delivers no more (at its torque limit, 12 N from cycle 1 on): settled from cycle 2,
    # the first that shows no rise
    assert _raises_after(state, [12.0] * 9)[0] == (8, 32.0)
    # still rising toward it (the slope-limited ramp of a large raise): no second raise meanwhile
    assert _raises_after(state, [8.5 + 0.5 * k for k in range(1, 14)]) == []
    # without the drive's force: 60 ms after the send, as before
    cmd, state = grip_step(P, replace(start, actual_n=None), close(slip=True))
    assert state.raise_pending_n == 0.0
    assert _raises_after(state, [None] * 9)[0] == (6, 32.0)


def test_after_an_episodes_first_raise_only_new_evidence_raises_again():
    """A slip at 8 N raises to 16 N (the episode's first raise: taken whether the flag is new or
    held). Past the settle (60 ms) flags the caller holds from before (slip_new False: the motion
    they stood for was seen while the raise was arriving) raise nothing; the first new one does
    (32 N); a caller that cannot tell (None) raises as before."""
    start = GripState(phase="hold", command_n=8.0, quiet_s=5.0)
    cmd, state = grip_step(P, start, replace(close(slip=True), slip_new=False))
    assert cmd.force_n == 16.0 and "slip_raise" in cmd.flags and "slip_onset" in cmd.flags
    for _ in range(10):                                                  # 10..100 ms: held flags only
        cmd, state = grip_step(P, state, replace(close(slip=True), slip_new=False))
        assert cmd.force_n == 16.0 and "slip_raise" not in cmd.flags
    cmd, state = grip_step(P, state, replace(close(slip=True), slip_new=True))
    assert cmd.force_n == 32.0 and "slip_raise" in cmd.flags
    unknown = grip_step(P, start, close(slip=True))[1]
    for k in range(1, 7):
        cmd, unknown = grip_step(P, unknown, close(slip=True))
    assert cmd.force_n == 32.0 and "slip_raise" in cmd.flags           # 60 ms after the first: as before


def test_an_episodes_first_raise_deferred_at_its_onset_needs_no_new_evidence():
    """The exemption is the episode's first raise, not its onset cycle: with settle_s (0.25 s)
    longer than return_delay_s (0.2 s), a new episode can begin while the last raise is still
    settling - its onset cycle raises nothing; its first raise comes once settled, on a held
    flag too (slip_new False); the raise after that needs new evidence again."""
    p = replace(P, settle_s=0.25)
    cmd, state = grip_step(p, GripState(phase="hold", command_n=8.0, quiet_s=5.0), close(slip=True))
    assert cmd.force_n == 16.0 and state.episode_raised
    for _ in range(21):                                                   # 0.21 s quiet: the next slip is an onset
        cmd, state = grip_step(p, state, close())
    cmd, state = grip_step(p, state, replace(close(slip=True), slip_new=True))
    assert "slip_onset" in cmd.flags and "slip_raise" not in cmd.flags and not state.episode_raised  # 0.22 s < settle
    onset_n = cmd.force_n                 # the onset's floor, 1.2 x the command it began under
    raised = []
    for k in range(1, 12):
        cmd, state = grip_step(p, state, replace(close(slip=True), slip_new=False))
        if "slip_raise" in cmd.flags:
            raised.append((k, cmd.force_n))
    assert raised == [(3, pytest.approx(2 * onset_n))]   # 0.25 s after the last raise, on held flags: the first


def test_slip_raise_is_capped_at_max_n():
    state = GripState(phase="hold", command_n=30.0, quiet_s=5.0)
    cmd, state = grip_step(P, state, close(slip=True))
    assert cmd.force_n == 40.0 and "at_max" in cmd.flags
    assert state.learned_n == pytest.approx(36.0)


def test_small_commands_raise_by_raise_n():
    p = replace(P, raise_fraction=0.1, raise_n=2.0)
    cmd, _ = grip_step(p, GripState(phase="hold", command_n=5.0, quiet_s=5.0), close(slip=True))
    assert cmd.force_n == 7.0                                         # max(5.5, 7.0)


def test_raw_mode_rises_to_the_target_at_once_and_follows_it_down_slowly():
    """Raw mode: eq 26a per jaw T / mu = least; the target 1.2 least. Below it the command rises at
    once; above it, relax_delay_s after the grasp, it falls by relax_per_s (0.5 %/cycle) to it; while
    the pads carry nothing (least 0: the object on the table) it holds."""
    state = GripState(phase="hold", command_n=5.0)
    cmd, state = grip_step(P, state, close(least=10.0))
    assert cmd.force_n == pytest.approx(12.0)
    state = GripState(phase="hold", command_n=20.0, quiet_s=2.0)
    cmd, state = grip_step(P, state, close(least=0.0))
    assert cmd.force_n == 20.0                                        # nothing carried: hold
    for bad in (float("inf"), float("nan")):                          # no number: hold, floor kept
        c2, s2 = grip_step(P, replace(state, learned_n=15.0), close(least=bad))
        assert c2.force_n == 20.0 and s2.learned_n == 15.0
    forces = []
    for _ in range(200):
        cmd, state = grip_step(P, state, close(least=10.0))
        forces.append(cmd.force_n)
    expected = 20.0
    for f in forces:
        expected = max(12.0, expected * (1 - 0.5 * DT))
        assert f == pytest.approx(expected, rel=1e-12)


def test_raw_mode_forgets_a_slip_floor_for_the_measured_target():
    """Raw mode: a slip at 8 N teaches 9.6 N; the load measured afterwards needs 1.2 x 5 = 6 N. After
    return_delay_s the command returns to the floor (6 %/cycle), and relax_delay_s after the slip
    the floor itself gives way by 0.5 %/cycle down to the target; decision mode keeps it."""
    state = GripState(phase="hold", command_n=8.0, quiet_s=5.0)
    _, state = grip_step(P, state, close(slip=True, least=5.0))
    assert state.learned_n == pytest.approx(9.6)
    raw, dec = state, state
    floors_raw, floors_dec = [], []
    for _ in range(400):
        c_raw, raw = grip_step(P, raw, close(least=5.0))
        c_dec, dec = grip_step(P, dec, close())
        floors_raw.append(raw.learned_n)
        floors_dec.append(dec.learned_n)
    assert floors_dec == [pytest.approx(9.6)] * 400 and c_dec.force_n == pytest.approx(9.6)
    # quiet_s reaches relax_delay_s (1 s) at the 100th quiet cycle (index 99)
    assert floors_raw[:98] == [pytest.approx(9.6)] * 98
    expected = 9.6
    for f in floors_raw[99:]:
        expected = max(6.0, expected * (1 - 0.5 * DT))
        assert f == pytest.approx(expected, rel=1e-9)
    assert c_raw.force_n == pytest.approx(max(6.0, expected), rel=1e-9)


def test_degraded_and_absent_cycles_hold_the_command():
    state = GripState(phase="hold", command_n=20.0, quiet_s=10.0, learned_n=5.0)
    cmd, s2 = grip_step(P, state, close(degraded=True))
    assert cmd.force_n == 20.0 and "held_degraded" in cmd.flags
    cmd, s2 = grip_step(P, state, close(present=False))
    assert cmd.force_n == 20.0 and "absent_while_held" in cmd.flags
    cmd, s2 = grip_step(P, state, close(present=None))
    assert cmd.force_n == 20.0
    cmd, s2 = grip_step(P, state, close())
    assert cmd.force_n == pytest.approx(20.0 * (1 - 3.0 * DT))
    # a degraded cycle still raises on slip and still rises to raw mode's target
    cmd, _ = grip_step(P, state, close(degraded=True, slip=True))
    assert cmd.force_n == 40.0
    cmd, _ = grip_step(P, state, close(degraded=True, least=30.0))
    assert cmd.force_n == pytest.approx(36.0)


def test_release_opens_then_waits_open():
    state = GripState(phase="hold", command_n=20.0)
    cmd, state = grip_step(P, state, GripFindings(task="release", present=True, slip=True))
    assert cmd.force_n == -10.0 and state.phase == "release"
    cmd, state = grip_step(P, state, GripFindings(task="close", present=True, slip=False))
    assert cmd.force_n == 0.0 and state.phase == "open"


def test_bad_findings_are_refused():
    with pytest.raises(ParameterError, match="task"):
        grip_step(P, GripState(), GripFindings(task="lift", present=True, slip=False))
    for dt in (0.0, -0.01, float("nan"), float("inf"), True):
        with pytest.raises(ParameterError, match="dt_s"):
            grip_step(P, GripState(), GripFindings(task="close", present=True, slip=False, dt_s=dt))


@pytest.mark.parametrize("field, value, words", [
    ("max_n", 0.0, "> 0"), ("mu", -1.0, "> 0"), ("open_n", 0.0, "> 0"), ("min_n", -0.1, ">= 0"),
    ("settle_s", -1.0, ">= 0"), ("margin", float("nan"), "finite"), ("grasp_n", 500.0, "[min_n, max_n]"),
    ("safety_factor", 0.99, ">= 1"), ("grasp_n", 0.0, "> 0"), ("presence_cycles", 0, "integer >= 1"), ("presence_cycles", 1.5, "integer"),
    ("return_per_s", 0.1, "relax_per_s"), ("probe_headroom", 0.9, ">= 1"), ("raise_fraction", True, "finite number"),
])
def test_bad_params_name_the_field(field, value, words):
    with pytest.raises(ParameterError) as info:
        replace(P, **{field: value})
    assert info.value.name == field and words in info.value.allowed
