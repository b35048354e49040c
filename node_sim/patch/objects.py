"""The patch node's object dictionary: ``eds/taxel_patch.eds`` loaded per node-ID
(:func:`load_patch_od`) and the indices the patch twin adds to :mod:`taxel_net.patches`' (the
fault bits 0x2022; which arrays are parameters, which the process image; its 85 TPDO pairs and
how many entries each may map on classic CAN / CAN FD, as ``eds/make_patch_eds.py`` writes them).
"""

from __future__ import annotations

from functools import lru_cache

import canopen

from taxel_net import patches as P
from taxel_net.resources import patch_eds_path

from .. import od as odx

PATCH_EDS_PATH = patch_eds_path()
PATCH_FAULTS = 0x2022            # ARRAY UNSIGNED8: sensor-fault bits, the layout of 0x2020
PARAMETER_ARRAYS = (P.PATCH_ZETA, P.PATCH_NOISE, P.PATCH_KIND, P.PATCH_X, P.PATCH_Y)
IMAGE_ARRAYS = (P.PATCH_DECISIONS, PATCH_FAULTS, P.PATCH_READINGS_I8, P.PATCH_READINGS_I16, P.PATCH_AI_STATUS)
READINGS_ARRAYS = (P.PATCH_READINGS_I8, P.PATCH_READINGS_I16)   # narrowest first
N_TPDOS = 85
FD_MAPPED, CLASSIC_MAPPED, FD_TPDOS = 64, 8, 16           # eds/make_patch_eds.py
TPDO_COMM = tuple(0x1800 + k for k in range(N_TPDOS))
TPDO_MAP = tuple(0x1A00 + k for k in range(N_TPDOS))


@lru_cache(maxsize=32)
def _import(path: str, mtime: float, node_id: int):
    return canopen.import_od(path, node_id)


def load_patch_od(node_id: int, eds_path=PATCH_EDS_PATH):
    """The patch node EDS imported for ``node_id`` (cached per file and node-ID: the import takes
    ~0.4 s, and the twins only read the dictionary - values live in each node's data store)."""
    if not isinstance(node_id, int) or not 1 <= node_id <= 127:
        from taxel_net.errors import ParameterError
        raise ParameterError("node_id", node_id, "CANopen node-ID must be an integer 1..127")
    path = odx.check_eds(eds_path, "patch node")
    return _import(str(path), path.stat().st_mtime, node_id)

