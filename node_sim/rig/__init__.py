"""The rig: every node twin of a scene on its CAN bus(es), configured and booted.

:class:`Rig` (``node_sim.Rig``) is the public API; the rig's jobs have a module each (issue 22):

* :mod:`.api` - :class:`Rig`: arguments, life cycle (start / stop), silence faults
  (:meth:`Rig.drop_node`), introspection; it composes the parts below;
* :mod:`.buses` - ONE python-can bus object per served scene channel and the receive thread;
* :mod:`.channel` - one channel: one CANopen network of node twins on one bus object (frame
  dispatch, SYNC cycle numbering, the SYNC burst);
* :mod:`.devices` - the node twins of the scene's taxels (with their LSS slaves) or patches,
  configured with their start-up values (:mod:`node_sim.taxel.startup`,
  :mod:`node_sim.patch.startup`), renumbered over LSS;
* :mod:`.readings` - the readings X_i per cycle: an injected ``reading_source``, the grasp world,
  or the scene physics read ahead (:data:`PREFETCH_CYCLES`);
* :mod:`.drive` - the scene's gripper drive (:mod:`node_sim.gripper`) and grasp world
  (:mod:`node_sim.world_runner`).

Every name is importable from ``node_sim.rig`` as before the split (:func:`identity_serial` lives
in :mod:`node_sim.taxel.startup`).
"""

from __future__ import annotations

from ..taxel.startup import identity_serial
from .api import Rig
from .readings import PREFETCH_CYCLES, ReadingSource

__all__ = ["Rig", "identity_serial", "PREFETCH_CYCLES", "ReadingSource"]
