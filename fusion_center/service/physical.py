"""Physical evaluation of a cycle: forces, contact area, contact type, slip (sec. 4-7).

* forces (sec. 4.1-4.2, 7): need the readings X_i, which travel on the bus only in raw mode.
  In decision mode a node sends only u_i (1 byte), so no force, grip limit or load is
  computable and the stage is skipped (``stages_skipped`` says so). In raw mode, with
  Y = X - N_i (eq 4), over the taxels deciding "present" (a cell deciding "absent" carries
  no force): tangential cells (non-zero slope) F = (Y - c)/m (eq 30); the total tangential
  force is eqs 24-25 over the cells, or - when every tangential cell has a gripper ``jaw`` and
  ``axis`` - eqs 28a/28b/29 per jaw and their mean (``forces.gripper_tangential``);
  load cells (``grip_factor`` M) give the grip force F_g = Y/M (eq 27b, mean over the jaws);
  the grip-force limit F_g^cal = TotF_t / mu (eq 26a) and the maximum load W = 2 mu F_g^cal
  (eq 26b).
* area (sec. 4.3.2, 6.2.3.3, eq 35): convex hull of the scene coordinates of the taxels
  deciding "present" - computable from u_i alone (cached per present set).
* contact type (sec. 5.2, eqs 34a/34b, Table 1): t_c = present / n_received and
  fp_c = area / area of the hull of all taxels;
  :func:`fusion_center.core.contact.classify_ratio` (scalar, same class boundaries as
  :func:`~fusion_center.core.contact.classify`).
* slip (sec. 4): :class:`fusion_center.core.slip.SlipTracker`, motion criterion over the centroid
  of the present taxels, plus the force criterion TotF_t > mu F_g when raw-mode forces give
  both a total tangential force and a load-cell grip force. A cycle that did not receive all the
  taxels present in the contact's last observed cycle (its frames lost or late; a part of the
  footprint's centroid would jump) did not observe the contact: ``observed`` False, the
  episode goes on for at most ``max_unobserved`` (10) cycles
  (:meth:`~fusion_center.core.slip.SlipTracker.unobserved`) - not "contact ended", which took the
  reference again wherever a sliding contact had got to and hid the slip under way.

Area and contact type depend only on the decision vector: the pipeline caches them per vector.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import contact, forces, geometry
from ..core.forces import CycleForces
from taxel_net.scene import Scene
from .records import jsonable


class PhysicalEvaluation:
    """The physical quantities of one scene's cycles; stateful only through the slip tracker
    (``slip``: None unless ``slip`` is asked for and every taxel has coordinates)."""

    def __init__(self, scene: Scene, labels: list, noise: np.ndarray, *, slip: bool):
        self.scene = scene
        self.labels = labels
        self.n = scene.n
        self.noise = noise
        taxels = scene.taxels
        self.slope = np.array([t.slope if t.slope is not None else 0.0 for t in taxels], dtype=float)
        self.intercept = np.array([t.intercept if t.intercept is not None else 0.0 for t in taxels],
                                  dtype=float)
        self.tangential = self.slope != 0.0
        self.grip_factor = np.array([t.grip_factor if t.grip_factor else 0.0 for t in taxels], dtype=float)
        self.load_cells = self.grip_factor != 0.0
        self.jaws = self._jaw_layout(taxels)
        self.layout_forces = forces.LayoutForces(self.slope, self.intercept, self.grip_factor, jaws=self.jaws,
                                                 inclusion_angle=math.radians(scene.forces.inclusion_angle_deg))
        has_xy = all(t.x is not None and t.y is not None for t in taxels)
        self.xy = np.array([[t.x, t.y] for t in taxels], dtype=float) if has_xy else None
        self.total_area = geometry.contact_area(self.xy) if has_xy and self.n >= 3 else 0.0
        self._areas: dict[bytes, float] = {}
        # the taxels' distinct locations sorted once: a cycle's area and centroid from its mask
        self.locations = geometry.Locations(self.xy) if has_xy else None
        self.slip = None
        if slip and self.xy is not None:
            from ..core.slip import SlipTracker

            self.slip = SlipTracker(scene.forces.mu, noise_band=self._noise_band(),
                                    period=scene.bus.sync_period_ms * 1e-3)
        self._last_slip_t: float | None = None
        self._contact_mask: np.ndarray | None = None  # the taxels present in the contact's last observed cycle

    @staticmethod
    def _jaw_layout(taxels):
        """Gripper layout (sec. 3.2, 7.2) when every tangential cell has a jaw and an axis:
        {jaw: (indexes of its y-axis cells, indexes of its x-axis cells)}, else None."""
        cells = [(i, t) for i, t in enumerate(taxels) if t.slope is not None and t.slope != 0.0]
        if not cells or any(t.jaw is None or t.axis is None for _, t in cells):
            return None
        layout: dict[str, tuple[list[int], list[int]]] = {}
        for i, t in cells:
            ys, xs = layout.setdefault(t.jaw, ([], []))
            (ys if t.axis == "y" else xs).append(i)
        return {jaw: (np.array(ys, dtype=np.intp), np.array(xs, dtype=np.intp)) for jaw, (ys, xs) in layout.items()}

    def _noise_band(self) -> float:
        """Half the smallest distance between distinct taxel locations: one taxel pitch of
        centroid motion is slip, less is the staircase of the taxel grid."""
        from scipy.spatial import cKDTree

        pts = np.unique(self.xy, axis=0)
        if len(pts) < 2:
            return 1.0
        # nearest distinct neighbour of every location by k-d tree: O(n log n) time, O(n) memory
        # (the pairwise distance matrix took 400 MB at 4,096 taxels)
        d, _ = cKDTree(pts).query(pts, k=2)
        return float(d[:, 1].min()) / 2.0

    def area(self, present_mask: np.ndarray, present: int) -> float:
        """Eq 35 on the convex hull of the ``present`` taxels of ``present_mask`` (cached per
        pattern: contacts repeat)."""
        if present < 3:
            return 0.0  # eq 35 of fewer than 3 points is 0 (geometry.contact_area: no polygon), no hull needed
        key = present_mask.tobytes()
        area = self._areas.get(key)
        if area is None:
            if len(self._areas) > 1024:
                self._areas.clear()
            area = self._areas[key] = self.locations.contact_area(present_mask)
        return area

    def force_totals(self, readings: np.ndarray, present_mask: np.ndarray) -> CycleForces:
        """Raw-mode forces of one cycle (module docstring: eqs 30, 24-25 or 28-29, 27b) through
        the layout's :class:`~fusion_center.core.forces.LayoutForces` (checked once, float
        arithmetic per cycle): what the slip stage and the grip law need - ``total`` (TotF_t) and
        ``grip`` (F_g) - before the command; :meth:`forces_record` makes the record's part after."""
        y = (readings - self.noise).tolist()  # Y = X - N (eq 4)
        used = (present_mask & ~np.isnan(readings)).tolist()  # a cell deciding "absent" carries no force
        return self.layout_forces.cycle(y, used)

    def forces_record(self, cycle: CycleForces) -> dict:
        """The record's ``forces`` of a cycle's :meth:`force_totals` (eqs 26a, 26b added here)."""
        scene = self.scene
        labels = self.labels
        mu = scene.forces.mu
        out: dict = {"unit": scene.forces.unit}
        out["per_taxel"] = {str(labels[i]): jsonable(f) for i, f in cycle.per_cell}
        total = cycle.total
        if total is not None:
            if cycle.per_jaw is not None:
                out["tangential_per_jaw"] = {jaw: jsonable(v) for jaw, v in cycle.per_jaw.items()}
            out["total_tangential"] = jsonable(total)
        if cycle.grip is not None:
            out["grip_force"] = jsonable(cycle.grip)
            out["grip_force_per_cell"] = {str(labels[i]): jsonable(f)
                                          for i, f in zip(self.layout_forces.load_cells, cycle.grip_per_cell)}
        if total is not None:
            limit = forces.grip_force_limit(total, mu)  # eq 26a
            out["grip_force_limit"] = jsonable(limit)
            out["max_load"] = jsonable(forces.max_load(limit, mu))  # eq 26b
        return out

    def forces(self, readings: np.ndarray, present_mask: np.ndarray) -> tuple[dict, float | None, float | None]:
        """Raw-mode forces of one cycle: (the record's ``forces``, TotF_t, F_g)."""
        cycle = self.force_totals(readings, present_mask)
        return self.forces_record(cycle), cycle.total, cycle.grip

    def contact_fields(self, present: int, n_received: int, area: float | None) -> tuple:
        """(key, value) pairs of the contact type (eqs 34a/34b): t_c, contact_type and, with an
        area and a hull of all taxels, fp_c, contact_type_fp (``n_received`` > 0)."""
        contact_fields: list[tuple[str, object]] = []
        t_c = contact.taxel_count_ratio(present, n_received)
        contact_fields += [("t_c", jsonable(t_c)), ("contact_type", contact.classify_ratio(t_c).value)]
        if area is not None and self.total_area > 0:
            fp_c = contact.friction_plane_ratio(min(area, self.total_area), self.total_area)
            contact_fields += [("fp_c", jsonable(fp_c)), ("contact_type_fp", contact.classify_ratio(fp_c).value)]
        return tuple(contact_fields)

    def slip_record(self, t_seconds: float, present_mask: np.ndarray, total_tangential: float | None,
                    grip_force: float | None, cycle: int, centroid: np.ndarray | None = None,
                    received: np.ndarray | None = None) -> dict | None:
        """The cycle's slip state (``slip`` set), or None for a cycle not later than the last
        one fed (the tracker needs increasing times). ``centroid``: ``locations.centroid`` of
        ``present_mask`` when the caller has it (the pipeline keeps it per decision vector).
        ``received``: the taxels whose u_i / X_i the cycle has; a cycle that did not receive every
        taxel present in the contact's last observed cycle did not observe the contact
        (``observed`` False: :meth:`SlipTracker.unobserved`, the episode goes on for at most its
        ``max_unobserved`` cycles) - a lost or late cycle is no "contact ended", and a part of the
        footprint no motion."""
        if self._last_slip_t is not None and t_seconds <= self._last_slip_t:
            return None
        self._last_slip_t = t_seconds
        if centroid is None:
            centroid = self.locations.centroid(present_mask)
        contact_mask = self._contact_mask
        # observed: every taxel of the contact's last observed cycle received (a part of them gives
        # the centroid of a part: a jump of up to the footprint's size, no motion)
        observed = received is None or contact_mask is None or bool(received[contact_mask].all())
        if not observed:
            state = self.slip.unobserved(t_seconds)
        elif total_tangential is not None and grip_force is not None:
            state = self.slip.update_centroid(t_seconds, centroid, total_tangential, grip_force)
        else:
            state = self.slip.update_centroid(t_seconds, centroid)
        if observed or not state.contact:  # (unobserved too long: the tracker ended the contact)
            self._contact_mask = present_mask if state.contact else None
        return {
            "contact": state.contact,
            "observed": observed,
            "slipping": state.slipping,
            "criterion": state.criterion,
            "force_ratio": jsonable(state.force_ratio),
            "onset_cycle": None if state.onset_index is None else cycle - (state.cycle - state.onset_index),
            "displacement": jsonable(state.displacement),
            "speed": jsonable(state.speed),
            "distance": jsonable(state.distance),
        }
