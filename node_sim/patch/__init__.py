"""The patch node twin: one CANopen node hosting the taxels of a patch (issue 14).

A skin patch puts many taxels behind one microcontroller: :class:`PatchNode` is that node, a
:class:`node_sim.node.TaxelNode` whose application and TPDOs handle ``n`` taxels (1..254, one
entry of each OD array per taxel) on the object dictionary of ``eds/taxel_patch.eds``
(:func:`load_patch_od`). The CiA 301 services are the one-taxel node's own modules - NMT and
boot-up (:mod:`node_sim.nmt`), heartbeat producer / consumer (:mod:`node_sim.heartbeat`), the SDO
server (:mod:`node_sim.sdo`, expedited and segmented on canopen's ``LocalNode``), SYNC consumer
(:mod:`node_sim.sync`), EMCY (:mod:`node_sim.emcy`) and the TPDO engine (:mod:`node_sim.pdo`,
generalised to 85 TPDO pairs and, on CAN FD, 64 mapping entries / 512 bits per PDO). What differs
has a module each (issue 22), as canopen parts its ``sdo`` / ``pdo`` packages:

* :mod:`.objects` - the patch EDS loaded per node-ID (:func:`load_patch_od`) and its indices;
* :mod:`.image` - :class:`PatchImage`, the process image the TPDOs and SDO uploads read (packed
  decisions 0x2020, cycle tag 0x2021, fault bits 0x2022, readings as counts 0x2030 / 0x2031, their
  AI status 0x2033);
* :mod:`.detector` - :class:`PatchDetector` and :func:`detect`: the local detector of the chapter
  (eqs 1-4) and the sensor-fault checks over every taxel at once, EMCY on a fault change;
* :mod:`.tpdo` - :class:`PatchTpdoEngine`: mappings compiled to slices of the process image, and
  raw mode's over-range check of the mapped readings before each SYNC's frames (EMCY 0x3000);
* :mod:`.node` - :class:`PatchNode`, composing them;
* :mod:`.startup` - :func:`patch_startup_values` (what :meth:`PatchNode.configure` gets: the node
  then sends exactly the frames :func:`taxel_net.patches.devices` describes for the device) and
  :func:`tpdo_mapping`;
* :mod:`.batch` - :class:`PatchSyncBatch`: a channel's patch nodes that consume the same SYNC,
  sampled as one (the same :func:`detect`).

Every name is importable from ``node_sim.patch`` as before the split.
"""

from __future__ import annotations

# every name of the one module it was stays importable from here (noqa F401: re-exported)
from ..emcy import FAULT_NONE, FAULT_OPEN_CIRCUIT, FAULT_STUCK  # noqa: F401
from .batch import PatchSyncBatch  # noqa: F401
from .detector import NEVER_STUCK, PatchDetector, detect, stuck_limit  # noqa: F401
from .image import PatchImage
from .node import PatchNode
from .objects import (CLASSIC_MAPPED, FD_MAPPED, FD_TPDOS, IMAGE_ARRAYS, N_TPDOS,  # noqa: F401
                      PARAMETER_ARRAYS, PATCH_EDS_PATH, PATCH_FAULTS, TPDO_COMM, TPDO_MAP, load_patch_od)
from .startup import patch_startup_values, tpdo_mapping
from .tpdo import PatchTpdoEngine

__all__ = ["PatchNode", "PatchDetector", "PatchImage", "PatchTpdoEngine", "detect", "load_patch_od",
           "patch_startup_values", "tpdo_mapping", "PATCH_FAULTS", "PATCH_EDS_PATH"]

