"""Slip onset, slip velocity and slipped distance (chapter sec. 4: named, not modelled).

Sec. 4 says the fusion model evaluates grip and slip force and "associated parameters, like
slip velocity and slipped distance", but gives no model for them. This module supplies one,
built only on quantities the chapter does define:

Onset (either criterion, whichever *flags* first):

* **force** (Coulomb, eq 26a read backwards): the measured total tangential force exceeds
  the friction limit, ``TotF_t > mu F_g``, i.e. ``force_ratio = TotF_t / (mu F_g) > 1``,
  for ``force_consecutive`` consecutive cycles (F_g = 0 with TotF_t > 0 counts as > 1);
* **motion**: the centroid of the distinct locations of the active taxels (u_i = +1)
  moves farther than ``noise_band`` (coordinate units) from its reference position for
  ``motion_consecutive`` consecutive cycles. The reference is the mean centroid of the first
  ``reference_cycles`` cycles of the contact episode (an episode ends when no taxel is
  active; a live cycle that observed nothing of the contact - :meth:`SlipTracker.unobserved` -
  does not end it); motion is not tested during those cycles.

The onset index is the first cycle of the run that triggered; the flagged index is the
cycle at which the run completed (what a live system can know). The slip state latches
until contact is lost.

Velocity and distance: least-squares line fit of the centroid track against time over the
cycles from onset to the latest one in the episode (optionally only the last ``fit_window``
of them for the velocity): velocity in coordinate units per time unit of ``times``, per
cycle = velocity x cycle period; slipped distance = |fitted position(latest) -
fitted position(onset)| over the full since-onset fit. The fit averages out the staircase
the taxel pitch imposes on the centroid.

All functions are pure numerics (no I/O); :class:`SlipTracker` is the incremental form of
:func:`detect_slip` for the live service and gives the same answer on the same data.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from taxel_net.errors import ParameterError
from .forces import _check_mu
from .geometry import active_centroid, as_points

__all__ = ["SlipResult", "SlipState", "detect_slip", "SlipTracker", "line_fit_velocity"]


# --------------------------------------------------------------------------- helpers
def _check_params(mu, noise_band, motion_consecutive, force_consecutive, reference_cycles, fit_window):
    mu_f = _check_mu(mu)
    band = float(noise_band)
    if not np.isfinite(band) or band < 0:
        raise ParameterError("noise_band", noise_band, "must be a finite distance >= 0 (coordinate units)")
    for value, name in ((motion_consecutive, "motion_consecutive"),
                        (force_consecutive, "force_consecutive"),
                        (reference_cycles, "reference_cycles")):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise ParameterError(name, value, "must be a whole number of cycles >= 1")
    if fit_window is not None and (isinstance(fit_window, bool) or int(fit_window) != fit_window
                                   or fit_window < 2):
        raise ParameterError("fit_window", fit_window, "must be None or a whole number of cycles >= 2")
    return mu_f, band


def _force_ratio(tangential: float, grip: float, mu: float) -> float:
    """``TotF_t / (mu F_g)``; +inf for F_g = 0 with a positive tangential force, 0 for 0/0."""
    if grip < 0 or tangential < 0:
        raise ParameterError("force", (tangential, grip), "tangential and grip force must be >= 0")
    if grip == 0:
        return float("inf") if tangential > 0 else 0.0
    return tangential / (mu * grip)


def line_fit_velocity(times, positions) -> np.ndarray:
    """Least-squares slope d(position)/dt of an (n, 2) track; zeros for n < 2."""
    t = np.asarray(times, dtype=float)
    p = np.asarray(positions, dtype=float).reshape(len(t), -1)
    if len(t) < 2:
        return np.zeros(p.shape[1])
    tc = t - t.mean()
    denom = float(tc @ tc)
    if denom == 0:
        return np.zeros(p.shape[1])
    return (tc @ (p - p.mean(axis=0))) / denom


def _first_run(exceed: np.ndarray, run: int) -> int | None:
    """Index where the first run of ``run`` consecutive True values completes, or None."""
    if len(exceed) < run:
        return None
    counts = np.convolve(exceed.astype(np.int64), np.ones(run, dtype=np.int64), mode="valid")
    hits = np.flatnonzero(counts == run)
    return int(hits[0]) + run - 1 if len(hits) else None


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class SlipResult:
    """Outcome of :func:`detect_slip` (see the module docstring for the model)."""

    slipping: bool
    onset_index: int | None          # first cycle of the triggering run
    onset_time: float | None
    flagged_index: int | None        # cycle at which the run completed
    criterion: str | None            # "force" | "motion"
    velocity: np.ndarray             # (2,) coordinate units per time unit of `times`
    velocity_per_cycle: np.ndarray   # (2,) coordinate units per cycle
    speed: float                     # |velocity|
    distance: float                  # slipped distance, coordinate units
    force_ratio: np.ndarray          # (n,) TotF_t / (mu F_g); nan where not available
    displacement: np.ndarray         # (n,) |centroid - reference|; nan where not available


@dataclass(frozen=True)
class SlipState:
    """State after one :meth:`SlipTracker.update` (one SYNC cycle)."""

    cycle: int
    time: float
    contact: bool
    centroid: np.ndarray             # (2,) or (nan, nan) without contact
    displacement: float | None       # None before the reference is established
    force_ratio: float | None        # None when forces were not given
    slipping: bool
    onset_index: int | None
    onset_time: float | None
    flagged_index: int | None
    criterion: str | None
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    velocity_per_cycle: np.ndarray = field(default_factory=lambda: np.zeros(2))
    speed: float = 0.0
    distance: float = 0.0


def _kinematics(times: np.ndarray, track: np.ndarray, fit_window: int | None, period: float):
    window = (times[-fit_window:], track[-fit_window:]) if fit_window is not None and len(times) > fit_window else None
    return _motion(line_fit_velocity(times, track), times[-1] - times[0] if len(times) >= 2 else 0.0, window, period)


def _motion(full_v: np.ndarray, span: float, window: tuple | None, period: float):
    """(velocity, velocity per cycle, speed, distance) of a slip from the fit over the whole
    track since the onset (slope ``full_v`` over ``span`` time units: the distance) and, when
    given, the ``(times, positions)`` of its last ``fit_window`` points (the velocity)."""
    distance = float(np.hypot(*full_v) * span)
    v = line_fit_velocity(*window) if window is not None else full_v
    return v, v * period, float(np.hypot(*v)), distance


# --------------------------------------------------------------------------- batch
def detect_slip(times, centroids, tangential, grip_force, mu, *, noise_band: float,
                motion_consecutive: int = 3, force_consecutive: int = 1,
                reference_cycles: int = 3, fit_window: int | None = None,
                period: float | None = None) -> SlipResult:
    """Detect the first slip in a per-cycle record and estimate its velocity and distance.

    ``times`` (n,) strictly increasing; ``centroids`` (n, 2) active-taxel centroids with
    NaN rows for cycles without contact; ``tangential`` and ``grip_force`` (n,) totals in
    one force unit (eqs 24-25/29 and 26a/27b), or None to use the motion criterion only;
    ``mu`` the friction coefficient (eq 26). ``period`` is the cycle period in the time
    unit of ``times`` (default: median spacing of ``times``).
    """
    mu_f, band = _check_params(mu, noise_band, motion_consecutive, force_consecutive,
                               reference_cycles, fit_window)
    t = np.asarray(times, dtype=float)
    if t.ndim != 1 or len(t) == 0 or np.any(~np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ParameterError("times", times, "must be a non-empty, finite, strictly increasing 1-D array")
    n = len(t)
    c = np.asarray(centroids, dtype=float)
    if c.shape != (n, 2):
        raise ParameterError("centroids", c.shape, f"must have shape ({n}, 2), NaN rows = no contact")
    if np.any(np.isinf(c)) or np.any(np.isnan(c[:, 0]) != np.isnan(c[:, 1])):
        raise ParameterError("centroids", "inf or half-NaN row", "rows must be finite or (nan, nan)")
    if period is None:
        period = float(np.median(np.diff(t))) if n > 1 else 1.0
    if not np.isfinite(period) or period <= 0:
        raise ParameterError("period", period, "cycle period must be finite and > 0")
    contact = np.isfinite(c[:, 0])

    ratio = np.full(n, np.nan)
    force_flag = force_onset = None
    if (tangential is None) != (grip_force is None):
        raise ParameterError("tangential/grip_force", (tangential is None, grip_force is None),
                             "give both (force criterion) or neither (motion only)")
    if tangential is not None:
        ft = np.asarray(tangential, dtype=float)
        fg = np.asarray(grip_force, dtype=float)
        for arr, name in ((ft, "tangential"), (fg, "grip_force")):
            if arr.shape != (n,) or np.any(~np.isfinite(arr)) or np.any(arr < 0):
                raise ParameterError(name, arr.shape, f"must be {n} finite forces >= 0")
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(fg > 0, ft / (mu_f * np.where(fg > 0, fg, 1.0)),
                         np.where(ft > 0, np.inf, 0.0))
        ratio = np.where(contact, r, np.nan)
        force_flag = _first_run(contact & (r > 1.0), force_consecutive)
        force_onset = None if force_flag is None else force_flag - force_consecutive + 1

    # motion criterion, per contact episode
    displacement = np.full(n, np.nan)
    motion_exceed = np.zeros(n, dtype=bool)
    edges = np.diff(np.concatenate(([0], contact.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    for s, e in zip(starts, ends):
        if e - s <= reference_cycles:
            continue
        ref = c[s:s + reference_cycles].mean(axis=0)
        d = np.hypot(*(c[s + reference_cycles:e] - ref).T)
        displacement[s + reference_cycles:e] = d
        motion_exceed[s + reference_cycles:e] = d > band
    motion_flag = _first_run(motion_exceed, motion_consecutive)
    motion_onset = None if motion_flag is None else motion_flag - motion_consecutive + 1

    candidates = [(f, o, name) for f, o, name in ((force_flag, force_onset, "force"),
                                                  (motion_flag, motion_onset, "motion")) if f is not None]
    if not candidates:
        zero = np.zeros(2)
        return SlipResult(False, None, None, None, None, zero, zero.copy(), 0.0, 0.0, ratio, displacement)
    flagged, onset, criterion = min(candidates, key=lambda x: (x[0], x[1]))
    episode_end = int(ends[np.searchsorted(ends, onset, side="right")])
    sel = np.arange(onset, episode_end)
    v, v_cycle, speed, distance = _kinematics(t[sel], c[sel], fit_window, period)
    return SlipResult(True, onset, float(t[onset]), flagged, criterion, v, v_cycle, speed,
                      distance, ratio, displacement)


# --------------------------------------------------------------------------- incremental
class _RunningLineFit:
    """The least-squares line of a growing (t, x, y) track, one point at a time in constant
    time and memory: Welford's updates of the means and of the co-moments ``sum (t - mean_t)^2``
    and ``sum (t - mean_t)(p - mean_p)`` (the centred sums :func:`line_fit_velocity` forms in
    one pass over the points, here without keeping them), on times since the first point. A
    live slip episode lasts as long as the object keeps sliding - minutes, at 100 cycles a
    second - and refitting every point at every cycle made the tracker's cost and memory grow
    with it."""

    __slots__ = ("n", "t_first", "t_last", "mean_t", "mean_x", "mean_y", "m2_t", "c_tx", "c_ty")

    def __init__(self):
        self.n = 0
        self.t_first = self.t_last = self.mean_t = self.mean_x = self.mean_y = 0.0
        self.m2_t = self.c_tx = self.c_ty = 0.0

    def add(self, t: float, point) -> None:
        x, y = float(point[0]), float(point[1])
        self.n += 1
        if self.n == 1:
            self.t_first = t
        self.t_last = t
        tau = t - self.t_first  # exact (both multiples of the ulp at t): the fit's times stay small
        dt = tau - self.mean_t  # a month into a run, the clock's own ulp would cost 2e-8 of the slope
        self.mean_t += dt / self.n
        self.mean_x += (x - self.mean_x) / self.n
        self.mean_y += (y - self.mean_y) / self.n
        self.m2_t += dt * (tau - self.mean_t)
        self.c_tx += dt * (x - self.mean_x)
        self.c_ty += dt * (y - self.mean_y)

    def velocity(self) -> np.ndarray:
        """The fitted slope d(position)/dt; zeros for fewer than 2 points (as line_fit_velocity)."""
        if self.n < 2 or self.m2_t == 0:
            return np.zeros(2)
        return np.array([self.c_tx / self.m2_t, self.c_ty / self.m2_t])


class SlipTracker:
    """Per-cycle slip detector for the live fusion centre (same model as :func:`detect_slip`).

    ``update(t, active_xy, total_tangential, grip_force)`` once per SYNC cycle with the
    coordinates of the taxels deciding u_i = +1 and the cycle's force totals (or None for
    both to use the motion criterion only). Pure numerics: no I/O, no clock.
    """

    def __init__(self, mu, noise_band: float, *, motion_consecutive: int = 3,
                 force_consecutive: int = 1, reference_cycles: int = 3,
                 fit_window: int | None = None, period: float | None = None, max_unobserved: int = 10):
        self.mu, self.noise_band = _check_params(mu, noise_band, motion_consecutive, force_consecutive,
                                                 reference_cycles, fit_window)
        if period is not None and (not np.isfinite(period) or period <= 0):
            raise ParameterError("period", period, "cycle period must be finite and > 0")
        self.motion_consecutive = int(motion_consecutive)
        self.force_consecutive = int(force_consecutive)
        self.reference_cycles = int(reference_cycles)
        self.fit_window = fit_window
        self.period = period
        if isinstance(max_unobserved, bool) or int(max_unobserved) != max_unobserved or max_unobserved < 0:
            raise ParameterError("max_unobserved", max_unobserved, "must be a whole number of cycles >= 0")
        self.max_unobserved = int(max_unobserved)
        self.cycle = -1
        self._last_time: float | None = None
        self._dts: list[float] = []
        self._in_contact = False           # the last observed cycle had contact (reset() keeps it)
        self._last_centroid: np.ndarray | None = None
        self._unobserved_run = 0           # unobserved cycles in a row
        self._new_episode()

    def _new_episode(self) -> None:
        self._ref_samples: list[np.ndarray] = []
        self._reference: np.ndarray | None = None
        self._ref_xy: list[float] = []  # the reference as Python floats
        self._force_run = 0
        self._motion_run = 0
        keep = max(self.motion_consecutive, self.force_consecutive)
        self._recent: deque[tuple[int, float, np.ndarray]] = deque(maxlen=keep)
        self._track = _RunningLineFit()  # since the onset: velocity (full fit), distance
        self._window: deque[tuple[float, np.ndarray]] = deque(maxlen=self.fit_window or 1)  # last fit_window
        self._onset: tuple[int, float, int, str] | None = None

    def reset(self) -> None:
        """Forget the current contact episode (e.g. after the gripper re-grasps)."""
        self._new_episode()

    def _track_point(self, t: float, centroid: np.ndarray) -> None:
        self._track.add(t, centroid)
        if self.fit_window is not None:
            self._window.append((t, centroid))

    def _kinematics(self):
        """:func:`_kinematics` of the track since the onset, from the running fit (and the
        last ``fit_window`` points for the velocity)."""
        track = self._track
        window = None
        if self.fit_window is not None and track.n > self.fit_window:
            window = ([w[0] for w in self._window], np.array([w[1] for w in self._window]))
        return _motion(track.velocity(), track.t_last - track.t_first if track.n >= 2 else 0.0, window,
                       self._period())

    def _period(self) -> float:
        if self.period is not None:
            return float(self.period)
        return float(np.median(self._dts)) if self._dts else 1.0

    def update(self, t, active_xy, total_tangential=None, grip_force=None) -> SlipState:
        """One cycle: ``active_xy`` the coordinates of the taxels deciding u_i = +1 (their
        distinct locations' centroid is what moves, :func:`~.geometry.active_centroid`). Bad
        input raises ParameterError and leaves the tracker as it was."""
        points = as_points(active_xy, "active_xy")
        with np.errstate(over="ignore"):
            centroid = active_centroid(points)
        if np.isinf(centroid).any():
            raise ParameterError("active_xy", [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
                                 "the centroid of the points must be finite (their mean overflows a float)")
        return self.update_centroid(t, centroid, total_tangential, grip_force)

    def unobserved(self, t) -> SlipState:
        """A cycle that observed none of the contact - none of the taxels active in the episode's
        last observed cycle was received (their frames lost or late, their node missing) - so it
        cannot tell whether the contact moved or ended: the episode goes on as if the cycle had
        not been (its reference, its runs of moving or overloaded cycles, a slip flagged; the
        track gets no point), and only the time and the cycle count advance. The state returned
        is the episode's at ``t``: ``displacement`` and ``force_ratio`` None (nothing measured),
        ``centroid`` the last observed one; no contact when the last observed cycle had none,
        and the episode ends (no contact) once more than ``max_unobserved`` cycles in a row went
        unobserved (a node gone for good must not keep a contact alive). A :meth:`reset` (the
        reference to be taken again) is no end of the contact. (Without this a lost
        cycle read as "no taxel active" ended the episode: the reference was taken again, three
        cycles later, at wherever the contact had slid to, and a slip under way went unseen.)"""
        t = float(t)
        if not math.isfinite(t) or (self._last_time is not None and t <= self._last_time):
            raise ParameterError("t", t, f"time must be finite and > the previous one ({self._last_time})")
        if self._last_time is not None and self.period is None:
            self._dts.append(t - self._last_time)
        self._last_time = t
        self.cycle += 1
        self._unobserved_run += 1
        if not self._in_contact or self._unobserved_run > self.max_unobserved:
            # no contact to go on with - or not seen for max_unobserved cycles (a node gone for
            # good): the episode ends as on a cycle without contact
            self._in_contact, self._last_centroid = False, None
            self._new_episode()
            return SlipState(self.cycle, t, False, np.array([math.nan, math.nan]), None, None, False,
                             None, None, None, None)
        return self._contact_state(t, self._last_centroid.copy(), None, None)

    def update_centroid(self, t, centroid, total_tangential=None, grip_force=None) -> SlipState:
        """:meth:`update` given the centroid of the active taxels' distinct locations - (nan,
        nan) for no contact - as a fixed layout computes it for any subset
        (:class:`~.geometry.Locations`); kept as a copy."""
        # scalar arithmetic on Python floats (the same IEEE operations as numpy's on the (2,)
        # array, and np.hypot for the displacement): a live cycle's slip stage was 0.1-0.4 ms of
        # numpy calls on 2-element arrays, on the grip command's path
        centroid = np.array(centroid, dtype=float)
        if centroid.shape != (2,):
            raise ParameterError("centroid", centroid.tolist() if centroid.ndim else centroid,
                                 "must be one finite (x, y), or (nan, nan) for no contact")
        cx, cy = centroid.tolist()
        if math.isinf(cx) or math.isinf(cy) or math.isnan(cx) != math.isnan(cy):
            raise ParameterError("centroid", [cx, cy], "must be one finite (x, y), or (nan, nan) for no contact")
        t = float(t)
        if not math.isfinite(t) or (self._last_time is not None and t <= self._last_time):
            raise ParameterError("t", t, f"time must be finite and > the previous one ({self._last_time})")
        if (total_tangential is None) != (grip_force is None):
            raise ParameterError("total_tangential/grip_force", (total_tangential, grip_force),
                                 "give both (force criterion) or neither (motion only)")
        if self._last_time is not None and self.period is None:  # only _period() reads them
            self._dts.append(t - self._last_time)
        self._last_time = t
        self.cycle += 1
        self._unobserved_run = 0
        contact = not math.isnan(cx)
        self._in_contact = contact
        self._last_centroid = centroid if contact else None
        if not contact:
            self._new_episode()
            return SlipState(self.cycle, t, False, centroid, None, None, False, None, None, None, None)

        ratio = None
        if total_tangential is not None:
            ft, fg = float(total_tangential), float(grip_force)
            if not (math.isfinite(ft) and math.isfinite(fg)):
                raise ParameterError("force", (total_tangential, grip_force), "forces must be finite")
            ratio = _force_ratio(ft, fg, self.mu)
            self._force_run = self._force_run + 1 if ratio > 1.0 else 0

        displacement = None
        if self._reference is None:
            self._ref_samples.append(centroid)
            if len(self._ref_samples) == self.reference_cycles:
                self._reference = np.mean(self._ref_samples, axis=0)
                self._ref_xy = self._reference.tolist()
        else:
            rx, ry = self._ref_xy
            displacement = float(np.hypot(cx - rx, cy - ry))
            self._motion_run = self._motion_run + 1 if displacement > self.noise_band else 0

        self._recent.append((self.cycle, t, centroid))
        if self._onset is None:
            hits = []
            # a run's first cycle from the observed cycles kept (an unobserved cycle inside a run is
            # not one of its cycles: the onset is the run's first observed cycle)
            if ratio is not None and self._force_run >= self.force_consecutive:
                hits.append((self._recent[-self.force_consecutive][0], "force"))
            if self._motion_run >= self.motion_consecutive:
                hits.append((self._recent[-self.motion_consecutive][0], "motion"))
            if hits:
                onset_idx, criterion = min(hits)
                back = [(ti, ci) for k, ti, ci in self._recent if k >= onset_idx]
                for ti, ci in back:
                    self._track_point(ti, ci)
                self._onset = (onset_idx, back[0][0], self.cycle, criterion)
        else:
            self._track_point(t, centroid)

        return self._contact_state(t, centroid, displacement, ratio)

    def _contact_state(self, t: float, centroid: np.ndarray, displacement, ratio) -> SlipState:
        """The state of a cycle in a contact episode: slipping from the onset on, with the track's
        kinematics."""
        if self._onset is None:
            return SlipState(self.cycle, t, True, centroid, displacement, ratio, False, None, None, None, None)
        v, v_cycle, speed, distance = self._kinematics()
        onset_idx, onset_t, flagged, criterion = self._onset
        return SlipState(self.cycle, t, True, centroid, displacement, ratio, True, onset_idx, onset_t,
                         flagged, criterion, v, v_cycle, speed, distance)
