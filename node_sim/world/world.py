"""The grasp world: the task's timeline and the mechanics, stepped on the world's own clock.

:class:`GraspWorld` is pure (no CAN, no wall clock): a caller - :class:`.coupling.JawCoupling` with
a drive, or a test - calls :meth:`GraspWorld.step` once per world step with the per-jaw normal
force held over that step and whether the jaws touch the object, and gets the step's ground truth
(:data:`TRUTH_FIELDS`). Before :meth:`GraspWorld.start` the task has not begun (phase ``idle``: the
object rests on the table, the gripper waits above it).

Truth per step (names the centre's records reuse):

* ``phase`` - the task's phase in the step's last instant (a step that ends where a phase ends
  still belongs to it; ``idle`` before the start, ``done`` after the last phase);
* ``normal_n`` - the per-jaw normal force during the step, N;
* ``min_hold_n`` - the least per-jaw force that holds the object now: ``m (g + a) / (2 mu_s)`` (eq
  26b solved for the grip force with the static coefficient; ``m`` with any added load), the
  largest over the step's pieces; 0 while it rests on the table and the gripper is not going up,
  and once it is gone;
* ``slipping`` - pads and object moved relative to each other (in contact) during the step;
* ``slid_mm`` - the net slide of the object relative to the pads since it was gripped, mm, down
  positive (the footprint's displacement on the pads);
* ``dropped`` - it fell: slid off the pads, or the jaws opened, while in the air (latched). An
  object put down on the table and released is not dropped;
* ``crushed`` - the normal force exceeded the object's ``max_force_n`` (latched; never without
  a ``max_force_n``);
* ``tangential_n`` - the tangential load on each jaw's pad in the step's last instant, N, down
  positive (what the pads' tangential cells feel, :mod:`.taxels`): sticking ``m (g + a) / 2`` (eq
  26b's load ``W`` shared by the two jaws), slipping ``sgn(v) mu_k N`` (the slide's direction; from
  rest that of ``g + a``), on the table ``sgn(w) mu_k N`` while the jaws press and the pads slide
  over it (the gripper moving), else 0;

and, for the curious: ``t_s`` (world clock since the world's creation), ``task_s`` (since the
start, None before), ``mode`` (:class:`.grasp.Mode`), ``height_mm`` (the object above its resting
height), ``in_grip`` (between the jaws and not lost).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from taxel_net.errors import ParameterError
from taxel_net.scene_grasp import GraspSpec, check_grasp

from .grasp import Mode, Params, State, advance
from .timeline import DONE, Timeline

IDLE = "idle"
TRUTH_FIELDS = ("phase", "normal_n", "min_hold_n", "slipping", "slid_mm", "dropped", "crushed")


@dataclass(frozen=True)
class Truth:
    """One world step's ground truth (module docstring)."""

    t_s: float
    task_s: float | None
    phase: str
    normal_n: float
    min_hold_n: float
    slipping: bool
    slid_mm: float
    dropped: bool
    crushed: bool
    mode: str
    height_mm: float
    in_grip: bool
    tangential_n: float = 0.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class GraspWorld:
    """The world of one grasp (module docstring). ``spec`` is checked (:func:`check_grasp`)."""

    def __init__(self, spec: GraspSpec, step_s: float):
        if not (isinstance(step_s, (int, float)) and 0 < step_s < float("inf")):
            raise ParameterError("step_s", step_s, "the world step must be a finite number of seconds > 0 "
                                                   "(the scene's SYNC period)")
        self.step_s = float(step_s)
        self.spec = spec = check_grasp(spec)
        self.timeline = Timeline(spec)
        self.params = Params(g=spec.gravity_m_s2, mu_s=spec.mu_s, mu_k=spec.mu_k,
                             s_down=spec.slide_down_mm / 1000.0, s_up=spec.slide_up_mm / 1000.0)
        self.state = State()
        self.steps = 0                 # world steps taken (the world clock: steps * step_s)
        self._start_step: int | None = None
        self.dropped = False
        self.crushed = False

    @property
    def t_s(self) -> float:
        """The world clock, s since the world's creation."""
        return self.steps * self.step_s

    @property
    def task_s(self) -> float | None:
        """Time since the task's start, s (None before)."""
        return None if self._start_step is None else (self.steps - self._start_step) * self.step_s

    @property
    def started(self) -> bool:
        return self._start_step is not None

    def start(self) -> None:
        """The task's timeline starts now, at the next step (idempotent)."""
        if self._start_step is None:
            self._start_step = self.steps

    def leave_behind(self) -> None:
        """The object resting on the table is out of the gripper's reach for good (the jaws were
        closed when the approach ended): it stays there, never gripped."""
        if self.state.mode is Mode.TABLE:
            self.state.mode = Mode.LEFT

    @property
    def phase(self) -> str:
        return IDLE if self.task_s is None else self.timeline.phase_at(self.task_s)

    @property
    def object_between_jaws(self) -> bool:
        """The approach is over and the object is neither dropped nor left behind."""
        return (self.task_s is not None and self.task_s >= self.timeline.phase_starts.get("close", 0.0)
                and self.state.mode not in (Mode.DROPPED, Mode.LEFT))

    def step(self, normal_n: float, jaws_open: bool = False) -> Truth:
        """Advance the world by one step with the per-jaw normal force ``normal_n`` (N, held over
        the step) and whether the jaws are open (not touching the object)."""
        if not (isinstance(normal_n, (int, float)) and 0 <= normal_n < float("inf")):
            raise ParameterError("normal_n", normal_n, "the per-jaw normal force must be finite and >= 0 N")
        st, p, spec = self.state, self.params, self.spec
        n = 0.0 if jaws_open else float(normal_n)
        slipping = False
        need = 0.0
        a_end, m_end = 0.0, spec.mass_kg
        t0 = self.task_s
        if t0 is None:
            pieces = []
            slipping = advance(st, self.step_s, 0.0, n, spec.mass_kg, p, jaws_open).slipped
        else:
            pieces = list(self.timeline.pieces(t0, (self.steps + 1 - self._start_step) * self.step_s))
        for pc in pieces:
            m = spec.mass_kg + pc.load_kg
            st.z, st.w = pc.z0, pc.w0          # the gripper's motion is the timeline's, in closed form
            if st.airborne or (st.mode is Mode.TABLE and (pc.a > 0 or pc.w0 > 0)):
                need = max(need, m * (p.g + pc.a) / (2.0 * p.mu_s))
            fl = advance(st, pc.t1 - pc.t0, pc.a, n, m, p, jaws_open)
            a_end, m_end = pc.a, m
            slipping = slipping or fl.slipped
            if st.airborne:
                need = max(need, m * (p.g + pc.a) / (2.0 * p.mu_s))
        self.steps += 1
        if st.mode is Mode.DROPPED:
            self.dropped = True
        mx = spec.max_force_n
        if mx is not None and n > mx:
            self.crushed = True
        gone = st.mode in (Mode.DROPPED, Mode.LEFT)
        phase = pieces[-1].phase if pieces else IDLE
        return Truth(t_s=self.t_s, task_s=self.task_s, phase=phase, normal_n=n,
                     min_hold_n=0.0 if gone else max(0.0, need), slipping=slipping,
                     slid_mm=st.s * 1000.0,
                     dropped=self.dropped, crushed=self.crushed, mode=st.mode.value,
                     height_mm=max(0.0, st.y) * 1000.0 if not gone else 0.0,
                     in_grip=self.object_between_jaws, tangential_n=tangential_load(st, a_end, n, m_end, p))


def tangential_load(st: State, a: float, n: float, m: float, p: Params) -> float:
    """The tangential load per jaw's pad, N, down positive (module docstring, ``tangential_n``),
    in the regime ``st`` with the gripper's acceleration ``a``, the per-jaw normal force ``n`` and
    the mass ``m`` (with any added load) of that instant."""
    if st.mode is Mode.STICK:
        return m * (p.g + a) / 2.0                      # eq 26b's W = m (g + a), half on each jaw
    if st.mode is Mode.SLIP:
        d = math.copysign(1.0, st.v) if st.v != 0 else math.copysign(1.0, p.g + a)
        return d * p.mu_k * n
    if st.mode is Mode.TABLE and n > 0 and st.w != 0:
        return math.copysign(p.mu_k * n, st.w)           # the pads slide over the resting object
    return 0.0


__all__ = ["GraspWorld", "Truth", "tangential_load", "TRUTH_FIELDS", "IDLE", "DONE"]
