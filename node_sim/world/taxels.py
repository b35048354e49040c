"""What the taxels see of the grasp world: each taxel's signal from one world step's truth (pure).

The grasp world (:mod:`.world`) gives per step the per-jaw normal force ``N`` (``normal_n``), the
tangential load on each jaw's pad ``T`` (``tangential_n``, down positive), the slide ``s``
(``slid_mm``) and whether the object is between the jaws (``in_grip``). The taxels of both jaws
(``jaw`` "left" / "right"; a taxel without a jaw belongs to the one pad of a one-pad sensor) sit on
identical pads in jaw-local coordinates: ``y`` is the height on the pad above its lower edge, mm
(the slip axis, vertical), ``x`` across it.

**Footprint.** The object touches each pad over ``contact_mm`` along the slip axis, centred
``grip_at_mm - s`` above the lower edge (it moves down the pad by the slid distance, so the centre's
slip stage sees the present taxels' centroid move), across the whole pad: a taxel is in the
footprint while the object is between the jaws and ``abs(y - centre) <= contact_mm / 2`` (a taxel
without ``y`` whenever the object is between the jaws).

**Signal** ``S_i`` (mV, the noise-free ``Y_i`` of eq 4; 0 outside the footprint), by what the
taxel measures - its calibration in the scene (``[kinds]`` / ``[[taxels]]``, ``docs/scene-format.md``):

| taxel | ``S_i`` in the footprint | chapter |
|---|---|---|
| a ``grip_factor`` M (the load cells, LC) | ``M N`` | eq 27b ``Y = M F_g`` |
| a tangential calibration (``slope`` m != 0, ``intercept`` c; R, TBS) | ``m F_i + c`` while the jaws press (``N > 0``), ``F_i`` = its share of ``T`` | eqs 23 / 27a |
| kind ``IR`` (presence) | ``signal_mv`` (the object is in front of it, pressed or not) | eq 1 |
| any other (C, P, uncalibrated R / TBS) | ``signal_mv N / pressure_ref_n`` (pressure grows with the normal force) | eq 1 |

``F_i``: the load is vertical, so a cell with ``axis = "x"`` carries none (``F_i = 0``: it reads its
intercept); the ``k`` cells of a pad with ``axis`` "y" or none that lie in the footprint share
``T`` equally, ``F_i = T / k``. So eq 30 ``F = (y - c) / m`` on each and eqs 24-25 / 28-29 (with
α = 0: the sum of the magnitudes) give back ``abs(T)`` per pad in raw mode, and eq 26a
``TotF_t / mu_s`` the least holding force while it sticks - which decision mode, one bit per
taxel, cannot see.

Readings: ``X_i = S_i + N_i + sigma_i eps`` with the canonical random numbers of the SYNC cycle and
the scene's faults (:func:`node_sim.physics.observe`), decided by the node's local detector
(eqs 1-4) as for every scene.
"""

from __future__ import annotations

import numpy as np

from taxel_net.errors import ParameterError
from taxel_net.scene import Scene

from .. import physics

_EDGE_TOL_MM = 1e-9          # a taxel exactly on the footprint's edge is in it


def _check(scene: Scene) -> None:
    if not isinstance(scene, Scene) or scene.grasp is None:
        raise ParameterError("scene.grasp", None, "the taxels' view of the grasp world needs a scene with [grasp]")


def _pads(scene: Scene) -> np.ndarray:
    """Pad index per taxel: 0 left / no jaw, 1 right."""
    return np.array([1 if t.jaw == "right" else 0 for t in scene.taxels], dtype=np.intp)


def footprint_mask(scene: Scene, in_grip: bool, slid_mm: float) -> np.ndarray:
    """Which taxels lie in the object's footprint (module docstring), shape (n,) bool."""
    _check(scene)
    if not in_grip:
        return np.zeros(scene.n, dtype=bool)
    g = scene.grasp
    centre = g.grip_at - float(slid_mm)
    y = physics.taxel_arrays(scene)["y"]
    inside = np.abs(y - centre) <= g.contact_mm / 2.0 + _EDGE_TOL_MM
    return np.where(np.isnan(y), True, inside)


def tangential_shares(scene: Scene, mask: np.ndarray, tangential_n: float) -> np.ndarray:
    """``F_i`` per taxel (N, down positive): the tangential load ``T`` of each pad shared equally by
    its tangential cells with a vertical axis ("y" or none) in ``mask``; 0 elsewhere."""
    a = physics.taxel_arrays(scene)
    slope = a["slope"]
    tangential = np.isfinite(slope) & (slope != 0) & np.asarray(mask, bool)
    vertical = np.array([t.axis != "x" for t in scene.taxels], dtype=bool)
    carriers = tangential & vertical
    pads = _pads(scene)
    out = np.zeros(scene.n)
    for pad in (0, 1):
        sel = carriers & (pads == pad)
        k = int(sel.sum())
        if k:
            out[sel] = float(tangential_n) / k
    return out


def taxel_signal(scene: Scene, in_grip: bool, normal_n: float, tangential_n: float, slid_mm: float) -> np.ndarray:
    """``S_i`` of every taxel (mV, scene order) for one instant of the world (module docstring)."""
    _check(scene)
    a = physics.taxel_arrays(scene)
    mask = footprint_mask(scene, in_grip, slid_mm)
    n = max(0.0, float(normal_n))
    s = np.zeros(scene.n)
    if not mask.any():
        return s
    slope, intercept, grip = a["slope"], a["intercept"], a["grip_factor"]
    is_ir = np.array([t.kind == "IR" for t in scene.taxels], dtype=bool)
    is_grip = np.isfinite(grip) & (grip != 0)
    is_tangential = ~is_grip & np.isfinite(slope) & (slope != 0)
    is_pressure = ~(is_grip | is_tangential | is_ir)
    sel = mask & is_grip
    s[sel] = grip[sel] * n                                              # eq 27b: Y = M F_g
    if n > 0:
        shares = tangential_shares(scene, mask, tangential_n)
        sel = mask & is_tangential
        c = np.where(np.isfinite(intercept), intercept, 0.0)
        s[sel] = slope[sel] * shares[sel] + c[sel]                      # eqs 23 / 27a: y = m F + c
    sel = mask & is_ir
    s[sel] = a["signal_mv"][sel]                                        # presence
    sel = mask & is_pressure
    s[sel] = a["signal_mv"][sel] * n / scene.grasp.pressure_ref_n       # pressure ~ N
    return s


def truth_signal(scene: Scene, truth) -> np.ndarray:
    """:func:`taxel_signal` of a world step's :class:`~.world.Truth`."""
    return taxel_signal(scene, truth.in_grip, truth.normal_n, truth.tangential_n, truth.slid_mm)


def truth_readings(scene: Scene, truth, cycle: int, held: dict | None = None) -> np.ndarray:
    """``X_i`` of SYNC ``cycle`` with the world in ``truth``: :func:`truth_signal` through the noise
    and faults of :func:`node_sim.physics.observe` (``held``: its stuck-reading memory)."""
    return physics.observe(scene, cycle, truth_signal(scene, truth), held)


__all__ = ["footprint_mask", "tangential_shares", "taxel_signal", "truth_signal", "truth_readings"]
