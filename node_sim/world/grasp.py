"""The grasp world's mechanics: an object held by friction between two jaws (pure: no CAN, no clock).

Vertical motion only (up positive). The gripper's height ``z`` and velocity ``w`` follow the task's
timeline (:mod:`.timeline`: piecewise constant acceleration ``a``). The object (mass ``m`` = its
mass + an added load) sits between two jaws, each pressing with the normal force ``N`` (per jaw, the
drive's convention), so friction carries at most ``2 mu_s N`` while it sticks and exactly
``2 mu_k N`` while it slides. The relative slide ``s = z - y`` (the object's position ``y`` below
where it was gripped, down positive, m) and its rate ``v = w - u`` are what the pads feel.

Regimes (:class:`Mode`):

* **STICK** (airborne, moving with the gripper) while ``|m (g + a)| <= 2 mu_s N`` - eq 26b read as a
  condition: the load ``W = m (g + a)`` is at most ``2 mu F_g``;
* **SLIP**, otherwise: relative acceleration ``s'' = (g + a) - sgn(v) 2 mu_k N / m`` (for a slide
  starting from rest ``sgn(v) = sgn(g + a)``); it sticks again **only when v reaches 0** while the
  stick condition holds (stick-slip hysteresis: with mu_k < mu_s a slide that started goes on at
  forces that would have held a sticking object, until it has stopped);
* **TABLE**: resting on the table (``y = 0``, ``u = 0``): at the start, after landing, after being put
  down. The pads slide over it while the gripper moves (``s = z``); it is lifted when the gripper
  starts up from rest with ``m (g + a) <= 2 mu_s N`` (STICK), or when kinetic friction exceeds its
  weight ``2 mu_k N > m g`` while the pads move up or start up (SLIP);
* **DROPPED**: it slid off the pads while airborne (``s`` beyond ``slide_down_mm`` / ``slide_up_mm``
  of the spec) or the jaws opened while it was airborne - it fell;
* **LEFT**: the pads slid off it while it stood on the table (lost from the grip, not fallen).

Within a constant-input interval every regime has constant accelerations, so the motion is
quadratic in time and every event - v = 0, landing (y = 0 from above), the slide reaching a pad's
edge, the gripper's velocity crossing 0 on the table - has a closed-form time: :func:`advance` steps
exactly from event to event (no stick -> slip or slip -> stick detected a step late). The normal
force is held over a world step (zero-order hold: the force is the discretised input, the motion is
exact for it).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

SLIP_EPS_M = 1e-9            # a relative motion below 1 nm is rounding (a landing found 1e-16 s early)
_MAX_EVENTS = 10_000          # events within one constant-input interval (a guard: a handful is normal)


class Mode(str, enum.Enum):
    TABLE = "table"
    STICK = "stick"
    SLIP = "slip"
    DROPPED = "dropped"
    LEFT = "left"


@dataclass(frozen=True)
class Params:
    """The constants of the mechanics (SI)."""

    g: float
    mu_s: float
    mu_k: float
    s_down: float         # slide (m, object down) at which the contact leaves the pads
    s_up: float           # slide upward (m, > 0) at which it leaves them


@dataclass
class State:
    """The object's mechanical state. ``s``/``v``: relative slide and rate (m, m/s, object down
    relative to the pads positive); ``z``/``w``: the gripper's height and velocity."""

    mode: Mode = Mode.TABLE
    z: float = 0.0
    w: float = 0.0
    s: float = 0.0
    v: float = 0.0

    @property
    def y(self) -> float:
        """The object's height above its resting height on the table, m."""
        return 0.0 if self.mode is Mode.TABLE else self.z - self.s

    @property
    def airborne(self) -> bool:
        return self.mode in (Mode.STICK, Mode.SLIP)


@dataclass
class Flags:
    """What happened during an :func:`advance` (for the step's truth)."""

    slipped: bool = False            # pads and object moved relative to each other (> SLIP_EPS_M), in contact
    dropped: bool = False
    left: bool = False
    landed: bool = False


def _sign(x: float) -> float:
    return 1.0 if x > 0 else (-1.0 if x < 0 else 0.0)


def first_root(c0: float, c1: float, c2: float, horizon: float) -> float | None:
    """Smallest ``t`` in (0, horizon] with c0 + c1 t + c2 t²/2 = 0 where the quadratic, positive or
    zero at 0, becomes <= 0 (a downward crossing or a touch), or None. ``c0 < 0`` (already past,
    by rounding): 0, the event is now."""
    if c0 < 0.0:
        return 0.0
    if c0 == 0.0:
        # t = 0 is a root; the other one, -2 c1 / c2, if it is ahead (the function goes up first)
        if c1 > 0 and c2 < 0:
            t = -2.0 * c1 / c2
            return t if t <= horizon else None
        return None
    if 0.5 * c2 == 0.0:
        # linear (c2 == 0, or a subnormal c2 whose half underflows: its root is beyond any horizon)
        if c1 < 0:
            t = -c0 / c1
            return t if t <= horizon else None
        return None
    disc = c1 * c1 - 2.0 * c2 * c0
    if disc < 0:
        return None
    sq = math.sqrt(disc)
    # roots of (c2/2) t² + c1 t + c0 (stable form)
    q = -0.5 * (c1 + math.copysign(sq, c1)) if c1 != 0 else 0.5 * sq * (1.0 if c2 < 0 else -1.0)
    roots = []
    if q != 0:
        roots.append(c0 / q)
        roots.append(q / (0.5 * c2))
    else:
        roots.append(math.sqrt(-2.0 * c0 / c2) if c2 < 0 else 0.0)
    ahead = sorted(t for t in roots if t > 0)
    for t in ahead:
        if t <= horizon:
            return t
    return None


def settle(st: State, a: float, n: float, m: float, p: Params) -> None:
    """Choose the regime at an instant, the inputs (``a``, ``n``, ``m``) constant from now on."""
    g, mode = p.g, st.mode
    if mode in (Mode.DROPPED, Mode.LEFT):
        return
    if mode is Mode.TABLE:
        st.s, st.v = st.z, st.w
        if n <= 0:
            return
        if st.w > 0 or (st.w == 0 and a > 0):
            if st.w == 0 and m * (g + a) <= 2 * p.mu_s * n:
                st.mode, st.v = Mode.STICK, 0.0
            elif 2 * p.mu_k * n > m * g:
                st.mode = Mode.SLIP         # v = w >= 0: slides up the pads' way, lifted by kinetic friction
        return
    # airborne: landing on the table first (object at y <= 0 going down, or at rest about to go down)
    u = st.w - st.v
    if st.z - st.s <= 0:
        if u < 0 or (u == 0 and not _lifts(st, a, n, m, p)):
            st.mode, st.s, st.v = Mode.TABLE, st.z, st.w
            return
    if st.v == 0:
        load = m * (g + a)
        if abs(load) <= 2 * p.mu_s * n:
            st.mode = Mode.STICK
        else:
            st.mode = Mode.SLIP
    else:
        st.mode = Mode.SLIP


def _lifts(st: State, a: float, n: float, m: float, p: Params) -> bool:
    """At y = 0, u = 0 (just touching the table from above): does the object's acceleration point up?"""
    if st.v == 0 and abs(m * (p.g + a)) <= 2 * p.mu_s * n:
        return a > 0
    d = _sign(st.v) or _sign(p.g + a)
    return d * 2 * p.mu_k * n / m - p.g > 0


def slip_accel(st: State, a: float, n: float, m: float, p: Params) -> float:
    """s'' while slipping: (g + a) - sgn(v) 2 mu_k N / m, sgn(v) = sgn(g + a) from rest."""
    d = _sign(st.v) or _sign(p.g + a)
    return (p.g + a) - d * 2.0 * p.mu_k * n / m


def advance(st: State, h: float, a: float, n: float, m: float, p: Params, jaws_open: bool = False) -> Flags:
    """Advance ``st`` by ``h`` seconds with constant gripper acceleration ``a``, per-jaw normal force
    ``n`` and object mass ``m``, exactly from event to event (module docstring). ``jaws_open``: the
    jaws do not touch the object (an airborne object is dropped at once, ``n`` is taken as 0)."""
    fl = Flags()
    if jaws_open:
        n = 0.0
        if st.airborne:
            st.mode = Mode.DROPPED
            fl.dropped = True
    left = h
    for _ in range(_MAX_EVENTS):
        settle(st, a, n, m, p)
        if left <= 0:
            return fl
        mode = st.mode
        if mode in (Mode.DROPPED, Mode.LEFT):
            _gripper(st, left, a)
            return fl
        if mode is Mode.TABLE:
            t_ev, kind = _table_event(st, left, a, p)
        elif mode is Mode.STICK:
            t_ev, kind = _stick_event(st, left, a)
        else:
            t_ev, kind = _slip_event(st, left, a, n, m, p)
        dt = left if t_ev is None else t_ev
        s_before = st.s
        if mode is Mode.SLIP:
            r = slip_accel(st, a, n, m, p)
            st.s += st.v * dt + 0.5 * r * dt * dt
            st.v += r * dt
        _gripper(st, dt, a)
        if mode is Mode.TABLE:
            st.s, st.v = st.z, st.w
        if not jaws_open and abs(st.s - s_before) > SLIP_EPS_M:   # monotone between events
            fl.slipped = True
        left -= dt
        if t_ev is None:
            left = 0.0
            continue
        # the event: snap to it exactly
        if kind == "v0":
            st.v = 0.0
        elif kind == "w0":
            st.w = 0.0
            st.v = 0.0
        elif kind == "land":
            st.mode, st.s, st.v = Mode.TABLE, st.z, st.w
            fl.landed = True
        elif kind in ("down", "up"):
            st.s = p.s_down if kind == "down" else -p.s_up
            if mode is Mode.TABLE:
                st.mode = Mode.LEFT
                fl.left = True
            else:
                st.mode = Mode.DROPPED
                fl.dropped = True
    raise RuntimeError("grasp world: more than %d events in one interval" % _MAX_EVENTS)


def _gripper(st: State, dt: float, a: float) -> None:
    st.z += st.w * dt + 0.5 * a * dt * dt
    st.w += a * dt


def _earliest(*cands):
    best = (None, None)
    for t, kind in cands:
        if t is not None and (best[0] is None or t < best[0]):
            best = (t, kind)
    return best


def _table_event(st: State, horizon: float, a: float, p: Params):
    w = st.w
    t_w0 = -w / a if (w != 0 and a != 0 and _sign(a) != _sign(w)) else None
    if t_w0 is not None and t_w0 > horizon:
        t_w0 = None
    # the pads slide off the object: s = z reaches s_down (going up) or -s_up (going down)
    t_dn = first_root(p.s_down - st.z, -w, -a, horizon)
    t_up = first_root(st.z + p.s_up, w, a, horizon)
    return _earliest((t_w0, "w0"), (t_dn, "down"), (t_up, "up"))


def _stick_event(st: State, horizon: float, a: float):
    # landing: y = z - s reaches 0 from above
    return first_root(st.z - st.s, st.w, a, horizon), "land"


def _slip_event(st: State, horizon: float, a: float, n: float, m: float, p: Params):
    r = slip_accel(st, a, n, m, p)
    v = st.v
    t_v0 = -v / r if (v != 0 and r != 0 and _sign(r) != _sign(v)) else None
    if t_v0 is not None and t_v0 > horizon:
        t_v0 = None
    t_dn = first_root(p.s_down - st.s, -v, -r, horizon)
    t_up = first_root(st.s + p.s_up, v, r, horizon)
    y0, u0 = st.z - st.s, st.w - v
    t_land = first_root(y0, u0, a - r, horizon) if y0 >= 0 else None
    # landing wins a tie with a pad edge (the object is on the table, not fallen)
    return _earliest((t_land, "land"), (t_v0, "v0"), (t_dn, "down"), (t_up, "up"))
