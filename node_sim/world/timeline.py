"""The task's timeline: the gripper's vertical motion and the object's added load, piece by piece.

Time ``t`` (s) runs from the task's start (the drive's first OPERATION ENABLED, see
:class:`node_sim.world.coupling.JawCoupling`). The phases of :class:`taxel_net.scene_grasp.GraspSpec`
follow each other; within them the gripper's acceleration is **piecewise constant** (the lift's and
the place's trapezoidal velocity profiles, the hold's square-wave shaking), so the timeline is a list
of :class:`Piece` s - constant acceleration ``a`` and added mass - with the gripper's height ``z`` and
velocity ``w`` at each piece's start computed in closed form (a still piece has ``w = 0`` exactly:
no velocity drift from summing ramps). After the last phase the gripper stands still ("done").
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Iterator

from taxel_net.scene_grasp import GraspSpec, PhaseSpec, profile_times

DONE = "done"


@dataclass(frozen=True)
class Piece:
    """[t0, t1) of constant gripper acceleration ``a`` (m/s², up positive) and added mass."""

    t0: float
    t1: float
    phase: str
    a: float
    z0: float            # gripper height at t0, m (0: the object's resting height on the table)
    w0: float            # gripper velocity at t0, m/s
    load_kg: float       # added to the object (hold's load), from its time on

    def at(self, t: float) -> tuple[float, float]:
        """(z, w) at ``t`` within the piece."""
        tau = t - self.t0
        return self.z0 + self.w0 * tau + 0.5 * self.a * tau * tau, self.w0 + self.a * tau


def _move(h_m: float, accel: float, speed: float, duration: float, sign: float, z0: float) -> list:
    """Relative pieces (t0, t1, a, z0, w0) of a trapezoidal move of ``sign * h_m`` from ``z0``."""
    ta, tc = profile_times(h_m, accel, speed)
    a = sign * accel
    v = a * ta
    z1 = z0 + 0.5 * a * ta * ta
    z2 = z1 + v * tc
    out = [(0.0, ta, a, z0, 0.0)]
    if tc > 0:
        out.append((ta, ta + tc, 0.0, z1, v))
    out.append((ta + tc, 2 * ta + tc, -a, z2, v))
    if 2 * ta + tc < duration:
        out.append((2 * ta + tc, duration, 0.0, z0 + sign * h_m, 0.0))
    return [p for p in out if p[1] > p[0]]


def _shake(p: PhaseSpec, z: float) -> list:
    """Relative pieces of the hold phase: still, shaking (sgn(cos) square wave), still."""
    out = []
    if p.shake_m_s2 <= 0:
        return [(0.0, p.duration_s, 0.0, z, 0.0)]
    amp, period = p.shake_m_s2, 1.0 / p.shake_hz
    q = period / 4.0
    start = p.shake_at_s
    if start > 0:
        out.append((0.0, start, 0.0, z, 0.0))
    for k in range(p.shake_cycles):
        c = start + k * period
        # +A for a quarter period, -A for half, +A for a quarter: back at z, at rest
        out.append((c, c + q, amp, z, 0.0))
        out.append((c + q, c + 3 * q, -amp, z + 0.5 * amp * q * q, amp * q))
        out.append((c + 3 * q, c + period, amp, z + 0.5 * amp * q * q, -amp * q))
    end = start + p.shake_cycles * period
    if end < p.duration_s:
        out.append((end, p.duration_s, 0.0, z, 0.0))
    return out


class Timeline:
    """The task's pieces (module docstring) and queries by time."""

    def __init__(self, spec: GraspSpec):
        self.spec = spec
        pieces: list[Piece] = []
        self.phase_starts: dict[str, float] = {}
        t = 0.0
        z = 0.0
        load = 0.0
        lift_h = 0.0
        for p in spec.phases:
            self.phase_starts[p.name] = t
            if p.name == "lift":
                lift_h = p.height_mm / 1000.0
                rel = _move(lift_h, p.accel_m_s2, p.speed_m_s, p.duration_s, +1.0, z)
            elif p.name == "place":
                rel = _move(p.height_mm / 1000.0, p.accel_m_s2, p.speed_m_s, p.duration_s, -1.0, z)
            elif p.name == "hold":
                rel = _shake(p, z)
            else:
                rel = [(0.0, p.duration_s, 0.0, z, 0.0)]
            load_at = p.load_at_s if p.name == "hold" and p.load_kg > 0 else None
            for r0, r1, a, pz, pw in rel:
                piece = Piece(t + r0, t + r1, p.name, a, pz, pw, load)
                if load_at is not None and r0 <= load_at < r1:
                    if load_at > r0:
                        pieces.append(Piece(t + r0, t + load_at, p.name, a, pz, pw, load))
                        pz, pw = piece.at(t + load_at)
                    load += p.load_kg
                    load_at = None
                    piece = Piece(t + max(r0, p.load_at_s), t + r1, p.name, a, pz, pw, load)
                pieces.append(piece)
            if load_at is not None:          # load_at_s == duration_s: from the phase's end on
                load += p.load_kg
            t += p.duration_s
            if p.name == "lift":
                z = z + lift_h
            elif p.name == "place":
                z = z - p.height_mm / 1000.0
        self.end = t
        self.final_z = z
        self.final_load = load
        self.lift_height = lift_h
        self._pieces = pieces
        self._starts = [pc.t0 for pc in pieces]

    def phase_at(self, t: float) -> str:
        """The phase at task time ``t`` (``t`` in [start, end) of a phase; ``done`` from the end on)."""
        if t >= self.end:
            return DONE
        i = bisect.bisect_right(self._starts, t) - 1
        return self._pieces[max(i, 0)].phase

    def pieces(self, t0: float, t1: float) -> Iterator[Piece]:
        """The pieces covering [t0, t1), clipped to it (their z0, w0 at the clipped start)."""
        if t1 <= t0:
            return
        i = max(bisect.bisect_right(self._starts, t0) - 1, 0)
        while i < len(self._pieces):
            pc = self._pieces[i]
            if pc.t0 >= t1:
                return
            a0, a1 = max(pc.t0, t0), min(pc.t1, t1)
            if a1 > a0:
                z, w = pc.at(a0)
                yield Piece(a0, a1, pc.phase, pc.a, z, w, pc.load_kg)
            i += 1
        if t1 > self.end:
            a0 = max(self.end, t0)
            yield Piece(a0, t1, DONE, 0.0, self.final_z, 0.0, self.final_load)
