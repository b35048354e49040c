"""The scene's grip-force law (issue 23): the ``[grip]`` table -> ``Scene.grip``.

``[grip]`` holds the gains and limits of the centre's grip-force law
(:mod:`fusion_center.core.grip_law`, ``docs/grip-control.md``) as a
:class:`taxel_net.grip_params.GripParams` (the law's own type, re-exported there). Every field is
optional; the table's presence switches the law on for the scene's gripper.

Every bad value is refused in one line naming the file, ``grip.<field>``, the value and what is
allowed (:class:`SceneError`; the CLIs exit 2): a wrong type, a value outside the law's domain
(:func:`taxel_net.grip_params.check_params`), and the cross-checks with the rest of the scene:

* ``[grip]`` needs ``[gripper]`` (the drive the law commands);
* ``max_n`` and ``open_n`` (per jaw) at most the drive's largest force per jaw,
  ``rated_force_n * max_torque_permille / 1000`` (0x2103 x 0x6072: the drive clamps beyond it);
  ``max_n`` defaults to that force;
* ``mu`` (eq 26a's friction coefficient) defaults to ``[forces] mu``.
"""

from __future__ import annotations

from dataclasses import fields

from taxel_net.errors import ParameterError, SceneError
from taxel_net.grip_params import FLOAT_FIELDS, INT_FIELDS, GripParams
from taxel_net.scene_fields import Where, integer, number, table

GRIP_KEYS = tuple(f.name for f in fields(GripParams))


def drive_max_force_n(gripper) -> float:
    """The drive's largest grip force per jaw, N: 0x2103 (per jaw at 1000 ‰) x 0x6072 / 1000."""
    return gripper.rated_force_n * gripper.max_torque_permille / 1000.0


def load_grip(sp: str, raw, gripper, forces_mu: float) -> GripParams:
    """The ``[grip]`` table of scene file ``sp`` -> GripParams; ``gripper`` is the scene's
    :class:`taxel_net.gripper.GripperSpec` (None: no drive, refused), ``forces_mu`` its
    ``[forces] mu``. SceneError naming ``grip.<field>`` on any bad value."""
    g = table(Where(sp), "grip", raw, GRIP_KEYS)
    w = Where(sp, "grip")
    if gripper is None:
        Where(sp).fail("grip", "{...}", "needs a [gripper] table: the drive the grip-force law commands")
    vals: dict = {}
    for k in FLOAT_FIELDS:
        if k in g:
            vals[k] = number(w, k, g[k])
    for k in INT_FIELDS:
        if k in g:
            vals[k] = integer(w, k, g[k])
    top = drive_max_force_n(gripper)
    vals.setdefault("mu", forces_mu)
    vals.setdefault("max_n", top)
    # the default opening force (10 N) on a drive that cannot give it: the drive's largest, not an error
    # the scene never asked for (2026-11-30, stop 32: it was taken unchecked)
    if "open_n" not in vals and GripParams().open_n > top:
        vals["open_n"] = top
    for k in ("max_n", "open_n"):
        if k in vals and vals[k] > top * (1 + 1e-12):
            w.fail(k, vals[k], f"must not exceed the drive's largest force per jaw, {top:g} N (gripper.rated_force_n "
                               f"{gripper.rated_force_n:g} x max_torque_permille {gripper.max_torque_permille} / 1000)")
    try:
        return GripParams(**vals)
    except ParameterError as exc:
        origin = "" if exc.name in g or exc.name not in ("max_n", "mu") else (
            " (the drive's largest force per jaw)" if exc.name == "max_n" else " ([forces] mu)")
        raise SceneError(sp, f"grip.{exc.name}", exc.value, exc.allowed + origin) from None


__all__ = ["GRIP_KEYS", "drive_max_force_n", "load_grip"]
