"""The process image of a patch node: what its TPDOs and SDO uploads read (:class:`PatchImage`).

The packed decisions 0x2020 (bit ``k % 8`` of sub ``k // 8 + 1`` for taxel ``k``,
:func:`taxel_net.patches.pack`), the cycle tag 0x2021 (the counter byte of the sampling SYNC, 0
without), the fault bits 0x2022, the readings as INTEGER8 / INTEGER16 counts of 0x2032 mV (0x2030 /
0x2031, :func:`taxel_net.patches.readings_to_counts`: NaN -> the most negative code, saturated
beyond the range; computed only when mapped or read) and the AI status of each taxel 0x2033
(CiA 404 AI status 0x6150's bits: 1 not valid, 2 positive overload, 4 negative overload) with
respect to the readings array the node's TPDOs map (:attr:`PatchImage.raw_index`, set by
:class:`~node_sim.patch.tpdo.PatchTpdoEngine` when it reads the TPDO configuration, so in
PRE-OPERATIONAL too; INTEGER16 while none is mapped). They are served to canopen's
``LocalNode`` by a read callback (:meth:`node_sim.patch.PatchNode._read_image`), never copied into the data
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
        self._status: dict[int, np.ndarray] = {}
        self.raw_index = P.PATCH_READINGS_I16   # what 0x2033 refers to (the TPDOs' readings array)
        self._encoding = {P.PATCH_READINGS_I8: P.ENC_INT8, P.PATCH_READINGS_I16: P.ENC_INT16}

    def update(self, readings: np.ndarray, decisions: bytes, faults: bytes, tag: int) -> None:
        self.readings = readings
        self.decisions = decisions
        self.faults = faults
        self.tag = tag
        self.tag_byte = _ONE_BYTE[tag]
        self._counts = {}
        self._status = {}

    def counts(self, index: int) -> bytes:
        """0x2030 / 0x2031: the readings as packed counts (computed once per SYNC, when asked)."""
        data = self._counts.get(index)
        if data is None:
            counts, self._status[index] = P.counts_and_status(self._encoding[index], self.readings, self.lsb_mv)
            data = self._counts[index] = counts.tobytes()
        return data

    def status(self, index: int) -> np.ndarray:
        """The AI status of every taxel (uint8, CiA 404 0x6150's bits) with respect to the
        readings array ``index`` (0x2030 / 0x2031), computed with its counts (once per SYNC)."""
        status = self._status.get(index)
        if status is None:
            self.counts(index)
            status = self._status[index]
        return status

    def data(self, index: int) -> bytes:
        """The bytes of image object ``index`` (sub 1 first)."""
        if index == P.PATCH_DECISIONS:
            return self.decisions
        if index == P.PATCH_CYCLE_TAG:
            return self.tag_byte
        if index == PATCH_FAULTS:
            return self.faults
        if index == P.PATCH_AI_STATUS:
            return self.status(self.raw_index).tobytes()
        return self.counts(index)

    def entries(self, index: int) -> int:
        """Sub 0 of a patch array for this node."""
        return self.n_bytes if index in _BYTE_ARRAYS else self.n

    @staticmethod
    def entry_bytes(index: int) -> int:
        return 2 if index == P.PATCH_READINGS_I16 else 1

