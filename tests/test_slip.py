"""Slip model (fusion_center.core.slip) on synthetic traces with known onset, speed and distance."""

import dataclasses

import numpy as np
import pytest

from taxel_net.errors import ParameterError
from fusion_center.core.geometry import active_centroid
from fusion_center.core.slip import SlipTracker, detect_slip, line_fit_velocity

PERIOD = 0.01  # s per SYNC cycle


def synthetic_trace(rng, *, n=120, onset=50, velocity=(0.6, 0.2), pitch=2.0, radius=7.0,
                    dropout=0.05, mu=0.3, grip=10.0, force_noise=0.0, force_step=0.06):
    """Object footprint on a taxel grid; static until `onset`, then moving at `velocity`/cycle.

    Tangential force ramps so that the true ratio F_t / (mu F_g) crosses 1 exactly at `onset`.
    Returns times, per-cycle active taxel coordinates, tangential, grip and the true centres.
    """
    gx, gy = np.meshgrid(np.arange(0, 80.1, pitch), np.arange(0, 80.1, pitch))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    times = np.arange(n) * PERIOD
    k = np.arange(n)
    centres = np.array([20.0, 30.0]) + np.outer(np.clip(k - onset, 0, None), velocity)
    active = []
    for c in centres:
        inside = grid[np.hypot(*(grid - c).T) <= radius]
        keep = rng.random(len(inside)) >= dropout
        active.append(inside[keep])
    ratio = 1.0 + force_step * (k - onset + 0.5)          # > 1 from `onset` on
    tangential = np.clip(ratio * mu * grip + rng.normal(0, force_noise, n), 0, None)
    grip_force = np.full(n, grip)
    return times, active, tangential, grip_force, centres


def centroids_of(active):
    return np.array([active_centroid(a) for a in active])


def test_force_criterion_flags_exact_onset_and_estimates_motion():
    rng = np.random.default_rng(1)
    v = np.array([0.6, 0.2])
    times, active, ft, fg, centres = synthetic_trace(rng, velocity=tuple(v))
    res = detect_slip(times, centroids_of(active), ft, fg, 0.3, noise_band=1.5)
    assert res.slipping and res.criterion == "force"
    assert res.onset_index == 50 and res.flagged_index == 50
    assert res.onset_time == pytest.approx(0.5)
    # 70 cycles of slip at 0.6325 units/cycle: true distance = 44.27
    true_speed = np.hypot(*v)
    np.testing.assert_allclose(res.velocity_per_cycle, v, atol=0.03)
    np.testing.assert_allclose(res.velocity, v / PERIOD, atol=3.0)
    assert res.speed == pytest.approx(true_speed / PERIOD, rel=0.05)
    assert res.distance == pytest.approx(true_speed * 69, rel=0.05)


def test_motion_criterion_without_forces():
    rng = np.random.default_rng(2)
    times, active, _, _, _ = synthetic_trace(rng, velocity=(1.0, 0.0))
    res = detect_slip(times, centroids_of(active), None, None, 0.3, noise_band=1.5,
                      motion_consecutive=2)
    assert res.slipping and res.criterion == "motion"
    # centre leaves the 1.5 band after 2 cycles at 1 unit/cycle; quantisation adds at most a pitch
    assert 50 <= res.onset_index <= 53
    assert res.flagged_index == res.onset_index + 1
    assert res.velocity_per_cycle[0] == pytest.approx(1.0, abs=0.05)


def test_static_grasp_with_dropouts_is_not_slip():
    rng = np.random.default_rng(3)
    times, active, ft, fg, _ = synthetic_trace(rng, onset=10_000, n=200, dropout=0.1)
    res = detect_slip(times, centroids_of(active), ft, fg, 0.3, noise_band=1.5)
    assert not res.slipping and res.onset_index is None
    assert res.speed == 0.0 and res.distance == 0.0
    assert np.nanmax(res.force_ratio) < 1.0
    assert np.nanmax(res.displacement) < 1.5


def test_tracker_matches_batch_on_random_traces():
    rng = np.random.default_rng(4)
    for trial in range(6):
        onset = int(rng.integers(10, 60))
        vel = tuple(rng.uniform(-0.2, 0.2, 2))  # stays on the grid: one contact episode
        times, active, ft, fg, _ = synthetic_trace(rng, n=90, onset=onset, velocity=vel,
                                                   force_noise=0.05)
        use_forces = trial % 2 == 0
        tracker = SlipTracker(0.3, 1.5, period=PERIOD, fit_window=15)
        for t, a, f, g in zip(times, active, ft, fg):
            state = tracker.update(t, a, f if use_forces else None, g if use_forces else None)
        res = detect_slip(times, centroids_of(active), ft if use_forces else None,
                          fg if use_forces else None, 0.3, noise_band=1.5, fit_window=15, period=PERIOD)
        assert state.slipping == res.slipping
        if res.slipping:
            assert (state.onset_index, state.flagged_index, state.criterion) == \
                (res.onset_index, res.flagged_index, res.criterion)
            np.testing.assert_allclose(state.velocity, res.velocity, rtol=1e-9, atol=1e-9)
            assert state.distance == pytest.approx(res.distance, rel=1e-9, abs=1e-12)


def test_tracker_resets_on_contact_loss():
    tracker = SlipTracker(0.3, 0.5, reference_cycles=1, motion_consecutive=1)
    assert not tracker.update(0.0, [(0, 0)]).slipping
    s = tracker.update(1.0, [(2, 0)])
    assert s.slipping and s.criterion == "motion" and s.onset_index == 1
    s = tracker.update(2.0, [(4, 0)])
    np.testing.assert_allclose(s.velocity, [2.0, 0.0])      # 2 units per time unit
    assert s.distance == pytest.approx(2.0)
    lost = tracker.update(3.0, [])
    assert not lost.contact and not lost.slipping
    again = tracker.update(4.0, [(50, 50)])
    assert not again.slipping and again.displacement is None


def test_force_ratio_edge_cases_and_bad_input():
    tracker = SlipTracker(0.5, 1.0)
    s = tracker.update(0.0, [(0, 0)], 1.0, 0.0)             # no grip at all: slips
    assert s.force_ratio == float("inf") and s.slipping and s.criterion == "force"
    with pytest.raises(ParameterError, match="t"):
        tracker.update(0.0, [(0, 0)], 1.0, 1.0)               # time not increasing
    with pytest.raises(ParameterError):
        tracker.update(1.0, [(0, 0)], 1.0, None)
    with pytest.raises(ParameterError, match="mu"):
        SlipTracker(0.0, 1.0)
    with pytest.raises(ParameterError, match="noise_band"):
        SlipTracker(0.3, -1.0)
    with pytest.raises(ParameterError, match="times"):
        detect_slip([0.0, 0.0], np.zeros((2, 2)), None, None, 0.3, noise_band=1.0)
    with pytest.raises(ParameterError, match="centroids"):
        detect_slip([0.0, 1.0], np.zeros((3, 2)), None, None, 0.3, noise_band=1.0)


def test_line_fit_velocity_exact_on_a_line():
    t = np.array([0.0, 0.5, 1.0, 2.0])
    p = np.column_stack([3 + 2 * t, -1 - 0.5 * t])
    np.testing.assert_allclose(line_fit_velocity(t, p), [2.0, -0.5])
    np.testing.assert_array_equal(line_fit_velocity([1.0], [[1.0, 2.0]]), [0.0, 0.0])


def test_exact_track_known_onset_speed_and_distance():
    # noise-free centroid (no taxel grid): still at (5, 5) up to cycle 10, then 0.3 / -0.4 units
    # per 0.02 s cycle (0.5 per cycle, 25 per s) until cycle 39; contact lost at 40-41, a new
    # static grasp from 42 on. Forces: 4 during 10-39, else 2, against mu F_g = 0.3 x 10 = 3.
    dt, n = 0.02, 50
    k = np.arange(n)
    times = k * dt
    steps = np.clip(k - 10, 0, None)[:, None]
    centroids = np.array([5.0, 5.0]) + steps * np.array([0.3, -0.4])
    centroids[40:42] = np.nan
    centroids[42:] = [50.0, 50.0]
    tangential = np.where((k >= 10) & (k < 40), 4.0, 2.0)
    grip = np.full(n, 10.0)

    res = detect_slip(times, centroids, tangential, grip, 0.3, noise_band=1.0, motion_consecutive=2)
    assert (res.onset_index, res.flagged_index, res.criterion) == (10, 10, "force")
    np.testing.assert_allclose(res.velocity, [15.0, -20.0], rtol=1e-12)
    np.testing.assert_allclose(res.velocity_per_cycle, [0.3, -0.4], rtol=1e-12)
    assert res.speed == pytest.approx(25.0, rel=1e-12)
    assert res.distance == pytest.approx(0.5 * 29, rel=1e-12)        # cycles 10..39 of the episode
    np.testing.assert_allclose(res.force_ratio[[0, 10, 40]], [2 / 3, 4 / 3, np.nan])

    # motion only: displacement 0.5 (k - 10) first exceeds the 1.0 band at k = 13 (1.5)
    res = detect_slip(times, centroids, None, None, 0.3, noise_band=1.0, motion_consecutive=2)
    assert (res.onset_index, res.flagged_index, res.criterion) == (13, 14, "motion")
    assert res.speed == pytest.approx(25.0, rel=1e-12)
    assert res.distance == pytest.approx(0.5 * 26, rel=1e-12)        # cycles 13..39

    tracker = SlipTracker(0.3, 1.0, motion_consecutive=2)
    states = [tracker.update(t, [] if np.isnan(c[0]) else [c], f, g)
              for t, c, f, g in zip(times, centroids, tangential, grip)]
    s = states[39]
    assert (s.onset_index, s.flagged_index, s.criterion) == (10, 10, "force")
    assert s.distance == pytest.approx(0.5 * 29, rel=1e-12) and s.speed == pytest.approx(25.0, rel=1e-12)
    assert not states[40].contact and not states[41].slipping
    assert not states[-1].slipping and states[-1].force_ratio == pytest.approx(2.0 / 3.0)


def _exact_slope(times, points):
    """Least-squares slope of an (n, 2) track in 60-digit arithmetic (mpmath), an independent
    reference for the tracker's running fit."""
    import mpmath

    with mpmath.workdps(60):
        t = [mpmath.mpf(float(v)) for v in times]
        mean_t = mpmath.fsum(t) / len(t)
        denom = mpmath.fsum((v - mean_t) ** 2 for v in t)
        slope = []
        for axis in (0, 1):
            p = [mpmath.mpf(float(q[axis])) for q in points]
            mean_p = mpmath.fsum(p) / len(p)
            slope.append(mpmath.fsum((a - mean_t) * (b - mean_p) for a, b in zip(t, p)) / denom)
        return [float(v) for v in slope], float(t[-1] - t[0])


@pytest.mark.parametrize("t0", [0.0, 3600.0, 86400.0 * 30])
def test_tracker_fits_a_long_episode_as_the_exact_least_squares_line(t0):
    """Thousands of cycles of one slip (an object sliding for a minute at 100 Hz), the clock an
    hour or a month into a run: velocity and distance of the tracker's running fit against the
    least-squares line through every point since the onset, computed in 60 digits - and the
    last-15 window against line_fit_velocity on those points."""
    rng = np.random.default_rng(11)
    n, onset = 6000, 40
    times = t0 + np.arange(n) * PERIOD
    k = np.clip(np.arange(n) - onset, 0, None)
    # the centroid on a 2-unit taxel grid: the true path rounded to the grid, plus jitter
    path = np.column_stack([20.0 + 0.013 * k, 30.0 - 0.007 * k])
    centroids = np.round(path / 2.0) * 2.0 + rng.normal(0.0, 0.05, (n, 2))
    tracker = SlipTracker(0.3, 1.5, period=PERIOD)
    windowed = SlipTracker(0.3, 1.5, period=PERIOD, fit_window=15)
    for t, c in zip(times, centroids):
        state = tracker.update(t, [c])
        state_w = windowed.update(t, [c])
    assert state.slipping and state.criterion == "motion"
    since = state.onset_index
    slope, track_span = _exact_slope(times[since:], centroids[since:])
    np.testing.assert_allclose(state.velocity, slope, rtol=1e-9)
    assert state.distance == pytest.approx(np.hypot(*slope) * track_span, rel=1e-9)
    assert state.velocity_per_cycle == pytest.approx(np.asarray(slope) * PERIOD, rel=1e-9)
    np.testing.assert_allclose(state_w.velocity, line_fit_velocity(times[-15:], centroids[-15:]), rtol=1e-12)
    assert state_w.distance == pytest.approx(state.distance, rel=1e-12)


def test_tracker_memory_stays_flat_over_hours_of_cycles():
    """What the tracker keeps does not grow with the cycles it has seen, in contact or slipping
    (the service runs it for hours at 100 Hz): the memory it allocates between cycle 2,000 and
    cycle 6,000 of a slip episode stays under what 1,000 kept points would take."""
    import tracemalloc

    tracker = SlipTracker(0.3, 0.5, period=PERIOD, fit_window=15)
    point = np.array([10.0, 10.0])

    def run(first, count):
        for k in range(first, first + count):
            tracker.update(k * PERIOD, [point + (0.02 * k, 0.0)])

    run(0, 2000)
    assert tracker.update(2000 * PERIOD, [point + (40.0, 0.0)]).slipping
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        run(2001, 4000)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 1000 * 48, grown  # a kept float is 24-32 bytes, a kept centroid over 100


def test_update_centroid_is_update_and_refuses_a_bad_centroid():
    """The centroid entry point (the centre's layout computes the centroid) gives the states
    update gives from the active rows, and a centroid that is not one finite point or (nan,
    nan) is refused with the field named, the tracker left as it was."""
    rng = np.random.default_rng(5)
    times, active, ft, fg, _ = synthetic_trace(rng, n=80, onset=30)
    by_rows, by_centroid = SlipTracker(0.3, 1.5, period=PERIOD), SlipTracker(0.3, 1.5, period=PERIOD)
    for t, a, f, g in zip(times, active, ft, fg):
        a_state, b_state = by_rows.update(t, a, f, g), by_centroid.update_centroid(t, active_centroid(a), f, g)
        np.testing.assert_equal(dataclasses.asdict(a_state), dataclasses.asdict(b_state))
    for bad in ([1.0, np.nan], [np.inf, 0.0], [1.0, 2.0, 3.0], 5.0):
        with pytest.raises(ParameterError, match="centroid"):
            by_centroid.update_centroid(times[-1] + 1.0, bad)
    assert by_centroid.update_centroid(times[-1] + 1.0, [np.nan, np.nan]).contact is False


def test_bad_input_leaves_the_tracker_as_it_was():
    """A cycle refused (active rows not finite, their centroid overflowing, a bad centroid, a
    time not after the last) changes nothing: the same cycle then goes through as if the bad
    one had never come; the centroid handed in is kept as a copy."""
    tracker, reference = SlipTracker(0.3, 0.5, reference_cycles=1), SlipTracker(0.3, 0.5, reference_cycles=1)
    for tr in (tracker, reference):
        tr.update(0.0, [(0.0, 0.0)])
    for bad in ([[np.nan, 1.0]], [[1e308, 0.0], [1e308, 0.5]], [[1.0, 2.0, 3.0]]):
        with pytest.raises(ParameterError, match="active_xy"):
            tracker.update(1.0, bad)
    with pytest.raises(ParameterError, match="centroid"):
        tracker.update_centroid(1.0, [np.inf, 0.0])
    with pytest.raises(ParameterError, match="t"):
        tracker.update(0.0, [(1.0, 0.0)])
    buffer = np.array([2.0, 0.0])
    got = tracker.update_centroid(1.0, buffer)
    buffer[:] = 50.0  # the caller reuses its buffer
    want = reference.update(1.0, [(2.0, 0.0)])
    np.testing.assert_equal(dataclasses.asdict(got), dataclasses.asdict(want))
    np.testing.assert_equal(dataclasses.asdict(tracker.update(2.0, [(4.0, 0.0)])),
                            dataclasses.asdict(reference.update(2.0, [(4.0, 0.0)])))


@pytest.mark.parametrize("reference_cycles", [1, 3, 5])
def test_displacement_is_the_correctly_rounded_distance_to_the_reference(reference_cycles):
    """The tracker's per-cycle displacement (scalar float arithmetic since the command path was
    shortened) against mpmath: the distance of the centroid from the mean of the episode's first
    ``reference_cycles`` centroids, evaluated at 60 digits from the float inputs; and bit for
    bit the former numpy expression, ``np.hypot(*(c - np.mean(refs, axis=0)))``."""
    import mpmath

    with mpmath.workdps(60):
        rng = np.random.default_rng(23 + reference_cycles)
        tracker = SlipTracker(0.5, 0.7, reference_cycles=reference_cycles, period=PERIOD)
        track = rng.normal(20.0, 3.0, size=(200, 2)) * rng.choice([1e-3, 1.0, 1e3], size=(200, 1))
        refs = track[:reference_cycles]
        ref_np = np.mean(refs, axis=0)
        ref_mp = [mpmath.fsum(mpmath.mpf(float(v)) for v in refs[:, k]) / reference_cycles for k in (0, 1)]
        checked = 0
        for k, c in enumerate(track):
            state = tracker.update_centroid(PERIOD * (k + 1), c)
            if k < reference_cycles:
                assert state.displacement is None
                continue
            assert state.displacement == float(np.hypot(*(c - ref_np)))           # the former code, bit for bit
            exact = mpmath.sqrt((mpmath.mpf(float(c[0])) - ref_mp[0]) ** 2 + (mpmath.mpf(float(c[1])) - ref_mp[1]) ** 2)
            # the reference itself is rounded (a mean of floats) before the distance: a few ulps of it
            tol = 4 * np.spacing(max(abs(ref_np).max(), abs(c).max())) + 2 * np.spacing(state.displacement)
            assert abs(state.displacement - float(exact)) <= tol
            checked += 1
        assert checked == 200 - reference_cycles


@pytest.mark.parametrize("use_forces", [False, True])
def test_an_unobserved_cycle_is_as_if_it_had_not_been(use_forces):
    """A cycle that saw nothing of the contact (``unobserved``: its frames lost or late) neither
    ends the episode nor moves it: every other cycle's state equals the batch detector's on the
    trace without that cycle (cycle indices after it shifted by one), for an unobserved cycle
    anywhere - before the reference, inside a moving run, at the onset, after it."""
    rng = np.random.default_rng(11)
    times, active, ft, fg, _ = synthetic_trace(rng, n=80, onset=30, velocity=(0.7, 0.0), dropout=0.0,
                                               force_noise=0.05)
    for lost in (1, 20, 29, 30, 31, 32, 33, 50, 79):
        keep = [k for k in range(len(times)) if k != lost]
        f_in = (ft[keep], fg[keep]) if use_forces else (None, None)
        res = detect_slip(times[keep], centroids_of([active[k] for k in keep]), *f_in, 0.3, noise_band=1.5,
                          period=PERIOD)
        tracker = SlipTracker(0.3, 1.5, period=PERIOD)
        states = {}
        for k, (t, a) in enumerate(zip(times, active)):
            if k == lost:
                held = tracker.unobserved(t)
                continue
            forces = (ft[k], fg[k]) if use_forces else (None, None)
            states[k] = tracker.update(t, a, *forces)
        # the unobserved cycle's own state: the episode's, nothing measured
        assert held.contact and held.displacement is None and held.force_ratio is None
        assert held.slipping == states[lost - 1].slipping and held.cycle == lost
        index = {k: i for i, k in enumerate(keep)}          # the tracker's cycle -> the batch's
        batch_of = lambda c: None if c is None else index[c]  # noqa: E731
        last = states[keep[-1]]
        assert last.slipping == res.slipping
        assert res.slipping, "the trace slides: nothing tested"
        assert (batch_of(last.onset_index), batch_of(last.flagged_index), last.criterion) == \
            (res.onset_index, res.flagged_index, res.criterion)
        assert last.distance == pytest.approx(res.distance, rel=1e-9, abs=1e-12)
        for k in keep:
            assert states[k].slipping == (index[k] >= res.flagged_index), (lost, k)
            d = res.displacement[index[k]]
            assert (states[k].displacement is None) == bool(np.isnan(d)) and \
                (states[k].displacement is None or states[k].displacement == pytest.approx(d, rel=1e-12))


def test_an_unobserved_cycle_outside_a_contact_and_bad_times():
    tracker = SlipTracker(0.3, 0.5, reference_cycles=1, motion_consecutive=1)
    s = tracker.unobserved(0.0)
    assert not s.contact and not s.slipping and s.cycle == 0
    tracker.update(1.0, [(0, 0)])
    with pytest.raises(ParameterError, match="time must be finite"):
        tracker.unobserved(1.0)
    with pytest.raises(ParameterError, match="time must be finite"):
        tracker.unobserved(float("nan"))
    s = tracker.unobserved(2.0)
    assert s.contact and s.cycle == 2 and s.centroid.tolist() == [0.0, 0.0]
    # a real "no taxel active" still ends the episode; the next contact takes a new reference
    assert not tracker.update(3.0, []).contact
    assert not tracker.unobserved(4.0).contact
    assert tracker.update(5.0, [(9, 9)]).displacement is None
