"""The grasp world and a gripper drive: :class:`JawCoupling`.

Once per world step (the world's own clock, the scene's SYNC period - not the master's SYNCs), the
coupling reads the drive and steps the world:

* the task's timeline starts the first time the drive is in OPERATION ENABLED (not when the
  process starts: every master meets the whole task, its approach of at least 1 s included);
* when the approach ends the object is between the jaws: the drive is told
  ``jaw_blocked_at(size_mm)`` (closing jaws stop there, the drive's force builds up against it).
  Jaws already narrower than the object then cannot take it: it stays on the table, never gripped
  (``missed``);
* the jaws touch the object while it is between them and the drive's width is at most its size;
  the **normal force** per jaw ``N`` then follows the drive's grip force ``F`` (0x2101 before
  rounding: its torque through the slope 0x6087, max torque 0x6072 and the stroke 0x607D are the
  drive's) through a first-order lag of time constant ``tau`` (``force_lag_ms``), exact for ``F``
  held over the step: ``N <- F + (N - F) exp(-dt / tau)``; while they do not touch, ``N = 0`` at
  once (and an object in the air is dropped);
* when the object is lost - dropped, or left behind on the table by pads that slid off it - the
  drive is told ``part_lost()`` (grip state PART_LOST) once.

The drive is anything with the world's interface of ``docs/gripper-drive.md`` (:class:`DriveLike`):
:class:`node_sim.gripper.drive.GripperDrive`, or a fake in tests. ``lock``: held around each step
(a :class:`node_sim.gripper.host.DriveHost`'s ``lock``: the drive's receive thread must not run
meanwhile).
"""

from __future__ import annotations

import contextlib
import math
from typing import Protocol

from .grasp import Mode
from .world import GraspWorld, Truth

OPERATION_ENABLED = "OPERATION ENABLED"      # cia402.State.OPERATION_ENABLED.label
WIDTH_TOL_MM = 1e-6                          # the drive's width is µm floats: "at the object" within 1 nm


class DriveLike(Protocol):
    """The world's interface of a gripper drive (``docs/gripper-drive.md``)."""

    @property
    def grip_force_n(self) -> float: ...

    @property
    def width_mm(self) -> float: ...

    @property
    def cia402_state(self) -> str: ...

    def jaw_blocked_at(self, width_mm: float | None) -> None: ...

    def part_lost(self) -> None: ...


class JawCoupling:
    """A :class:`GraspWorld` driven by a gripper drive (module docstring)."""

    def __init__(self, world: GraspWorld, drive: DriveLike, lock=None):
        self.world = world
        self.drive = drive
        self.lock = lock if lock is not None else contextlib.nullcontext()
        tau = world.spec.force_lag_ms / 1000.0
        self.decay = math.exp(-world.step_s / tau) if tau > 0 else 0.0
        self.normal_n = 0.0
        self.between = False             # the object is between the jaws (the drive was told)
        self.missed = False              # the jaws were too narrow when the approach ended
        self.lost_told = False
        self._close_at = world.timeline.phase_starts["close"]

    def step(self) -> Truth:
        """One world step (module docstring); returns its truth."""
        with self.lock:
            return self._step()

    def _step(self) -> Truth:
        world, drive, size = self.world, self.drive, self.world.spec.size_mm
        if not world.started and drive.cia402_state == OPERATION_ENABLED:
            world.start()
        t = world.task_s
        if t is not None and not (self.between or self.missed) and t >= self._close_at - 1e-9 * world.step_s:
            if drive.width_mm >= size - WIDTH_TOL_MM:
                drive.jaw_blocked_at(size)
                self.between = True
            else:
                self.missed = True
                world.leave_behind()
        gone = world.state.mode in (Mode.DROPPED, Mode.LEFT)
        touching = self.between and not gone and drive.width_mm <= size + WIDTH_TOL_MM
        if touching:
            f = max(0.0, float(drive.grip_force_n))
            self.normal_n = f + (self.normal_n - f) * self.decay
        else:
            self.normal_n = 0.0
        truth = world.step(self.normal_n, jaws_open=not touching)
        if self.between and not self.lost_told and world.state.mode in (Mode.DROPPED, Mode.LEFT):
            drive.part_lost()
            self.lost_told = True
        return truth


__all__ = ["JawCoupling", "DriveLike", "OPERATION_ENABLED"]
