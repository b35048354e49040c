"""taxel-can node firmware twins: CANopen taxel nodes running the chapter's local detector.

Public API (``docs/api.md``): :class:`Rig` (every node twin of a scene on its CAN bus(es)),
:class:`TaxelNode` (one node twin) and :mod:`physics` (the simulated readings and ground
truth). They are imported on first use (PEP 562): ``import node_sim.physics`` loads neither
python-can nor canopen.

Layout: the layout is the protocol. As in the ``canopen`` package (``nmt``, ``sdo``, ``pdo``,
``sync``, ``emcy``), one module per CANopen service the twin implements, each owning that
service's state; :class:`TaxelNode` composes them:

* :mod:`.nmt` - NMT slave: states, boot-up, start/stop/pre-operational/resets;
* :mod:`.heartbeat` - heartbeat producer (0x1017);
* :mod:`.sdo` - SDO server: canopen's server behind the CiA 301 checks, abort codes;
* :mod:`.pdo` - TPDO engine: SYNC-driven (types 0..240, SYNC start value) and event-driven
  (254/255, inhibit time, event timer) TPDOs;
* :mod:`.rpdo` - RPDO engine: receive PDOs applied at the next SYNC (types 0..240) or at once
  (254/255), length errors (EMCY 0x8210); used by the gripper drive;
* :mod:`.sync` - SYNC consumer (0x1005): what a SYNC triggers;
* :mod:`.emcy` - EMCY producer, error register 0x1001, error history 0x1003;
* :mod:`.detector` - the application: the local detector of the chapter (eqs 1-4,
  u_i = ±1 from X_i − N_i ≥ ζ; also as 0x2003 with its cycle tag), sensor-fault checks, its
  analog input (X_i in mV);
* :mod:`.od` - the object dictionary glue (the EDS ``eds/taxel_node.eds``, canopen's
  ``LocalNode``, start-up values);
* :mod:`.node` - :class:`TaxelNode`; :mod:`.link` - a node's channel (send, SYNC bursts,
  timers);
* :mod:`.rig` - :class:`Rig`; :mod:`.physics` - readings and ground truth; :mod:`.cli` - the
  ``node-sim`` command.

* :mod:`.gripper` - a second device kind (issue 22): the gripper drive, one jaw axis of an electric
  parallel gripper as a CiA 402 drive (``eds/gripper_drive.eds``, ``docs/gripper-drive.md``),
  composed of the same service modules;

* :mod:`.world` - the grasp world (issue 22 part 2): an object held by friction between the gripper
  drive's jaws through a task, on its own clock (``docs/grasp-world.md``); pure, imported on use;

* :mod:`.lss` - the LSS slave (CiA 305: switch state, configure node-ID and bit timing, store,
  inquire, identify, Fastscan).

Nothing here imports from
``fusion_center``; what the twins and the centre share comes from ``taxel_net``.
"""

from __future__ import annotations

import lazy_loader

# imported on first use (PEP 562): ``import node_sim.physics`` loads no CAN library
__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__, submodules=["physics"], submod_attrs={"rig": ["Rig"], "node": ["TaxelNode"]})
