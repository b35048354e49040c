"""The patch node twin (:class:`PatchNode`): a :class:`node_sim.node.TaxelNode` whose application
(:class:`~node_sim.patch.detector.PatchDetector`) and TPDOs
(:class:`~node_sim.patch.tpdo.PatchTpdoEngine`) handle ``n`` taxels, on the object dictionary of
``eds/taxel_patch.eds`` (:func:`~node_sim.patch.objects.load_patch_od`), serving its process image
(:class:`~node_sim.patch.image.PatchImage`) to canopen's ``LocalNode`` by a read callback.
"""

from __future__ import annotations

import numpy as np
from canopen.sdo import SdoAbortedError

from taxel_net import patches as P

from .. import od as odx
from ..emcy import over_range_field
from ..link import NodeLink
from ..node import TaxelNode
from ..pdo import TpdoEngine
from ..sdo import ABORT_SUBINDEX_NOT_IN_OD
from .detector import PatchDetector
from .image import PatchImage
from .objects import IMAGE_ARRAYS, PARAMETER_ARRAYS, PATCH_EDS_PATH, load_patch_od
from .tpdo import PatchTpdoEngine


class PatchNode(TaxelNode):
    """One patch node twin hosting ``n`` taxels (module docstring). ``fd``: its TPDOs are CAN
    FD frames (mappings of up to 64 entries / 512 bits). ``od`` defaults to the patch EDS
    imported for ``node_id`` (:func:`load_patch_od`)."""

    SCALAR_READING = False
    APPLICATION_OBJECTS = (odx.FAULT_DETECTION, *PARAMETER_ARRAYS, P.PATCH_RAW_LSB)

    def __init__(self, node_id: int, link: NodeLink, n: int, od=None, eds_path=PATCH_EDS_PATH, *, fd: bool = False):
        if not 1 <= n <= P.PATCH_TAXELS_MAX:
            from taxel_net.errors import ParameterError
            raise ParameterError("n", n, f"a patch node hosts 1..{P.PATCH_TAXELS_MAX} taxels")
        self.n = n
        self.image = PatchImage(n)
        if od is None:
            od = load_patch_od(node_id, eds_path)
        super().__init__(node_id, link, od, eds_path, fd=fd)
        self.local.add_read_callback(self._read_image)

    def configure(self, values) -> None:
        super().configure(values)
        self.detector.config()   # the arrays decoded now, not at the first SYNC

    def _new_detector(self):
        return PatchDetector(self.objects, self.image, self.emcy.fault_changed)

    def _new_pdo(self, fd: bool) -> TpdoEngine:
        return PatchTpdoEngine(self, fd=fd)

    def _read_image(self, index: int, subindex: int, od):
        """LocalNode read callback: the process image and the sub 0 counts of the patch arrays."""
        if index < P.PATCH_ZETA or index > P.PATCH_AI_STATUS:
            return None
        image = self.image
        if index in IMAGE_ARRAYS or index in PARAMETER_ARRAYS:
            count = image.entries(index)
            if subindex == 0:
                return count
            if subindex > count:
                raise SdoAbortedError(ABORT_SUBINDEX_NOT_IN_OD)
            if index in PARAMETER_ARRAYS:
                return None
            width = image.entry_bytes(index)
            return od.decode_raw(image.data(index)[(subindex - 1) * width: subindex * width])
        if index == P.PATCH_CYCLE_TAG:
            return image.tag
        return None

    def check_over_range(self, index: int, tpdo_of: np.ndarray, overload: np.ndarray) -> None:
        """A SYNC in OPERATIONAL with readings array ``index`` mapped (``tpdo_of``: the TPDO of
        each taxel, 0 if none; ``overload``: the AI status bits that count per taxel;
        :class:`PatchTpdoEngine`): the over-range EMCY on the rising edge of "a mapped reading
        saturates" (its AI status 0x2033 has an overload bit), its error reset when none does
        (:meth:`node_sim.emcy.EmcyProducer.over_range`)."""
        status = self.image.status(index)
        over = status & overload
        count = int(np.count_nonzero(over))
        emcy = self.emcy
        if not count:
            emcy.over_range(None)   # its error reset, once (nothing while none is active)
        elif not emcy.over_range_active:   # the rising edge: the field made only then
            k = int(np.flatnonzero(over)[0])
            emcy.over_range(over_range_field(k, int(tpdo_of[k]), int(status[k]), count))

    # ------------------------------------------------------------------ introspection
    @property
    def decision(self) -> np.ndarray:
        """u_i of the last SYNC, ±1 per taxel (int8)."""
        bits = np.unpackbits(np.frombuffer(self.image.decisions, dtype=np.uint8), bitorder="little")[: self.n]
        return 2 * bits.astype(np.int8) - 1

    @property
    def faulted(self) -> np.ndarray:
        return self.detector.faulted

