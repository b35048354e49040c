"""Grip-force control law of the fusion centre (issue 23): pure, one call per SYNC cycle.

The chapter's software "also controls the gripping force" (Grip Force and Slip Analysis in
Robotic Grasp: New Stochastic Paradigm Through Sensor Data Fusion, sec. 4.3.2 and 8): the
centre that knows whether an object is present (the HEBTEM decision, eqs 5-20), whether it
slips (sec. 4) and, from raw readings, the tangential load it carries (eqs 24-30), sets the
force the gripper squeezes with. This module is that law and nothing else: parameters, the
law's state and this cycle's findings in, the command and the new state out (no bus, no
clock, no I/O). :mod:`fusion_center.service` feeds it every closed cycle and sends the command
in the drive's RPDO; ``bench/grasp.py`` feeds it the same way without the bus. The reasoning
behind each rule and the measured behaviour: ``docs/grip-control.md``.

Forces are **per jaw** (the drive's convention, 0x2101: the normal force one jaw exerts), in N.
A positive command grips with that force, a negative one opens the jaws with that force, 0
leaves the jaws without torque. ``f.slip`` is slip **this cycle** (the caller derives it from the
slip stage, whose ``slipping`` latches until contact is lost).

Phases (``GripState.phase``):

* ``open``: nothing held; command 0. While the task asks to close and the decision has said
  "present" (H1) for ``presence_cycles`` cycles in a row, the law squeezes with ``grasp_n``
  -> ``grasp``.
* ``grasp`` / ``hold``: ``grasp`` until the first cycle the object is present and not slipping
  after the squeeze, then ``hold``. The command follows these rules, in this order:

  1. **target** = ``max(min_n, floor, safety_factor * least_hold_n)``: ``floor`` is what slips
     taught (rule 2), ``least_hold_n`` raw mode's eq 26a per jaw, ``F_g = T / mu`` (T the
     tangential load one pad carries, eqs 24-25 / 28-30; None in decision mode, which cannot see
     it). Below the target the command rises to it at once.
  2. **raise on slip**: a slipping cycle raises the command to
     ``max(command (1 + raise_fraction), command + raise_n)`` - but only once the last raise has
     **arrived** and is ``settle_s`` old: with the drive's force known (``actual_n``, 0x2101 of
     this SYNC) the settle counts from the cycle that force reached ``ARRIVED_FRACTION`` (95 %) of
     the raise or stopped rising (the drive delivers no more: its torque limit), without it from
     the send. The drive's torque slope delivers a large raise over several cycles and the jaws'
     force lag and the slide's stop take ``settle_s`` more, while the centre's slip flags trail the
     slide (the taxels see it a cycle late, the grip stage holds a flag ``slip_hold`` cycles):
     raising on that tail compounded - 3 x 3 = 9 times the force a slip began under. A raise after
     an episode's first also needs **new** evidence (``f.slip_new``: a new farthest displacement of
     the contact this cycle, not a flag the caller holds from the cycles before): a flag held past
     the settle stands for motion seen while the raised force was still arriving, which may have
     stopped since - a slide that goes on shows a new displacement. The first
     slipping cycle of an episode (no slip for ``relax_delay_s`` before it) teaches the floor
     ``(1 + margin) * command``: the command it began under, plus the margin. A new episode is the
     grasp's first slip or one ``return_delay_s`` after the last slipping cycle. In decision mode
     a floor never falls within a grasp; in raw mode, which measures the load, it gives way to
     the measured target ``relax_delay_s`` after the last slip, at the slow ``relax_per_s``.
  3. **relax** (not on a degraded or absent cycle; in raw mode only while the pads carry a load,
     a finite ``least_hold_n > 0``: an object resting on the table weighs nothing on them, and the lift to
     come needs the grip), never below ``max(floor, target)``: **return** - above a learned floor,
     ``return_delay_s`` after the last slip - by ``return_per_s`` of itself per second (back from
     a raise); otherwise - no floor learned in this grasp - from ``relax_delay_s`` after the grasp
     or the last slip by the slower ``relax_per_s``: in decision mode this is **probing** (it
     cannot see the load, so it finds the least holding force by the slip that ends the probe;
     rule 2's floor then holds it at ``1 + margin`` times that) - only while
     ``probe_headroom * command <= max_n``: a slide is stopped only by ``mu_s / mu_k`` times the
     force it began under, so a probe near a fragile object's ``max_n`` could start a slip the
     law is not allowed to stop; in raw mode it follows the
     measured target down slowly (a load that falls for a moment, the arm accelerating downward,
     comes back).
* ``release``: the task asks to release: the command is ``-open_n`` (the jaws open); once the
  task no longer says release, the law waits ``open`` again.

Safety: a cycle with missing, late or degraded taxel data (``degraded``) never lowers the
command - it holds the last one (flag ``held_degraded``); an H0 or undecided cycle while holding
does not lower it either (flag ``absent_while_held``). The command never exceeds ``max_n``
(flag ``at_max`` when a rule asked for more). The law never opens the jaws except on the task's
release.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from taxel_net.errors import ParameterError
from taxel_net.grip_params import GripParams, check_params  # noqa: F401  (the scene's [grip] table)

LAW_PHASES = ("open", "grasp", "hold", "release")
TASKS = ("open", "close", "release")  # what the task asks of the gripper this cycle
TIME_EPS_S = 1e-9                      # times summed from dt_s: 6 x 0.01 s is "60 ms" whatever the rounding
ARRIVED_FRACTION = 0.95                # a raise has arrived when the drive's force reached this share of it


@dataclass(frozen=True)
class GripState:
    """The law's state carried from cycle to cycle."""

    phase: str = "open"
    command_n: float = 0.0
    learned_n: float = 0.0          # the floor slips taught (0: none yet in this grasp)
    present_run: int = 0            # consecutive cycles with the object present
    slipping: bool = False          # the previous cycle slipped
    quiet_s: float = 0.0            # time since the grasp began or the last slipping cycle
    since_raise_s: float = math.inf  # time since the last raise on slip arrived (sent, without the drive's force)
    raise_pending_n: float = 0.0     # the last raise's command while the drive's force is on its way to it (0: none)
    actual_n: float | None = None    # the drive's force of the previous cycle (findings.actual_n)
    episode_raised: bool = False     # the current slip episode has had its first raise (later ones need new evidence)


@dataclass(frozen=True)
class GripFindings:
    """What one closed cycle gave the law."""

    task: str                       # TASKS: "close" from the task's close phase until its release
    present: bool | None            # the HEBTEM decision of the scene's rule: H1 True, H0 False, None undecided
    slip: bool                      # the centre's slip stage flags slip this cycle
    degraded: bool = False          # missing, late or degraded taxel data this cycle
    least_hold_n: float | None = None  # raw mode: eq 26a per jaw, T / mu (None: decision mode)
    dt_s: float = 0.01              # the SYNC period
    actual_n: float | None = None   # the drive's force per jaw at this SYNC (0x2101; None: not known)
    slip_new: bool | None = None    # the slip is new evidence this cycle (False: a flag held from before; None: not known)


@dataclass(frozen=True)
class GripCommand:
    """The law's output for one cycle: the per-jaw force (N; < 0 opens) and what shaped it."""

    force_n: float
    flags: tuple[str, ...] = ()


def grip_step(p: GripParams, state: GripState, f: GripFindings) -> tuple[GripCommand, GripState]:
    """One cycle of the law (module docstring): ``(command, new state)``."""
    if f.task not in TASKS:
        raise ParameterError("task", f.task, f"must be one of {TASKS}")
    if isinstance(f.dt_s, bool) or not isinstance(f.dt_s, (int, float)) or not f.dt_s > 0 or not math.isfinite(f.dt_s):
        raise ParameterError("dt_s", f.dt_s, "the SYNC period must be a finite number of seconds > 0")
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
        return GripCommand(0.0), GripState(phase="open", present_run=present_run)

    # grasp / hold
    dt = float(f.dt_s)
    before = state.command_n
    command = before
    learned = state.learned_n
    quiet = state.quiet_s + dt
    since_raise = state.since_raise_s + dt
    pending = state.raise_pending_n
    actual = f.actual_n if f.actual_n is not None and math.isfinite(f.actual_n) else None
    if pending > 0:
        if actual is None:
            pending = 0.0                             # the drive's force not known: settle from the send
        elif actual >= ARRIVED_FRACTION * pending or (state.actual_n is not None and actual <= state.actual_n):
            pending = 0.0                             # arrived, or the drive delivers no more: settle from now
            since_raise = 0.0
    least = f.least_hold_n
    carried = least is not None and math.isfinite(least) and least > 0   # raw mode: the pads carry a load
    target = max(p.min_n, p.safety_factor * least) if carried else p.min_n
    if f.slip:
        onset = math.isinf(state.since_raise_s) or state.quiet_s >= p.return_delay_s - TIME_EPS_S
        if onset:
            # a new slip episode (the first of the grasp, or return_delay_s after the last): the command failed
            learned = max(learned, (1.0 + p.margin) * before)
            flags.append("slip_onset")
        quiet = 0.0
        # a raise: the episode's first, or on new evidence once the last raise arrived and settled
        episode_raised = state.episode_raised and not onset
        if pending == 0 and since_raise >= p.settle_s - TIME_EPS_S and (not episode_raised or f.slip_new is not False):
            episode_raised = True
            command = max(command * (1.0 + p.raise_fraction), command + p.raise_n)
            since_raise = 0.0
            pending = min(command, p.max_n) if actual is not None else 0.0
            flags.append("slip_raise")
        command = max(command, target, learned)
    else:
        episode_raised = state.episode_raised
        if state.slipping:
            flags.append("stuck")
        if carried and learned > target and quiet >= p.relax_delay_s - TIME_EPS_S:
            # raw mode measures the load: a quiet while after a slip, its floor gives way to the
            # measured target (at the follow's slow rate) - a lesson from a load that has passed
            learned = max(target, learned * max(0.0, 1.0 - p.relax_per_s * dt))
        floor = max(target, learned)
        if command < floor:
            command = floor                           # the load grew (raw) or a floor was learned
        elif command > floor and (least is None or carried):     # raw: no relaxing on a load of 0 or no number
            if learned > 0:                           # back from a raise, down to the floor slips taught
                if quiet >= p.return_delay_s - TIME_EPS_S:
                    command = max(floor, command * max(0.0, 1.0 - p.return_per_s * dt))
            elif quiet >= p.relax_delay_s - TIME_EPS_S and (carried or command * p.probe_headroom <= p.max_n):
                # probing (decision: only where a slip can still be stopped below max_n) /
                # following the measured target down (raw)
                command = max(floor, command * max(0.0, 1.0 - p.relax_per_s * dt))
    if f.degraded and command < before:
        command = before
        flags.append("held_degraded")
    if not f.present and command < before:
        command = before
        flags.append("absent_while_held")
    if command > p.max_n:
        command = p.max_n
        flags.append("at_max")
    phase = "hold" if (state.phase == "hold" or (f.present and not f.slip)) else "grasp"
    return (GripCommand(command, tuple(flags)),
            GripState(phase=phase, command_n=command, learned_n=learned, present_run=present_run,
                      slipping=bool(f.slip), quiet_s=quiet, since_raise_s=since_raise, raise_pending_n=pending,
                      actual_n=actual, episode_raised=episode_raised))
