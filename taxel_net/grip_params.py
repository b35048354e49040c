"""The grip-force law's parameters (issue 23): the scene's ``[grip]`` table in typed form.

Shared by the scene loader (:mod:`taxel_net.scene_grip`, which the twins load too) and the law
itself (:mod:`fusion_center.core.grip_law`, which re-exports :class:`GripParams`): the type lives
in the shared layer as :class:`taxel_net.scene_grasp.GraspSpec` does, so that loading a scene never
imports the centre. Pure: the standard library's ``math`` / ``dataclasses`` and
:mod:`taxel_net.errors` only (the core may import it, ``tests/test_layout.py``).

Forces are **per jaw** in N (the drive's convention, 0x2101). Meaning of each field and the law
that uses them: ``docs/grip-control.md``; the table's format: ``docs/scene-format.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from taxel_net.errors import ParameterError


@dataclass(frozen=True)
class GripParams:
    """The law's gains and limits (the scene's ``[grip]`` table; per-jaw forces in N, times in s).

    Defaults suit a 100 Hz SYNC and a drive of some hundreds of N/s torque slope with a force lag
    of some tens of ms (``docs/grip-control.md`` says why each is what it is)."""

    grasp_n: float = 5.0            # the first squeeze once the object is present
    min_n: float = 0.5              # the least command while holding
    max_n: float = 100.0            # the most (the drive's range; a fragile object's limit)
    raise_fraction: float = 2.0     # a slip raises the command to max(command (1 + raise_fraction), command + raise_n)
    raise_n: float = 0.5
    settle_s: float = 0.06          # after a raise arrived (the drive's force reached it), slip raises again only after this long
    margin: float = 0.2             # the floor a slip teaches: (1 + margin) x the command the slip began under
    relax_delay_s: float = 1.0      # no probing until this long after the grasp or the last slip
    return_delay_s: float = 0.2     # no return toward the floor / target until this long after the last slip
    relax_per_s: float = 0.5        # probing (no floor learned yet): the command falls by this fraction of itself per s
    probe_headroom: float = 1.7     # decision mode probes only while max_n >= probe_headroom x the command
    return_per_s: float = 6.0       # above the floor or raw mode's target: falls by this fraction of itself per s
    safety_factor: float = 1.2      # raw mode: the target is safety_factor * T / mu (eq 26a per jaw)
    mu: float = 0.5                 # the friction coefficient of eq 26a ([forces] mu by default)
    open_n: float = 10.0            # release: opening force
    presence_cycles: int = 2        # H1 this many cycles in a row before the squeeze
    edge_fraction: float = 0.4      # the slip cue's edge: before a contact's first slip flag, a displacement
    edge_cycles: int = 2            # beyond edge_fraction x the noise band for edge_cycles cycles in a row is slip

    def __post_init__(self):
        check_params(self)


FLOAT_FIELDS = ("grasp_n", "min_n", "max_n", "raise_fraction", "raise_n", "settle_s", "margin", "relax_delay_s",
                "return_delay_s", "relax_per_s", "probe_headroom", "return_per_s", "safety_factor", "mu", "open_n",
                "edge_fraction")
INT_FIELDS = ("presence_cycles", "edge_cycles")


def check_params(p: GripParams) -> None:
    """Raise :class:`ParameterError` naming the first bad field (the scene loader names the file)."""
    for name in FLOAT_FIELDS:
        value = getattr(p, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ParameterError(name, value, "must be a finite number")
    for name in ("grasp_n", "max_n", "mu", "open_n"):
        if getattr(p, name) <= 0:
            raise ParameterError(name, getattr(p, name), "must be > 0")
    for name in ("min_n", "raise_n", "raise_fraction", "settle_s", "margin", "relax_delay_s", "return_delay_s",
                 "relax_per_s", "return_per_s"):
        if getattr(p, name) < 0:
            raise ParameterError(name, getattr(p, name), "must be >= 0")
    if p.raise_fraction == 0 and p.raise_n == 0:
        raise ParameterError("raise_n", p.raise_n, "must be > 0 when raise_fraction is 0 (a slip must raise the force)")
    if p.return_per_s < p.relax_per_s:
        raise ParameterError("return_per_s", p.return_per_s, f"must be >= relax_per_s ({p.relax_per_s:g}): probing "
                                                             "below the floor is the slow part")
    if p.probe_headroom < 1:
        raise ParameterError("probe_headroom", p.probe_headroom, "must be >= 1 (a slip must be stoppable below max_n)")
    if p.safety_factor < 1:
        raise ParameterError("safety_factor", p.safety_factor, "must be >= 1 (eq 26a's bound is the least)")
    if not p.min_n <= p.grasp_n <= p.max_n:
        raise ParameterError("grasp_n", p.grasp_n, f"must lie in [min_n, max_n] = [{p.min_n:g}, {p.max_n:g}]")
    if not 0 < p.edge_fraction <= 1:
        raise ParameterError("edge_fraction", p.edge_fraction, "must lie in (0, 1]: a fraction of the slip stage's noise "
                                                               "band (1: no cue below the band)")
    for name in INT_FIELDS:
        value = getattr(p, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ParameterError(name, value, "must be an integer >= 1")


__all__ = ["GripParams", "check_params", "FLOAT_FIELDS", "INT_FIELDS"]
