"""The taxel node: one taxel behind one CANopen node (the chapter's node, ``eds/taxel_node.eds``).

Its device is :class:`node_sim.node.TaxelNode`, the composition of the shared CANopen service
modules (NMT, heartbeat, SDO, SYNC, TPDO, EMCY, LSS) that the patch node (:mod:`node_sim.patch`)
and the gripper drive (:mod:`node_sim.gripper`) reuse; what is the taxel node's own is here:

* :mod:`.detector` - its application: the local detector of the chapter (eqs 1-4, u_i = ±1 from
  X_i − N_i ≥ ζ; also as 0x2003 with its cycle tag), sensor-fault checks, its analog input (X_i
  in mV); :class:`~node_sim.taxel.detector.Detector`;
* :mod:`.startup` - its start-up values from the scene
  (:func:`~node_sim.taxel.startup.taxel_startup_values`) and its serial number 0x1018:4
  (:func:`~node_sim.taxel.startup.identity_serial`).

Their old paths still import: ``node_sim.detector`` (re-exports the detector) and
``node_sim.rig.identity_serial``.
"""
