"""The gripper drive's actuator model: jaw width, torque and grip state, one SYNC step at a time.

Deliberately simple (the grasp world - mass, friction, slip - is not modelled here; it talks to the
drive through :meth:`JawAxis.jaw_blocked_at` and :meth:`JawAxis.part_lost`):

* **width** ``w`` (µm, the opening between the two jaws; the CiA 402 position) moves at the profile
  velocity 0x6081 ``v`` (µm/s): ``w <- w ∓ v·dt``, never past the stroke limits 0x607D nor, when
  closing, past the width of an object between the jaws (``w_obj``, set by the world);
* **torque** ``T`` (‰ of the rated torque 0x6076; positive closes the jaws) follows its demand
  with the torque slope 0x6087 ``s`` (‰/s): ``T <- T + clamp(T* - T, -s·dt, s·dt)``, the demand
  clamped to ±max torque 0x6072. Profile torque: ``T*`` = target torque 0x6071; the jaws move
  while nothing blocks them (closing for ``T > 0``, opening for ``T < 0``). Profile position: the
  jaws move toward the latched target; ``T* = 0`` while they move freely, ``+0x6072`` when an
  object blocks them (a position loop saturating at its torque limit);
* **stop ramp** (quick stop, fault reaction, halt): ``T* = 0`` at the same slope ``s`` (CiA 402 has
  no torque quick-stop slope: slow-down and quick-stop ramps are the same here) and no motion;
  done when ``T = 0`` (a slope of 0, which only a value that bypassed the SDO rules can give:
  ``T = 0`` at once, so the ramp always ends). **Drive function off** (any state but OPERATION
  ENABLED, QUICK STOP ACTIVE, FAULT REACTION ACTIVE): ``T = 0`` at once, no motion - the jaws let go;
* **grip force per jaw** (0.1 N, the normal force ONE jaw exerts on the part, not the sum of
  both): ``F = T · F_rated / 1000`` while the jaws press on the object (width at the object,
  ``T > 0``), else 0; ``F_rated`` = 0x2103, the per-jaw force at rated torque (0.1 N).

Grip states (0x2100, the codes of the Weiss / SCHUNK WSG grasping state): IDLE (0, nothing
happened yet), GRASPING (1, closing on the way to a part), NO_PART (2, closed to the stroke limit
without meeting a part), PART_LOST (3, the world reports the part gone while gripped; kept until
the jaws open), HOLDING (4, pressing on the part with ``T > 0``), RELEASED (5, the jaws opened
after a grip, or the force on a held part went to 0).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class GripState(enum.IntEnum):
    IDLE = 0
    GRASPING = 1
    NO_PART = 2
    PART_LOST = 3
    HOLDING = 4
    RELEASED = 5


# statusword bits 8, 14, 15 (manufacturer-specific) carry grip-state bits 0, 1, 2
GRIP_STATE_BITS = ((0, 8), (1, 14), (2, 15))


def grip_state_statusword(state: int) -> int:
    """The statusword bits (8, 14, 15) of grip state ``state`` (0..7)."""
    return sum(((state >> bit) & 1) << sw for bit, sw in GRIP_STATE_BITS)


def grip_state_of_statusword(statusword: int) -> int:
    """The grip state code in a statusword's bits 8, 14, 15."""
    return sum(((statusword >> sw) & 1) << bit for bit, sw in GRIP_STATE_BITS)


@dataclass
class Limits:
    """The drive's parameters as the OD holds them now (µm, µm/s, ‰, ‰/s, 0.1 N)."""
    min_um: float = 0.0
    max_um: float = 80000.0
    velocity_um_s: float = 50000.0
    slope_permille_s: float = 5000.0
    max_torque: float = 1000.0
    rated_force: float = 1000.0     # 0x2103, 0.1 N per jaw at 1000 ‰


def _toward(x: float, target: float, step: float) -> float:
    if x < target:
        return min(target, x + step)
    return max(target, x - step)


class JawAxis:
    """The jaw axis (see module docstring). ``width_um`` starts at the open stroke limit."""

    def __init__(self, limits: Limits | None = None, width_um: float | None = None):
        self.limits = limits or Limits()
        self.width_um = float(self.limits.max_um if width_um is None else width_um)
        self.torque = 0.0                 # ‰, actual = demand after the slope
        self.object_um: float | None = None
        self.grip_state = GripState.IDLE
        self.moving = False
        self.internal_limit = False

    # -- the world's side
    def jaw_blocked_at(self, width_um: float | None) -> None:
        """An object of ``width_um`` is between the jaws (None: nothing): closing stops there."""
        self.object_um = None if width_um is None else float(width_um)

    def part_lost(self) -> None:
        """The world reports the part slipped out: nothing blocks the jaws any more."""
        self.object_um = None
        if self.grip_state in (GripState.HOLDING, GripState.GRASPING):
            self.grip_state = GripState.PART_LOST

    @property
    def in_contact(self) -> bool:
        return self.object_um is not None and abs(self.width_um - self.object_um) < 1e-6 and self.torque > 0

    @property
    def force_per_jaw(self) -> float:
        """Grip force of one jaw on the part, 0.1 N."""
        return self.torque * self.limits.rated_force / 1000.0 if self.in_contact else 0.0

    # -- one SYNC step
    def disabled(self) -> None:
        """Drive function off: no torque, no motion."""
        self.torque = 0.0
        self.moving = False
        self.internal_limit = False
        self._grip_after(opened=False, closing=False)

    def stop_ramp(self, dt: float) -> bool:
        """Quick stop / fault reaction / halt: torque to 0 at the slope, no motion. True when done.
        A slope that is not positive (0x6087 = 0 reached the OD without the SDO's rules) stops at
        once: a fault reaction or a quick stop always ends."""
        slope = self.limits.slope_permille_s
        self.torque = _toward(self.torque, 0.0, slope * dt) if slope > 0 else 0.0
        self.moving = False
        self.internal_limit = False
        self._grip_after(opened=False, closing=False)
        return self.torque == 0.0

    def torque_step(self, dt: float, target: float) -> None:
        """Profile torque: ramp toward ``target`` (‰), move while free."""
        lim = self.limits
        demand = max(-lim.max_torque, min(lim.max_torque, target))
        self.torque = _toward(self.torque, demand, lim.slope_permille_s * dt)
        before = self.width_um
        if self.torque > 0:
            self.width_um = _toward(self.width_um, self._closed_stop(), lim.velocity_um_s * dt)
        elif self.torque < 0:
            self.width_um = _toward(self.width_um, lim.max_um, lim.velocity_um_s * dt)
        self.moving = self.width_um != before
        at_stroke = (self.torque > 0 and self.width_um <= lim.min_um) or (self.torque < 0 and self.width_um >= lim.max_um)
        self.internal_limit = demand != target or at_stroke
        self._grip_after(opened=self.width_um > before, closing=self.torque > 0)

    def position_step(self, dt: float, target_um: float) -> None:
        """Profile position: move toward ``target_um`` (already within the stroke limits)."""
        lim = self.limits
        before = self.width_um
        goal = max(target_um, self._closed_stop()) if target_um < self.width_um else target_um
        self.width_um = _toward(self.width_um, goal, lim.velocity_um_s * dt)
        self.moving = self.width_um != before
        blocked = target_um < self.width_um and self.object_um is not None and self.width_um <= self.object_um
        self.torque = _toward(self.torque, lim.max_torque if blocked else 0.0, lim.slope_permille_s * dt)
        self.internal_limit = blocked
        self._grip_after(opened=self.width_um > before, closing=False)   # a move is no grasp: contact -> HOLDING

    def _closed_stop(self) -> float:
        lim = self.limits
        if self.object_um is not None and self.object_um >= lim.min_um:
            return min(self.object_um, self.width_um) if self.width_um >= self.object_um else lim.min_um
        return lim.min_um

    def _grip_after(self, opened: bool, closing: bool) -> None:
        g = GripState
        state = self.grip_state
        if opened:
            if state is not g.IDLE:
                self.grip_state = g.RELEASED
            return
        if state is g.PART_LOST:
            return
        if self.in_contact:
            self.grip_state = g.HOLDING
        elif state is g.HOLDING:
            self.grip_state = g.RELEASED        # the force on the part went to 0
        elif closing and self.width_um <= self.limits.min_um and self.object_um is None:
            self.grip_state = g.NO_PART
        elif closing and self.moving:
            self.grip_state = g.GRASPING
