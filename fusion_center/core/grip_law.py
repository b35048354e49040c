"""Grip-force control law of the fusion centre (issue 23): pure, one call per SYNC cycle.

The chapter's software "also controls the gripping force" (Grip Force and Slip Analysis in
Robotic Grasp: New Stochastic Paradigm Through Sensor Data Fusion, sec. 4.3.2 and 8): the
centre that knows whether an object is present (the HEBTEM decision, eqs 5-20), whether it
slips (sec. 4) and, from raw readings, the tangential load it carries (eqs 24-30), sets the
force the gripper squeezes with. This module is that law and nothing else: parameters, the
law's state and this cycle's findings in, the command and the new state out (no bus, no
clock, no I/O). :mod:`fusion_center.service` feeds it every closed cycle and sends the command
in the drive's RPDO; ``bench/grasp.py`` feeds it the same way without the bus.

Forces are **per jaw** (the drive's convention, 0x2101: the normal force one jaw exerts), in N.
A positive command grips with that force, a negative one opens the jaws with that force, 0
leaves the jaws without torque.

Phases of the law (``GripState.phase``):

* ``open``: nothing held. While the task asks to close and the decision has said "present"
  (H1) for ``presence_cycles`` cycles in a row, the law squeezes with ``grasp_n`` -> ``grasp``.
* ``grasp`` / ``hold``: ``grasp`` until the first cycle the object is present and not slipping
  after the squeeze, then ``hold``. Every cycle the command goes toward the **least safe force**

      target = max(min_n, learned_n, safety_factor * least_hold_n)

  where ``least_hold_n`` is the raw-mode estimate of eq 26a per jaw, ``F_g = T / mu`` (T the
  tangential load one pad carries, eqs 24-25/28-30; None in decision mode, which cannot see
  it) and ``learned_n`` the force at which the last slip stopped (decision mode learns the
  least holding force from slip). Above the target the command relaxes at most ``relax_n_s``
  N/s (slowly: a load that grows while relaxing is caught by the next slip); below it, it rises
  to the target at once.
* **raise on slip**: a cycle whose slip stage says "slipping" raises the command by
  ``max(raise_fraction * command, raise_n)`` (never below the target); the first cycle without
  slip after slipping stores the command as ``learned_n``.
* ``release``: the task asks to release: the command is ``-open_n`` (the jaws open).

Safety: a cycle with missing, late or degraded taxel data (``degraded``) never lowers the
command - it holds the last one (flag ``held_degraded``); an H0 or undecided cycle while holding
does not open the jaws either (flag ``absent_while_held``). The command never exceeds ``max_n``
(flag ``at_max`` when it would). The law never opens the jaws except on the task's release.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from taxel_net.errors import ParameterError
from taxel_net.grip_params import GripParams, check_params  # noqa: F401  (the scene's [grip] table)

LAW_PHASES = ("open", "grasp", "hold", "release")
TASKS = ("open", "close", "release")  # what the task asks of the gripper this cycle


@dataclass(frozen=True)
class GripState:
    """The law's state carried from cycle to cycle."""

    phase: str = "open"
    command_n: float = 0.0
    learned_n: float = 0.0          # the force at which the last slip stopped (0: none yet)
    present_run: int = 0            # consecutive cycles with the object present
    slipping: bool = False          # the previous cycle slipped


@dataclass(frozen=True)
class GripFindings:
    """What one closed cycle gave the law."""

    task: str                       # TASKS: "close" from the task's close phase until its release
    present: bool | None            # the HEBTEM decision of the scene's rule: H1 True, H0 False, None undecided
    slip: bool                      # the centre's slip stage flags slip this cycle
    degraded: bool = False          # missing, late or degraded taxel data this cycle
    least_hold_n: float | None = None  # raw mode: eq 26a per jaw, T / mu (None: decision mode)
    dt_s: float = 0.01              # the SYNC period


@dataclass(frozen=True)
class GripCommand:
    """The law's output for one cycle: the per-jaw force (N; < 0 opens) and what shaped it."""

    force_n: float
    flags: tuple[str, ...] = ()


def grip_step(p: GripParams, state: GripState, f: GripFindings) -> tuple[GripCommand, GripState]:
    """One cycle of the law (module docstring): ``(command, new state)``."""
    if f.task not in TASKS:
        raise ParameterError("task", f.task, f"must be one of {TASKS}")
    flags: list[str] = []
    present_run = state.present_run + 1 if f.present else 0
    if f.task == "release" or state.phase == "release":
        if f.task != "release":  # released: wait open until the task closes again
            return GripCommand(0.0), GripState(phase="open", present_run=present_run)
        return GripCommand(-p.open_n), GripState(phase="release", present_run=present_run)
    if state.phase == "open":
        if f.task == "close" and present_run >= p.presence_cycles:
            command = min(max(p.grasp_n, p.min_n), p.max_n)
            return (GripCommand(command, ("grasp",)),
                    GripState(phase="grasp", command_n=command, present_run=present_run))
        return GripCommand(0.0), replace(state, present_run=present_run, slipping=False)

    # grasp / hold
    command = state.command_n
    learned = state.learned_n
    target = max(p.min_n, learned)
    if f.least_hold_n is not None and math.isfinite(f.least_hold_n) and f.least_hold_n > 0:
        target = max(target, p.safety_factor * f.least_hold_n)
    if f.slip:
        command = max(command + max(p.raise_fraction * command, p.raise_n), target)
        flags.append("slip_raise")
    else:
        if state.slipping:
            learned = command
            target = max(target, learned)
            flags.append("stuck")
        if command < target:
            command = target
        else:
            command = max(target, command - p.relax_n_s * f.dt_s)
    if f.degraded and command < state.command_n:
        command = state.command_n
        flags.append("held_degraded")
    if not f.present and state.phase in ("grasp", "hold"):
        flags.append("absent_while_held")
        command = max(command, state.command_n)
    if command > p.max_n:
        command = p.max_n
        flags.append("at_max")
    phase = "hold" if (state.phase == "hold" or (f.present and not f.slip)) else "grasp"
    return (GripCommand(command, tuple(flags)),
            GripState(phase=phase, command_n=command, learned_n=learned, present_run=present_run,
                      slipping=bool(f.slip)))
