"""The TPDO engine of a patch node (:class:`PatchTpdoEngine`): :class:`node_sim.pdo.TpdoEngine`
over 85 TPDO pairs and, on CAN FD, 64 mapping entries / 512 bits per PDO.

It compiles each mapping once (on a change) into a function of byte ranges of the process image
(:mod:`.image`; consecutive entries of one array become one slice), so a SYNC costs one ``join``
of a few slices per TPDO (the tag and the packed decisions: one concatenation); on CAN FD the data
are padded with 0 to the next valid FD length. TPDOs all sent on every SYNC (transmission type 1)
leave in one call to the link.

Raw mode's over-range signal (docs/node-twins.md): when the configuration is read (after a boot,
after an SDO write to 0x180x / 0x1A0x: in PRE-OPERATIONAL too) the engine notes which readings
array its TPDOs map (the narrowest when both are; :attr:`PatchImage.raw_index`, what the AI status
0x2033 refers to), and on activation which TPDO carries each taxel; at every SYNC, before the TPDOs
leave, the node compares the AI status of the mapped readings with the last one
(:meth:`~node_sim.patch.node.PatchNode.check_over_range`): the over-range EMCY
(:data:`taxel_net.patches.EMCY_INPUT_OVER_RANGE`) on the rising edge, its error reset when every
mapped reading is back in range - so the EMCY precedes the first frame that carries a limit code.
A mapping that no longer carries any reading ends an over range too (its error reset at activation).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from canopen.sdo import SdoAbortedError

from taxel_net import patches as P

from ..pdo import TpdoEngine, _TpdoConfig
from ..sdo import ABORT_NOT_MAPPABLE
from .objects import (CLASSIC_MAPPED, FD_MAPPED, FD_TPDOS, IMAGE_ARRAYS, N_TPDOS, READINGS_ARRAYS, TPDO_COMM,
                      TPDO_MAP)

if TYPE_CHECKING:
    from .node import PatchNode


class PatchTpdoEngine(TpdoEngine):
    """TPDOs of a patch node: mappings compiled to slices of the process image."""

    def __init__(self, node: "PatchNode", *, fd: bool):
        super().__init__(node, node.nmt, node.objects, node.link, comm=TPDO_COMM, mapping=TPDO_MAP,
                         max_mapped=tuple(FD_MAPPED if fd and k < FD_TPDOS else CLASSIC_MAPPED
                                          for k in range(N_TPDOS)),
                         max_bits=8 * (P.FD_DATA_MAX if fd else P.CLASSIC_DATA_MAX), fd=fd)
        self._image = node.image
        self._check_over_range = node.check_over_range
        self._emcy = node.emcy
        self._every_sync = self._tagged_decisions = None   # what _activate finds
        self._watch = None   # what the over-range check watches (_mapped_readings)
        self._every_sync_runtimes: tuple = ()

    def _activate(self):
        active = super()._activate()
        # every active TPDO synchronous, sent on every SYNC (transmission type 1, no SYNC start
        # value): on_sync sends them without the general per-TPDO bookkeeping, which leaves
        # them started with their SYNC count at 0 after every SYNC - as here
        every_sync = bool(active) and all(cfg.transmission_type == 1 and not cfg.sync_start for _, cfg, _ in active)
        self._every_sync = tuple((cfg.can_id, cfg.plan, rt) for _, cfg, rt in active) if every_sync else None
        self._every_sync_runtimes = tuple(rt for _, _, rt in active)
        # and each the cycle tag and a range of packed decisions (classic): (can_id, start, stop)
        self._tagged_decisions = (tuple((cfg.can_id, *cfg.plan.tagged_decisions) for _, cfg, _ in active)
                                  if every_sync and not self.fd
                                  and all(hasattr(cfg.plan, "tagged_decisions") for _, cfg, _ in active)
                                  else None)
        if every_sync:
            for rt in self._every_sync_runtimes:
                rt.started = True
                rt.sync_count = 0
        self._watch = self._mapped_readings(active)
        if self._watch is None:
            self._emcy.over_range(None)   # no reading mapped is over range now: the error reset, if owed
        return active

    def read_configuration(self) -> None:
        super().read_configuration()
        self._note_readings_array()

    def reconfigure(self) -> None:
        super().reconfigure()
        self._note_readings_array()

    def _note_readings_array(self) -> None:
        """The configuration was read (after a boot, after an SDO write to 0x180x / 0x1A0x): the
        readings array the valid TPDOs map, what 0x2033 refers to from now on, also in
        PRE-OPERATIONAL (:attr:`PatchImage.raw_index`; activation finds the same)."""
        valid = []
        for pdo in range(self.n_tpdos):
            cfg = self.config(pdo)
            if cfg.valid and cfg.mapping:
                valid.append((pdo, cfg, None))
        self._mapped_readings(valid)

    def _mapped_readings(self, active):
        """``(index, tpdo_of, overload)`` of the readings array the active TPDOs map (INTEGER8 when both
        are: the narrower range), ``tpdo_of[k]`` the number (1-based, 1 = 0x1800) of the first
        TPDO carrying taxel k, 0 where none does; ``overload`` the AI status bits that count per
        taxel (the overload bits where mapped, else 0); None when no readings are mapped."""
        image = self._image
        mapped: dict[int, np.ndarray] = {}
        for pdo, cfg, _ in active:
            for index, subindex, _ in cfg.mapping:
                if index in READINGS_ARRAYS and 1 <= subindex <= image.n:
                    tpdo_of = mapped.setdefault(index, np.zeros(image.n, dtype=np.uint8))
                    if not tpdo_of[subindex - 1]:
                        tpdo_of[subindex - 1] = pdo + 1
        index = next((i for i in READINGS_ARRAYS if i in mapped), None)
        image.raw_index = P.PATCH_READINGS_I16 if index is None else index
        if index is None:
            return None
        tpdo_of = mapped[index]
        return index, tpdo_of, np.where(tpdo_of > 0, P.AI_OVERLOAD, 0).astype(np.uint8)

    def on_sync(self, counter: int | None) -> None:
        """A SYNC in OPERATIONAL for a live node: :meth:`TpdoEngine.on_sync`, or when every
        active TPDO is sent on every SYNC, their frames in one :meth:`NodeLink.send_all`
        (the same frames and run-time state)."""
        if self._active is None:
            self._activate()
        if self._watch is not None:
            self._check_over_range(*self._watch)   # its EMCY before the frames of this SYNC
        every_sync = self._every_sync
        if every_sync is None:
            super().on_sync(counter)
            return
        tagged = self._tagged_decisions
        if tagged is not None:
            image = self._image
            tag, decisions = image.tag_byte, image.decisions
            frames = [(can_id, tag + decisions[first:stop]) for can_id, first, stop in tagged]
            for (_, payload), rt in zip(frames, self._every_sync_runtimes):
                rt.last_sent = payload
        else:
            frames = []
            fd = self.fd
            for can_id, payload_of, rt in every_sync:
                payload = payload_of()
                rt.last_sent = payload
                frames.append((can_id, payload, True) if fd else (can_id, payload))
        self._link.send_all(frames, self._every_sync_runtimes)
        self.frames_sent += len(frames)

    def _compile(self, cfg: _TpdoConfig):
        """The payload of ``cfg`` as a function of no argument: byte ranges of the image
        (consecutive entries of one array: one range) and other objects (read from the OD at
        transmission), joined, then the FD padding; the cycle tag and one range of packed
        decisions (the rig's patch TPDOs) is one concatenation."""
        runs: list[list] = []
        image = self._image
        length = 0
        for index, subindex, bits in cfg.mapping:
            size = bits // 8
            length += size
            if index in IMAGE_ARRAYS:
                width = image.entry_bytes(index)
                start = (subindex - 1) * width
                if runs and runs[-1][0] == index and runs[-1][2] == start:
                    runs[-1][2] = start + width
                else:
                    runs.append([index, start, start + width])
            elif index == P.PATCH_CYCLE_TAG:
                runs.append([index, 0, 1])
            else:
                runs.append([index, subindex, None])
        padding = bytes(P.fd_length(length) - length) if self.fd and length <= P.FD_DATA_MAX else b""
        kinds = [r[0] for r in runs]
        if not padding and kinds == [P.PATCH_CYCLE_TAG, P.PATCH_DECISIONS]:
            first, stop = runs[1][1], runs[1][2]

            def tagged_decisions() -> bytes:
                return image.tag_byte + image.decisions[first:stop]

            tagged_decisions.tagged_decisions = (first, stop)   # what on_sync sends without the call
            return tagged_decisions
        if not padding and kinds == [P.PATCH_DECISIONS]:
            first, stop = runs[0][1], runs[0][2]
            return lambda: image.decisions[first:stop]
        runs = tuple(tuple(r) for r in runs)
        data = image.data
        local = self._objects.local

        def payload() -> bytes:
            parts = [data(i)[a:b] if b is not None else local.get_data(i, a) for i, a, b in runs]
            if padding:
                parts.append(padding)
            return b"".join(parts)

        return payload

    def _payload(self, cfg: _TpdoConfig) -> bytes:
        return cfg.plan()

    def _check_mappable(self, entry: int) -> int:
        index, subindex = entry >> 16, (entry >> 8) & 0xFF
        if index in IMAGE_ARRAYS and not 1 <= subindex <= self._image.entries(index):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)               # no such taxel on this node
        return super()._check_mappable(entry)

