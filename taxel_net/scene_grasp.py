"""The grasp world's part of a scene (issue 22 part 2): the object and its task, ``[grasp]``.

The typed, validated form (frozen dataclasses) shared by the scene loader and the world's Python
API (:mod:`node_sim.world`), and :func:`load_grasp` which reads the ``[grasp]`` table and its
``[[grasp.phase]]`` entries of a scene file. Format and meaning: ``docs/grasp-world.md``.

Conventions: SI in the world (kg, N, m/s², s); lengths in the scene in mm (sizes, heights); the
normal force is **per jaw** (the drive's convention, ``docs/gripper-drive.md``), two jaws, so the
friction the grasp can carry is 2 mu N (eq 26b read as a condition: m (g + a) <= 2 mu_s N).

:func:`check_grasp` is the one place of the semantic rules (negative mass, mu_k > mu_s, a task
phase out of order, a profile longer than its phase, ...): it raises
:class:`taxel_net.errors.ParameterError` naming the field relative to ``[grasp]``
(``mass_kg``, ``phase[2].name``); the loader turns that into a :class:`SceneError` naming the file
and ``grasp.<field>``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from taxel_net.errors import ParameterError
from taxel_net.scene_fields import Where, integer, number, string, table

# the task's phases, in the only order a task may list them (each at most once)
PHASES = ("approach", "close", "lift", "hold", "place", "release")
APPROACH_MIN_S = 1.0            # every master meets the whole task: >= 1 s before the jaws are due to close
STANDARD_GRAVITY = 9.80665      # m/s² (the kgf of taxel_net / fusion_center.core.units)
SHAKE_CYCLES_MAX = 100_000      # square-wave periods of one hold's shaking (3 timeline pieces each)

_PHASE_KEYS = {
    "approach": ("name", "duration_s"),
    "close": ("name", "duration_s"),
    "lift": ("name", "duration_s", "height_mm", "accel_m_s2", "speed_m_s"),
    "hold": ("name", "duration_s", "load_kg", "load_at_s", "shake_m_s2", "shake_hz", "shake_cycles",
             "shake_at_s"),
    "place": ("name", "duration_s", "height_mm", "accel_m_s2", "speed_m_s"),
    "release": ("name", "duration_s"),
}
_GRASP_KEYS = ("mass_kg", "mu_s", "mu_k", "size_mm", "max_force_n", "pad_length_mm", "contact_mm",
               "grip_at_mm", "force_lag_ms", "gravity_m_s2", "pressure_ref_n", "phase")


@dataclass(frozen=True)
class PhaseSpec:
    """One phase of the task (``[[grasp.phase]]``); the fields a phase does not use stay 0.

    ``lift`` / ``place``: the gripper moves up / down by ``height_mm`` with a trapezoidal velocity
    profile (accelerate at ``accel_m_s2``, cruise at ``speed_m_s`` if it is reached - 0: no cruise
    limit, a triangle -, decelerate at ``accel_m_s2``), at the phase's start, then stands still.
    ``hold``: the gripper stands still; ``load_kg`` is added to the object from ``load_at_s`` on (to
    the end of the task); shaking: the gripper's acceleration is ``shake_m_s2 * sgn(cos 2 pi f tau)``
    for ``shake_cycles`` whole periods of ``shake_hz`` from ``shake_at_s`` (it ends where it began,
    at rest).
    """

    name: str
    duration_s: float
    height_mm: float = 0.0
    accel_m_s2: float = 0.0
    speed_m_s: float = 0.0
    load_kg: float = 0.0
    load_at_s: float = 0.0
    shake_m_s2: float = 0.0
    shake_hz: float = 0.0
    shake_cycles: int = 0
    shake_at_s: float = 0.0


@dataclass(frozen=True)
class GraspSpec:
    """The object between the jaws and its task (``[grasp]``), see the module docstring."""

    mass_kg: float
    mu_s: float                          # static friction coefficient pad/object
    mu_k: float                          # kinetic (<= mu_s)
    size_mm: float                       # the object's width between the jaws (the drive's jaw_blocked_at)
    phases: tuple[PhaseSpec, ...]
    max_force_n: float | None = None     # fragile: crushed above this per-jaw normal force
    pad_length_mm: float = 40.0          # the pad's extent along the slip direction (vertical)
    contact_mm: float = 20.0             # the object's contact extent along the pad
    grip_at_mm: float | None = None      # the contact's centre from the pad's lower edge (None: the middle)
    force_lag_ms: float = 20.0           # time constant of the jaws' normal force behind the drive's force
    gravity_m_s2: float = STANDARD_GRAVITY
    pressure_ref_n: float = 10.0         # the taxels' view: a pressure cell reads its signal_mv at this per-jaw force

    @property
    def grip_at(self) -> float:
        """The contact's centre from the pad's lower edge, mm."""
        return self.pad_length_mm / 2.0 if self.grip_at_mm is None else self.grip_at_mm

    @property
    def slide_down_mm(self) -> float:
        """The slide (object down relative to the pads) at which the contact leaves the pads."""
        return self.grip_at + self.contact_mm / 2.0

    @property
    def slide_up_mm(self) -> float:
        """The slide upward at which the contact leaves the pads (past their upper edge)."""
        return self.pad_length_mm - self.grip_at + self.contact_mm / 2.0

    def phase(self, name: str) -> PhaseSpec | None:
        return next((p for p in self.phases if p.name == name), None)


def profile_times(height_m: float, accel: float, speed: float) -> tuple[float, float]:
    """Trapezoidal move of ``height_m`` (m) at ``accel`` (m/s²), cruise ``speed`` (m/s, 0: none):
    (time of the acceleration ramp = time of the deceleration ramp, time of the cruise)."""
    if height_m <= 0:
        return 0.0, 0.0
    if speed > 0 and speed * speed / accel < height_m:
        return speed / accel, (height_m - speed * speed / accel) / speed
    return math.sqrt(height_m / accel), 0.0


def _fail(name, value, allowed):
    raise ParameterError(name, value, allowed)


def _positive(name, v):
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
        _fail(name, v, "must be a finite number > 0")


def _non_negative(name, v):
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
        _fail(name, v, "must be a finite number >= 0")


def check_grasp(spec: GraspSpec) -> GraspSpec:
    """The semantic rules of a grasp (module docstring); returns ``spec`` (place's default height
    filled in: the lift's) or raises ParameterError naming the field relative to ``[grasp]``."""
    if not (isinstance(spec.mass_kg, (int, float)) and math.isfinite(spec.mass_kg) and spec.mass_kg > 0):
        _fail("mass_kg", spec.mass_kg, "the object's mass must be a finite number > 0 kg")
    _positive("mu_s", spec.mu_s)
    _positive("mu_k", spec.mu_k)
    if spec.mu_k > spec.mu_s:
        _fail("mu_k", spec.mu_k, f"kinetic friction must not exceed static friction (mu_s = {spec.mu_s:g})")
    _positive("size_mm", spec.size_mm)
    if spec.max_force_n is not None:
        _positive("max_force_n", spec.max_force_n)
    _positive("pad_length_mm", spec.pad_length_mm)
    _positive("contact_mm", spec.contact_mm)
    if spec.grip_at_mm is not None:
        _non_negative("grip_at_mm", spec.grip_at_mm)
        if spec.grip_at_mm > spec.pad_length_mm:
            _fail("grip_at_mm", spec.grip_at_mm, f"must lie on the pad: 0..pad_length_mm ({spec.pad_length_mm:g})")
    _non_negative("force_lag_ms", spec.force_lag_ms)
    _positive("gravity_m_s2", spec.gravity_m_s2)
    _positive("pressure_ref_n", spec.pressure_ref_n)
    phases = list(spec.phases)
    if not phases:
        _fail("phase", [], "a task needs at least the phases approach and close")
    last = -1
    lift: PhaseSpec | None = None
    for i, p in enumerate(phases):
        f = f"phase[{i}]"
        if p.name not in PHASES:
            _fail(f"{f}.name", p.name, f"must be one of {', '.join(PHASES)}")
        k = PHASES.index(p.name)
        if k <= last:
            _fail(f"{f}.name", p.name, f"task phase out of order: after {PHASES[last]!r} come only "
                                       f"{', '.join(PHASES[last + 1:]) or 'none'} (each at most once, in the "
                                       f"order {', '.join(PHASES)})")
        if i == 0 and k != 0:
            _fail(f"{f}.name", p.name, "task phase out of order: a task starts with 'approach'")
        if i == 1 and k != 1:
            _fail(f"{f}.name", p.name, "task phase out of order: 'close' follows 'approach'")
        last = k
        _positive(f"{f}.duration_s", p.duration_s)
        if p.name == "approach" and p.duration_s < APPROACH_MIN_S:
            _fail(f"{f}.duration_s", p.duration_s, f"the approach lasts at least {APPROACH_MIN_S:g} s (every "
                                                   "master meets the whole task)")
        if p.name in ("lift", "place"):
            if p.name == "place" and lift is None:
                _fail(f"{f}.name", p.name, "task phase out of order: 'place' needs a 'lift' before it")
            if p.name == "place" and p.height_mm == 0 and lift is not None:
                p = phases[i] = replace(p, height_mm=lift.height_mm)
            _positive(f"{f}.height_mm", p.height_mm)
            _positive(f"{f}.accel_m_s2", p.accel_m_s2)
            _non_negative(f"{f}.speed_m_s", p.speed_m_s)
            if p.name == "place" and p.height_mm > lift.height_mm:
                _fail(f"{f}.height_mm", p.height_mm, f"the gripper would go below the table: at most the lift's "
                                                     f"height ({lift.height_mm:g} mm)")
            ta, tc = profile_times(p.height_mm / 1000.0, p.accel_m_s2, p.speed_m_s)
            if 2 * ta + tc > p.duration_s:
                _fail(f"{f}.duration_s", p.duration_s, f"shorter than its move ({2 * ta + tc:.6g} s for "
                                                       f"{p.height_mm:g} mm at {p.accel_m_s2:g} m/s²)")
            if p.name == "lift":
                lift = p
        if p.name == "hold":
            _non_negative(f"{f}.load_kg", p.load_kg)
            _non_negative(f"{f}.load_at_s", p.load_at_s)
            if p.load_at_s > p.duration_s:
                _fail(f"{f}.load_at_s", p.load_at_s, f"must lie in the phase: 0..duration_s ({p.duration_s:g})")
            _non_negative(f"{f}.shake_m_s2", p.shake_m_s2)
            if p.shake_m_s2 > 0:
                _positive(f"{f}.shake_hz", p.shake_hz)
                if not (isinstance(p.shake_cycles, int) and 1 <= p.shake_cycles <= SHAKE_CYCLES_MAX):
                    _fail(f"{f}.shake_cycles", p.shake_cycles, f"whole periods of shaking: an integer in "
                                                               f"1..{SHAKE_CYCLES_MAX}")
                _non_negative(f"{f}.shake_at_s", p.shake_at_s)
                end = p.shake_at_s + p.shake_cycles / p.shake_hz
                if end > p.duration_s * (1 + 1e-12):
                    _fail(f"{f}.shake_cycles", p.shake_cycles, f"the shaking ends at {end:.6g} s, after the "
                                                               f"phase ({p.duration_s:g} s)")
    return replace(spec, phases=tuple(phases))


# ---------------------------------------------------------------------------- the scene table

def load_grasp(path: str, raw) -> GraspSpec:
    """``[grasp]`` of the scene file ``path`` (its parsed TOML table ``raw``) -> GraspSpec.

    Every bad value raises :class:`SceneError` (file, ``grasp.<field>``, value, what is allowed):
    the types here (:mod:`taxel_net.scene_fields`, as every table of a scene), the rest in
    :func:`check_grasp`."""
    g = table(Where(path), "grasp", raw, _GRASP_KEYS)
    w = Where(path, "grasp")
    for req in ("mass_kg", "mu_s", "mu_k", "size_mm"):
        if req not in g:
            w.fail(req, None, "missing required field")
    vals = {k: number(w, k, g[k]) for k in _GRASP_KEYS if k != "phase" and k in g}
    phases_raw = g.get("phase")
    if phases_raw is None:
        w.fail("phase", None, "missing: the task's [[grasp.phase]] entries (approach, close, ...)")
    if not isinstance(phases_raw, list):
        w.fail("phase", phases_raw, "must be an array of tables ([[grasp.phase]])")
    spec = GraspSpec(phases=tuple(_load_phase(w, f"phase[{i}]", pr) for i, pr in enumerate(phases_raw)), **vals)
    try:
        return check_grasp(spec)
    except ParameterError as exc:
        bad = exc.name, exc.value, exc.allowed
    w.fail(*bad)  # outside the except: the one-line SceneError chains no ParameterError


def _load_phase(w: Where, key: str, raw) -> PhaseSpec:
    """One ``[[grasp.phase]]`` entry, ``grasp.phase[i]`` in messages: its name first (the keys
    a phase allows depend on it), then its numbers."""
    if not isinstance(raw, dict):
        w.fail(key, raw, "must be a table")
    pw = Where(w.path, w.name(key))
    if "name" not in raw:
        pw.fail("name", None, "missing required field")
    name = string(pw, "name", raw["name"], PHASES)
    table(w, key, raw, _PHASE_KEYS[name], of=f"a {name!r} phase")
    if "duration_s" not in raw:
        pw.fail("duration_s", None, "missing required field")
    values = {k: integer(pw, k, v) if k == "shake_cycles" else number(pw, k, v)
              for k, v in raw.items() if k != "name"}
    return PhaseSpec(name=name, **values)


__all__ = ["PHASES", "APPROACH_MIN_S", "STANDARD_GRAVITY", "PhaseSpec", "GraspSpec", "check_grasp",
           "load_grasp", "profile_times"]
