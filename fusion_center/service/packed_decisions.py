"""Packed decisions of a cycle's patch TPDOs, kept as they came and unpacked once at its close.

A patch node sends the local decisions of its taxels (u_i of eqs 1-4 of "Grip Force and Slip
Analysis in Robotic Grasp: New Stochastic Paradigm Through Sensor Data Fusion") one bit per
taxel behind the cycle tag (:data:`taxel_net.patches.ENC_BITS`). Unpacking every frame as it
comes - a ``frombuffer`` and two array stores per frame - was a third of the centre's work per
frame at 4,096 taxels (88 frames a cycle on classic CAN). Here each accepted frame's payload is
copied into its slot's place in one buffer of the cycle (a ``bytearray`` slice store), and the
last frame heard of each slot into another; :meth:`PackedDecisions.unpack` turns both into the
per-taxel arrays in a few numpy calls when the cycle closes.

A scene of a few patch nodes (the grasp scenes: two pads, 52 taxels in 7 bytes) sends the same
few bit patterns cycle after cycle; there :meth:`PackedDecisions.unpack` keeps what each
(payloads, frames accepted, frames ever heard) unpacked to, and a repeat is three array stores
(1.7 against 15 µs in a loop; at the close of the cycle, on the SYNC -> grip command path,
docs/grip-control.md). Layouts of more than :data:`MEMO_BYTES` bytes - skin scale, where the
patterns rarely repeat - unpack every time.

Same results as unpacking per frame (``SlotDecoder.decode``, tests/test_packed_decisions.py):
bit k of the payload's byte j is taxel 8 j + k of the TPDO (``taxel_net.patches.unpack``); a
taxel's decision is +1 for a set bit, -1 for a clear one, 0 when its TPDO did not come this
cycle; its held decision is that of the last frame of its TPDO heard, whatever cycle it
answered, 0 before any.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PackedDecisions"]

MEMO_BYTES = 64      # layouts up to this size keep their unpacked patterns (module docstring)
MEMO_ENTRIES = 1024  # patterns kept at most (then forgotten all at once)


class PackedDecisions:
    """The packed-decision slots of a :class:`~.cycle_layout.CycleLayout` (module docstring).

    ``places[slot]``: ``(first, stop, start, end)`` - the slot's bytes ``first:stop`` of the
    buffers hold the frame's payload bytes ``start:end`` - or None for a slot of readings.
    ``usable`` is False when two slots carry the same taxel (the later frame would have to win
    whatever its slot; the assembler then unpacks every frame as it comes)."""

    def __init__(self, layout, n_taxels: int):
        self.places: list[tuple[int, int, int, int] | None] = []
        bit_position, bit_taxel, bit_slot = [], [], []
        size = 0
        for slot, (is_bits, decoder, taxels) in enumerate(zip(layout.slot_is_bits, layout.slot_decoders,
                                                              layout.slot_taxels)):
            if not is_bits:
                self.places.append(None)
                continue
            width = decoder.end - decoder.start
            self.places.append((size, size + width, decoder.start, decoder.end))
            indices = np.arange(n_taxels)[taxels] if isinstance(taxels, slice) else np.asarray(taxels)
            bit_position.append(8 * size + np.arange(decoder.count))
            bit_taxel.append(indices)
            bit_slot.append(np.full(decoder.count, slot, dtype=np.intp))
            size += width
        empty = np.zeros(0, dtype=np.intp)
        self.bit_position = np.concatenate(bit_position).astype(np.intp) if bit_position else empty
        self.bit_taxel = np.concatenate(bit_taxel).astype(np.intp) if bit_taxel else empty
        self.bit_slot = np.concatenate(bit_slot) if bit_slot else empty
        self.usable = len(np.unique(self.bit_taxel)) == len(self.bit_taxel)
        self.cycle_bytes = bytearray(size)   # the payloads accepted in the open cycle
        self.held_bytes = bytearray(size)    # the last payload heard per slot
        self.heard = np.zeros(len(self.places), dtype=bool)  # a frame of the slot was ever heard
        # (cycle bytes, held bytes, slot_got, heard) -> what unpack stores (module docstring)
        self.memo: dict[bytes, tuple] | None = {} if size <= MEMO_BYTES and len(self.bit_taxel) else None

    def unpack(self, slot_got: np.ndarray, decisions: np.ndarray, got: np.ndarray,
               held_decisions: np.ndarray) -> None:
        """Into the per-taxel arrays: ``decisions`` (+1 / -1 of the frames accepted this cycle,
        ``slot_got``; 0 for a taxel whose frame did not come), ``got`` (its frame came) and
        ``held_decisions`` (the last frame heard; taxels of a slot never heard are left as
        they are)."""
        taxels, slots = self.bit_taxel, self.bit_slot
        if not len(taxels):
            return
        memo = self.memo
        if memo is not None:
            key = b"".join((self.cycle_bytes, self.held_bytes, slot_got.tobytes(), self.heard.tobytes()))
            stored = memo.get(key)
            if stored is not None:
                values, came, held_taxels, held_values = stored
                decisions[taxels] = values
                got[taxels] = came
                held_decisions[held_taxels] = held_values
                return
        positions = self.bit_position
        came = slot_got[slots]
        bits = np.unpackbits(np.frombuffer(self.cycle_bytes, dtype=np.uint8), bitorder="little")[positions]
        values = np.where(came, 2 * bits.astype(np.int8) - 1, 0)
        decisions[taxels] = values
        got[taxels] = came
        heard = self.heard[slots]
        held = np.unpackbits(np.frombuffer(self.held_bytes, dtype=np.uint8), bitorder="little")[positions]
        held_taxels, held_values = taxels[heard], 2 * held[heard].astype(np.int8) - 1
        held_decisions[held_taxels] = held_values
        if memo is not None:
            if len(memo) >= MEMO_ENTRIES:
                memo.clear()
            memo[key] = (values, came, held_taxels, held_values)
