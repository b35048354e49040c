"""The grasp world's mechanics (node_sim.world, issue 22 part 2): hand-worked cases, the timeline,
stick-slip hysteresis, dropped vs placed, crushed, and an independent scipy integration."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from node_sim.world import GraspWorld
from node_sim.world.grasp import Mode, Params, State, advance, first_root
from node_sim.world.timeline import Timeline
from taxel_net.scene_grasp import GraspSpec, PhaseSpec

G = 9.81     # the hand-worked anchors use g = 9.81 m/s²


def airborne(s=0.0, v=0.0, mode=Mode.STICK, z=1.0):
    """An object held 1 m above the table (no landing within the tests' times)."""
    return State(mode=mode, z=z, w=0.0, s=s, v=v)


P = Params(g=G, mu_s=0.5, mu_k=0.4, s_down=0.05, s_up=0.05)


def task(**over):
    base = dict(mass_kg=0.5, mu_s=0.5, mu_k=0.4, size_mm=40.0, gravity_m_s2=G, phases=(
        PhaseSpec("approach", 1.0), PhaseSpec("close", 0.5),
        PhaseSpec("lift", 1.0, height_mm=100.0, accel_m_s2=2.0, speed_m_s=0.2),
        PhaseSpec("hold", 1.0), PhaseSpec("place", 1.0, accel_m_s2=2.0, speed_m_s=0.2),
        PhaseSpec("release", 0.5)))
    base.update(over)
    return GraspSpec(**base)


# ------------------------------------------------------------------ the hand-worked anchors

def test_least_holding_force_hand_worked():
    # m = 0.5 kg, a = 2 m/s², mu_s = 0.5: eq 26b as a condition m (g + a) <= 2 mu_s N, so
    # N_min = m (g + a) / (2 mu_s) = 0.5 * (9.81 + 2) / (2 * 0.5) = 0.5 * 11.81 / 1 = 5.905 N per jaw.
    n_min = 5.905
    world = GraspWorld(task(), step_s=0.01)
    world.start()
    truths = [world.step(10.0) for _ in range(152)]        # approach 1 s + close 0.5 s + 2 lift steps
    lift = [t for t in truths if t.phase == "lift"]
    assert lift and lift[0].min_hold_n == pytest.approx(n_min, abs=1e-12)
    assert truths[50].min_hold_n == 0.0                    # approaching: on the table, nothing to hold
    # the boundary itself: just above it sticks, just below it slips
    for n, mode in ((n_min + 1e-9, Mode.STICK), (n_min - 1e-9, Mode.SLIP)):
        s = airborne()
        advance(s, 0.01, 2.0, n, 0.5, P)
        assert s.mode is mode


def test_slide_at_constant_force_hand_worked():
    # at a constant 5 N per jaw (< 5.905): a_rel = (g + a) - 2 mu_k N / m = 11.81 - 2*0.4*5/0.5
    # = 11.81 - 8 = 3.81 m/s²; from rest in 40 ms: s = 0.5 * 3.81 * 0.04² = 0.5 * 3.81 * 0.0016
    # = 0.003048 m = 3.05 mm (the "3.0 mm"), v = 3.81 * 0.04 = 0.1524 m/s.
    s = airborne()
    fl = advance(s, 0.04, 2.0, 5.0, 0.5, P)
    assert s.mode is Mode.SLIP and fl.slipped and not fl.dropped
    assert s.s == pytest.approx(0.003048, abs=1e-12)
    assert s.v == pytest.approx(0.1524, abs=1e-12)
    # the same in 4 steps of 10 ms: the exact step does not depend on the step size
    s4 = airborne()
    for _ in range(4):
        advance(s4, 0.01, 2.0, 5.0, 0.5, P)
    assert s4.s == pytest.approx(0.003048, abs=1e-12)


def test_slip_to_stick_found_within_the_step():
    # sliding down at v0 = 0.1 m/s, gripper still, N = 10 N: a_rel = 9.81 - 2*0.4*10/0.5 = 9.81 - 16
    # = -6.19 m/s²: it stops after t* = 0.1/6.19 = 16.155 ms having slid v0²/(2*6.19) = 0.01/12.38
    # = 0.80775 mm, and sticks (m g = 4.905 <= 2 mu_s N = 10): one 40 ms step ends exactly there.
    s = airborne(v=0.1, mode=Mode.SLIP)
    advance(s, 0.04, 0.0, 10.0, 0.5, P)
    assert s.mode is Mode.STICK and s.v == 0.0
    assert s.s == pytest.approx(0.01 / 12.38, abs=1e-12)
    # detected a step late it would have gone on: a naive Euler step overshoots into reverse
    assert 0.1 * 0.04 + 0.5 * (-6.19) * 0.04 ** 2 < 0.01 / 12.38


def test_stick_slip_hysteresis():
    # N = 5.5 N with a = 0: 2 mu_k N = 4.4 < m g = 4.905 <= 2 mu_s N = 5.5. A sticking object stays put,
    # a sliding one keeps sliding (a_rel = 9.81 - 8.8 = +1.01 m/s²) - the same force, two outcomes.
    held = airborne()
    sliding = airborne(v=0.01, mode=Mode.SLIP)
    for _ in range(10):
        advance(held, 0.01, 0.0, 5.5, 0.5, P)
        advance(sliding, 0.01, 0.0, 5.5, 0.5, P)
    assert held.mode is Mode.STICK and held.s == 0.0
    assert sliding.mode is Mode.SLIP
    assert sliding.s == pytest.approx(0.01 * 0.1 + 0.5 * 1.01 * 0.1 ** 2, abs=1e-12)
    # it sticks again only once its speed is 0: now v = 0.01 + 1.01 * 0.1 = 0.111 m/s; with N = 7 N,
    # a_rel = 9.81 - 11.2 = -1.39 m/s²: it stops after 0.111 / 1.39 = 79.9 ms and stays stuck (4.905 <= 7)
    advance(sliding, 0.07, 0.0, 7.0, 0.5, P)
    assert sliding.mode is Mode.SLIP
    advance(sliding, 0.03, 0.0, 7.0, 0.5, P)
    assert sliding.mode is Mode.STICK and sliding.v == 0.0


def test_slides_off_the_pads_and_drops():
    # N = 0 while in the air (the drive lets go without opening): free fall relative to the pads,
    # s = g t²/2 reaches s_down = 0.05 m at t = sqrt(2*0.05/9.81) = 0.10096 s
    s = airborne()
    fl = advance(s, 0.1, 0.0, 0.0, 0.5, P)
    assert not fl.dropped and s.mode is Mode.SLIP
    fl = advance(s, 0.01, 0.0, 0.0, 0.5, P)
    assert fl.dropped and s.mode is Mode.DROPPED and s.s == 0.05


def test_first_root():
    assert first_root(1.0, 0.0, -2.0, 10.0) == pytest.approx(1.0)   # 1 - t² = 0
    assert first_root(1.0, 0.0, -2.0, 0.5) is None
    assert first_root(0.0, 1.0, -2.0, 10.0) == pytest.approx(1.0)   # t - t² = 0, the later root
    assert first_root(0.0, -1.0, 0.0, 10.0) is None                 # leaves at once: settle's job
    assert first_root(1.0, 1.0, 2.0, 10.0) is None                   # never comes down
    assert first_root(2.0, -3.0, 2.0, 10.0) == pytest.approx(1.0)   # 2 - 3t + t² = (t-1)(t-2)


# ------------------------------------------------------------------ the timeline

def test_first_root_with_a_subnormal_quadratic_term():
    # c2 = -5e-324 (hypothesis found it in test_against_scipy): 0.5 * c2 underflows to 0 and the
    # second root q / (0.5 c2) divided by zero; the linear root 1 - t = 0 is the answer
    assert first_root(1.0, -1.0, -5e-324, 10.0) == 1.0
    assert first_root(1.0, 1.0, 5e-324, 10.0) is None


def test_timeline_profiles_close_in_form():
    spec = task(phases=(PhaseSpec("approach", 1.0), PhaseSpec("close", 0.5),
                        PhaseSpec("lift", 1.0, height_mm=100.0, accel_m_s2=2.0, speed_m_s=0.2),
                        PhaseSpec("hold", 1.0, shake_m_s2=3.0, shake_hz=5.0, shake_cycles=3, shake_at_s=0.2),
                        PhaseSpec("place", 1.0, height_mm=100.0, accel_m_s2=2.0)))
    tl = Timeline(spec)
    assert tl.phase_starts == {"approach": 0.0, "close": 1.0, "lift": 1.5, "hold": 2.5, "place": 3.5}
    # lift: ramp 0.2/2 = 0.1 s (rises 0.5*2*0.01 = 10 mm), cruise (0.1 - 0.02)/0.2 = 0.4 s, ramp 0.1 s
    ps = list(tl.pieces(1.5, 2.5))
    assert [(round(p.t1 - p.t0, 12), p.a) for p in ps] == [(0.1, 2.0), (0.4, 0.0), (0.1, -2.0), (0.4, 0.0)]
    z, w = ps[2].at(ps[2].t1)
    assert z == pytest.approx(0.1, abs=1e-15) and w == pytest.approx(0.0, abs=1e-15)
    assert ps[3].z0 == 0.1 and ps[3].w0 == 0.0
    # shaking: back at the hold height and at rest after each period
    shake = [p for p in tl.pieces(2.5, 3.5) if p.a != 0]
    assert len(shake) == 9
    z, w = shake[-1].at(shake[-1].t1)
    assert z == pytest.approx(0.1, abs=1e-15) and w == pytest.approx(0.0, abs=1e-15)
    # place without a cruise limit: a triangle, sqrt(0.1/2) = 0.2236 s each way, back at 0
    last = list(tl.pieces(3.5, 4.5))
    assert last[0].a == -2.0 and last[0].t1 - last[0].t0 == pytest.approx(math.sqrt(0.05))
    assert last[-1].z0 == 0.0 and last[-1].phase == "place"
    assert tl.phase_at(4.5) == "done" and list(tl.pieces(4.5, 4.6))[0].phase == "done"


def test_timeline_starts_at_the_start_not_at_creation():
    world = GraspWorld(task(), step_s=0.01)
    idle = [world.step(0.0, jaws_open=True) for _ in range(30)]
    assert {t.phase for t in idle} == {"idle"} and all(t.task_s is None for t in idle)
    world.start()
    t = world.step(0.0, jaws_open=True)
    assert t.phase == "approach" and t.task_s == pytest.approx(0.01) and t.t_s == pytest.approx(0.31)


# ------------------------------------------------------------------ the whole task

def run_task(spec, force, open_at_phase="release", steps=600, step_s=0.01):
    """Close with ``force`` from the close phase on, open the jaws at ``open_at_phase``."""
    world = GraspWorld(spec, step_s)
    world.start()
    out, opened = [], False
    for _ in range(steps):
        phase = world.phase
        opened = opened or phase == open_at_phase
        closed = phase not in ("idle", "approach") and not opened
        out.append(world.step(force if closed else 0.0, jaws_open=not closed))
    return out


def test_placed_and_released_is_not_dropped():
    out = run_task(task(), 10.0)
    assert not any(t.slipping for t in out)
    assert max(t.height_mm for t in out) == pytest.approx(100.0, abs=1e-9)
    end = out[-1]
    assert end.phase == "done" and not end.dropped and end.mode == "table" and end.height_mm == 0.0
    assert end.slid_mm == pytest.approx(0.0, abs=1e-9)


def test_released_in_the_air_is_dropped():
    out = run_task(task(), 10.0, open_at_phase="hold")
    hold = [t for t in out if t.phase == "hold"]
    assert hold[0].dropped and hold[0].mode == "dropped" and out[-1].dropped


def test_lift_fails_when_too_weak():
    # N = 5.5: m (g + a) = 5.905 > 2 mu_s N = 5.5 and 2 mu_k N = 4.4 < m g: the object stays on the table,
    # the pads slide up over it until their lower edge passes its contact (20 + 10 = 30 mm): left, not dropped
    out = run_task(task(), 5.5)
    lift = [t for t in out if t.phase == "lift"]
    assert lift[0].slipping and lift[0].height_mm == 0.0
    assert out[-1].mode == "left" and not out[-1].dropped and out[-1].slid_mm == pytest.approx(30.0)


def test_slips_in_the_lift_then_sticks_again():
    lift_hold = (PhaseSpec("approach", 1.0), PhaseSpec("close", 0.5),
                 PhaseSpec("lift", 1.0, height_mm=100.0, accel_m_s2=2.0, speed_m_s=0.2), PhaseSpec("hold", 1.0))
    # mu_s = 0.5, mu_k = 0.4: from the table either it sticks (N >= 5.905) or kinetic friction cannot
    # lift it (2 mu_k N > m g needs N > 6.13): N = 5.9 is left behind
    assert run_task(task(phases=lift_hold), 5.9, steps=350)[-1].mode == "left"
    # mu_k = 0.48, N = 5.5: 2 mu_k N = 5.28 > m g = 4.905 lifts it, 2 mu_s N = 5.5 < m (g + 2) = 5.905
    # slips: ramp (0.1 s, a = 2): a_rel = 11.81 - 2*0.48*5.5/0.5 = 11.81 - 10.56 = 1.25 m/s², v = 0.125 m/s,
    # s = 0.5*1.25*0.01 = 6.25 mm; cruise (a = 0, 0.4 s): a_rel = 9.81 - 10.56 = -0.75 m/s², it stops after
    # 0.125/0.75 = 0.1667 s (inside the cruise) having slid 0.125²/(2*0.75) = 10.4167 mm more: 16.6667 mm,
    # and sticks (m g = 4.905 <= 5.5); the deceleration ramp (a = -2: 3.905 <= 5.5) and the hold keep it
    out = run_task(task(mu_k=0.48, phases=lift_hold), 5.5, steps=350)
    lift = [t for t in out if t.phase == "lift"]
    assert lift[0].slipping and lift[0].mode == "slip"
    assert lift[9].slid_mm == pytest.approx(6.25, abs=1e-9)
    assert lift[26].slipping and lift[26].mode == "stick" and not lift[27].slipping
    assert out[-1].slid_mm == pytest.approx(6.25 + 0.125 ** 2 / 1.5 * 1000, abs=1e-9)
    assert out[-1].mode == "stick" and out[-1].height_mm == pytest.approx(100.0 - 6.25 - 10.416666666666666)


def test_crushed_latches():
    out = run_task(task(max_force_n=8.0), 10.0)
    assert not out[0].crushed and out[-1].crushed
    assert next(t for t in out if t.crushed).normal_n == 10.0
    assert not run_task(task(max_force_n=12.0), 10.0)[-1].crushed
    assert not run_task(task(), 1000.0)[-1].crushed          # no limit: never crushed


def test_added_load_and_shaking_raise_the_holding_force():
    spec = task(phases=(PhaseSpec("approach", 1.0), PhaseSpec("close", 0.5),
                        PhaseSpec("lift", 1.0, height_mm=100.0, accel_m_s2=2.0, speed_m_s=0.2),
                        PhaseSpec("hold", 2.0, load_kg=0.3, load_at_s=0.5, shake_m_s2=4.0, shake_hz=5.0,
                                  shake_cycles=2, shake_at_s=1.0)))
    out = run_task(spec, 20.0, steps=450)
    hold = [t for t in out if t.phase == "hold"]
    # before the load: m g / (2 mu_s) = 4.905; with 0.3 kg: 0.8 * 9.81 = 7.848; shaking +4 m/s²:
    # 0.8 * 13.81 = 11.048 N
    assert hold[10].min_hold_n == pytest.approx(4.905)
    assert hold[70].min_hold_n == pytest.approx(7.848)
    assert max(t.min_hold_n for t in hold) == pytest.approx(11.048)
    assert not any(t.slipping for t in hold)
    out = run_task(spec, 10.0, steps=450)                     # 10 N < 11.048: slips while shaking
    hold = [t for t in out if t.phase == "hold"]
    assert not any(t.slipping for t in hold[:100]) and any(t.slipping for t in hold[100:])


# ------------------------------------------------------------------ an independent integration

def reference(pieces, m, mu_s, mu_k, g, s_down, s_up):
    """The same model integrated by scipy's solve_ivp with events (airborne object, from sticking)."""
    s, v, mode = 0.0, 0.0, "stick"
    for h, a, n in pieces:
        t = 0.0
        while t < h and mode != "dropped":
            if mode == "stick":
                if abs(m * (g + a)) <= 2 * mu_s * n:
                    break
                mode = "slip"
            d = np.sign(v) if v != 0 else np.sign(g + a)
            acc = (g + a) - d * 2 * mu_k * n / m

            def rhs(_t, y):
                return [y[1], acc]

            def stop(_t, y):
                return y[1]
            stop.terminal, stop.direction = True, -d

            def bottom(_t, y):
                return y[0] - s_down
            bottom.terminal, bottom.direction = True, 1

            def top(_t, y):
                return y[0] + s_up
            top.terminal, top.direction = True, -1

            # max_step: solve_ivp sees an event only as a sign change between its step ends - a
            # slide that reaches s_down and turns back within one long step was not seen dropping
            sol = solve_ivp(rhs, (t, h), [s, v], method="DOP853", rtol=1e-12, atol=1e-15, max_step=1e-3,
                            events=[stop, bottom, top])
            s, v = sol.y[0, -1], sol.y[1, -1]
            t = sol.t[-1]
            if sol.status == 1:
                if sol.t_events[0].size:
                    v = 0.0
                    mode = "stick" if abs(m * (g + a)) <= 2 * mu_s * n else "slip"
                else:
                    mode = "dropped"
    return s, mode


@settings(max_examples=60, deadline=None)
@given(m=st.floats(0.05, 5.0), mu_s=st.floats(0.1, 1.2), frac=st.floats(0.3, 1.0),
       pieces=st.lists(st.tuples(st.floats(0.001, 0.1), st.floats(-15.0, 15.0), st.floats(0.0, 30.0)),
                       min_size=1, max_size=6))
def test_against_scipy(m, mu_s, frac, pieces):
    mu_k = mu_s * frac
    g = 9.81
    for _, a, n in pieces:      # stay clear of the stick boundary, where rounding may decide either way
        assume(abs(abs(m * (g + a)) - 2 * mu_s * n) > 1e-6 * (1 + m * abs(g + a)))
        assume(abs(abs(m * (g + a)) - 2 * mu_k * n) > 1e-6 * (1 + m * abs(g + a)))
    p = Params(g=g, mu_s=mu_s, mu_k=mu_k, s_down=0.05, s_up=0.05)
    st_ = State(mode=Mode.STICK, z=1e6, w=0.0, s=0.0, v=0.0)     # far above the table
    for h, a, n in pieces:
        advance(st_, h, a, n, m, p)
        st_.w = 0.0                                              # the gripper's motion plays no role in the air
    s_ref, mode_ref = reference(pieces, m, mu_s, mu_k, g, 0.05, 0.05)
    assert st_.s == pytest.approx(s_ref, abs=1e-9)
    assert (st_.mode is Mode.DROPPED) == (mode_ref == "dropped")
    if mode_ref != "dropped":
        assert st_.mode.value == mode_ref
