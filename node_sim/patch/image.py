"""The process image of a patch node: what its TPDOs and SDO uploads read (:class:`PatchImage`).

The packed decisions 0x2020 (bit ``k % 8`` of sub ``k // 8 + 1`` for taxel ``k``,
:func:`taxel_net.patches.pack`), the cycle tag 0x2021 (the counter byte of the sampling SYNC, 0
without), the fault bits 0x2022, the readings as INTEGER8 / INTEGER16 counts of 0x2032 mV (0x2030 /
0x2031, :func:`taxel_net.patches.readings_to_counts`: NaN -> the most negative code, saturated
beyond the range; computed only when mapped or read). They are served to canopen's ``LocalNode``
by a read callback (:meth:`node_sim.patch.PatchNode._read_image`), never copied into the data
store per SYNC. Sub 0 of every patch array reads its number of entries for this node (``n``, or
``ceil(n / 8)`` for the packed bytes); a sub-index beyond it is refused (0x06090011) for reads,
writes and mappings.
"""

from __future__ import annotations

import numpy as np

from taxel_net import patches as P

from .objects import PATCH_FAULTS

_BYTE_ARRAYS = (P.PATCH_DECISIONS, PATCH_FAULTS)          # one sub per 8 taxels

_ONE_BYTE = tuple(bytes((v,)) for v in range(256))


class PatchImage:
    """The process image of one patch node (module docstring): bytes per image object."""

    def __init__(self, n: int):
        self.n = n
        self.n_bytes = (n + 7) // 8
        self.tag = 0
        self.tag_byte = _ONE_BYTE[0]     # 0x2021 as its one data byte
        self.decisions = bytes(self.n_bytes)
        self.faults = bytes(self.n_bytes)
        self.readings: np.ndarray = np.full(n, np.nan)   # X_i (mV) of the last SYNC
        self.lsb_mv = 0.01
        self._counts: dict[int, bytes] = {}
        self._tpdo = {P.PATCH_READINGS_I8: P.Tpdo(0, 0, 0, n, P.ENC_INT8, False, 0, False),
                      P.PATCH_READINGS_I16: P.Tpdo(0, 0, 0, n, P.ENC_INT16, False, 0, False)}

    def update(self, readings: np.ndarray, decisions: bytes, faults: bytes, tag: int) -> None:
        self.readings = readings
        self.decisions = decisions
        self.faults = faults
        self.tag = tag
        self.tag_byte = _ONE_BYTE[tag]
        self._counts = {}

    def counts(self, index: int) -> bytes:
        """0x2030 / 0x2031: the readings as packed counts (computed once per SYNC, when asked)."""
        data = self._counts.get(index)
        if data is None:
            counts, _ = P.readings_to_counts(self._tpdo[index], self.readings, self.lsb_mv)
            data = self._counts[index] = counts.tobytes()
        return data

    def data(self, index: int) -> bytes:
        """The bytes of image object ``index`` (sub 1 first)."""
        if index == P.PATCH_DECISIONS:
            return self.decisions
        if index == P.PATCH_CYCLE_TAG:
            return self.tag_byte
        if index == PATCH_FAULTS:
            return self.faults
        return self.counts(index)

    def entries(self, index: int) -> int:
        """Sub 0 of a patch array for this node."""
        return self.n_bytes if index in _BYTE_ARRAYS else self.n

    @staticmethod
    def entry_bytes(index: int) -> int:
        return 2 if index == P.PATCH_READINGS_I16 else 1

