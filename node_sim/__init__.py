"""taxel-can node firmware twins: CANopen taxel nodes running the chapter's local detector.

Public API (``docs/api.md``): :class:`Rig` (every node twin of a scene on its CAN bus(es)),
:class:`TaxelNode` (one node twin) and :mod:`physics` (the simulated readings and ground
truth). They are imported on first use (PEP 562): ``import node_sim.physics`` loads neither
python-can nor canopen.

Layout: the layout is the protocol. As in the ``canopen`` package (``nmt``, ``sdo``, ``pdo``,
``sync``, ``emcy``, ``lss``), one module per CANopen service the twins implement, each owning that
service's state and serving every device kind; :class:`TaxelNode` composes them:

* :mod:`.nmt` - NMT slave: states, boot-up, start/stop/pre-operational/resets;
* :mod:`.heartbeat` - heartbeat producer (0x1017) and consumer (0x1016);
* :mod:`.sdo` - SDO server: canopen's server behind the CiA 301 checks, abort codes;
* :mod:`.pdo` - TPDO engine: SYNC-driven (types 0..240, SYNC start value) and event-driven
  (254/255, inhibit time, event timer) TPDOs;
* :mod:`.rpdo` - RPDO engine: receive PDOs applied at the next SYNC (types 0..240) or at once
  (254/255), length errors (EMCY 0x8210); used by the gripper drive;
* :mod:`.sync` - SYNC consumer (0x1005): what a SYNC triggers;
* :mod:`.emcy` - EMCY producer, error register 0x1001, error history 0x1003;
* :mod:`.lss` - the LSS slave (CiA 305: switch state, configure node-ID and bit timing, store,
  inquire, identify, Fastscan);
* :mod:`.od` - the object dictionary glue (the EDS ``eds/taxel_node.eds``, canopen's
  ``LocalNode``, start-up values);
* :mod:`.node` - :class:`TaxelNode`, the services composed (the other device kinds reuse it);
  :mod:`.link` - a node's channel (send, SYNC bursts, timers).

Each device kind has its package beside them (issue 22), as canopen parts its ``sdo`` / ``pdo``:

* :mod:`.taxel` - the taxel node: its application :mod:`.taxel.detector` (the local detector of
  the chapter, eqs 1-4, u_i = ±1 from X_i − N_i ≥ ζ; also as 0x2003 with its cycle tag;
  sensor-fault checks; its analog input, X_i in mV) and its start-up values
  :mod:`.taxel.startup`;
* :mod:`.patch` - the patch node (issue 14): many taxels behind one node (``eds/taxel_patch.eds``);
* :mod:`.gripper` - the gripper drive (issue 22): one jaw axis of an electric parallel gripper as
  a CiA 402 drive (``eds/gripper_drive.eds``, ``docs/gripper-drive.md``).

And what runs them: :mod:`.rig` - :class:`Rig` (a package, one module per job: buses, channels,
devices, readings, gripper drive and world); :mod:`.physics` - readings and ground truth;
:mod:`.world` - the grasp world (issue 22 part 2): an object held by friction between the gripper
drive's jaws through a task, on its own clock (``docs/grasp-world.md``), pure, imported on use,
run by :mod:`.world_runner`; :mod:`.cli` - the ``node-sim`` command.

The old module paths ``node_sim.detector``, ``node_sim.channel`` and ``node_sim.patch_batch``
re-export what moved into the packages.

Nothing here imports from
``fusion_center``; what the twins and the centre share comes from ``taxel_net``.
"""

from __future__ import annotations

import lazy_loader

# imported on first use (PEP 562): ``import node_sim.physics`` loads no CAN library
__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__, submodules=["physics"], submod_attrs={"rig": ["Rig"], "node": ["TaxelNode"]})
