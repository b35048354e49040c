"""The grasp world (issue 22 part 2): an object held by friction between the gripper drive's jaws.

The twins' physics where a scene has a gripper (the scripted readings of :mod:`node_sim.physics`
stay for the other scenes). Pure modules, no CAN and no wall clock:

* :mod:`.timeline` - the task (approach, close, lift, hold, place, release): the gripper's
  piecewise-constant acceleration and the added load, in closed form;
* :mod:`.grasp` - the mechanics: stick / slip (with hysteresis) / on the table / dropped, stepped
  exactly from event to event;
* :mod:`.world` - :class:`GraspWorld`: both on the world's own clock, and the ground truth per step;
* :mod:`.coupling` - :class:`JawCoupling`: the world and a gripper drive (normal force from the
  drive's grip force through a first-order lag; ``jaw_blocked_at`` / ``part_lost`` to the drive);
* :mod:`.taxels` - what the taxels see of it (footprint pressure, position, tangential cells).

The object and its task come from a scene's ``[grasp]`` table (:mod:`taxel_net.scene_grasp`);
equations, conventions and fields: ``docs/grasp-world.md``.
"""

from .coupling import JawCoupling
from .world import DONE, IDLE, TRUTH_FIELDS, GraspWorld, Truth

__all__ = ["GraspWorld", "JawCoupling", "Truth", "TRUTH_FIELDS", "IDLE", "DONE"]
