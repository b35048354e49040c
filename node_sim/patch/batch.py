"""A channel's patch nodes that consume the same SYNC, sampled as one (issue 14).

:class:`PatchSyncBatch` runs :func:`node_sim.patch.detector.detect` (the detector of eqs 1-4 and
the fault checks, the one implementation :meth:`node_sim.patch.detector.PatchDetector.sample` also
runs) once over the concatenated taxels of the nodes that sample, the concatenated configuration
(:class:`_BatchLayout`) cached until a node's detector re-reads its own; then per node its slice
of the results, its EMCY on a fault change, its TPDOs - the frames each node's own
:class:`node_sim.sync.SyncConsumer` would send (tests/test_patch_sync_batch.py).

Hot path: one SYNC of a channel is one ``detect`` over its patch nodes' readings (a view of the
rig's vector; about ten numpy calls when no sample repeats and every reading is in range), one
``packbits``, then per node a few slices and its TPDOs - no per-taxel Python loop.
"""

from __future__ import annotations

import numpy as np

from ..nmt import INITIALISING, OPERATIONAL
from ..sync import SyncConsumer
from .detector import PatchDetector, detect, stuck_limit
from .node import PatchNode


class _BatchLayout:
    """Where each sampling node's taxels sit in a :class:`PatchSyncBatch`'s concatenation, and
    their configuration concatenated: each node's taxels start on a byte (its ``n`` padded to
    a multiple of 8 with entries :func:`detect` masks out), so one ``packbits`` of the batch,
    sliced per node, gives each node's packed bits. Built from the nodes' detectors and their
    :meth:`PatchDetector.config` tuples (``configs``, held: a write or NMT reset makes a new
    one, so a layout is current while every tuple it was built from is still its node's)."""

    def __init__(self, detectors: list, taxels: list, configs: list):
        self.detectors = detectors
        self.configs = configs
        sizes = [len(t) for t in taxels]
        padded = [-(-n // 8) * 8 for n in sizes]
        offsets = np.concatenate(([0], np.cumsum(padded)[:-1])).tolist()
        self.spans = [(a, a + n, a // 8, (a + m) // 8) for a, n, m in zip(offsets, sizes, padded)]
        self.pads = [m - n for n, m in zip(sizes, padded)]
        self.padded = any(self.pads)

        def concatenated(arrays, fill):
            parts = []
            for array, pad in zip(arrays, self.pads):
                parts.append(array)
                if pad:
                    parts.append(np.full(pad, fill, dtype=np.asarray(array).dtype))
            return np.concatenate(parts)

        self.zeta = concatenated([c[0] for c in configs], 0.0)
        self.noise = concatenated([c[1] for c in configs], 0.0)
        scales = {float(c[2]) for c in configs}
        self.full_scale = scales.pop() if len(scales) == 1 else np.repeat([float(c[2]) for c in configs], padded)
        if not self.noise.any():
            self.noise = None      # every N_i 0 (or -0): X_i - N_i is X_i
        limits = [stuck_limit(c[3]) for c in configs]
        self.stuck_after = np.repeat(np.array(limits, dtype=np.int64), padded)
        self.stuck_min = min(limits)
        self.valid = concatenated([np.ones(n, dtype=bool) for n in sizes], False) if self.padded else None
        starts = [int(t[0]) for t in taxels]
        consecutive = all(np.array_equal(t, np.arange(a, a + len(t))) for t, a in zip(taxels, starts)) \
            and all(starts[k] + sizes[k] == starts[k + 1] for k in range(len(sizes) - 1))
        # the readings of the batch: a view of the channel's readings when they are one run
        self.gather = (slice(starts[0], starts[-1] + sizes[-1]) if consecutive and not self.padded
                       else concatenated([np.asarray(t, dtype=np.intp) for t in taxels], starts[0]))
        self.pad_raw = {p: np.zeros(p, dtype=np.uint32) for p in self.pads if p}
        self.pad_same = {p: np.zeros(p, dtype=np.int64) for p in self.pads if p}
        self.raw = self.same = None     # the last batch's results, whose slices the detectors hold
        self.handed: list = []          # those slices, (last_raw, same) per detector

    def current(self, configs: list) -> bool:
        held = self.configs
        return len(held) == len(configs) and all(a is b for a, b in zip(held, configs))

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """The detectors' REAL32 patterns of the last sample and run lengths, concatenated: the
        last batch's arrays while every detector still holds its slices of them."""
        detectors = self.detectors
        handed = self.handed
        if len(handed) == len(detectors) and all(
                d._last_raw is r and d._same is c for d, (r, c) in zip(detectors, handed)):
            return self.raw, self.same
        raws, sames = [], []
        for d, pad in zip(detectors, self.pads):
            raws.append(d._last_raw)
            sames.append(d._same)
            if pad:
                raws.append(self.pad_raw[pad])
                sames.append(self.pad_same[pad])
        return np.concatenate(raws), np.concatenate(sames)


class PatchSyncBatch:
    """The patch nodes of one channel that consume the same SYNC, sampled as one: what each
    node's :meth:`node_sim.sync.SyncConsumer.on_sync` does, with the detectors (:func:`detect`,
    eqs 1-4) run once over the concatenated taxels of the nodes that sample this SYNC.

    A node samples unless it is silent or INITIALISING; in OPERATIONAL its TPDOs follow. The
    concatenated configuration (:class:`_BatchLayout`) is rebuilt when a node's detector
    configuration is re-read (an SDO or start-up write, an NMT reset swapping the data store)
    or the set of sampling nodes changes. Then node by node, in channel order: its slice of
    the results becomes its state, its fault change its EMCY (:meth:`PatchDetector.record`),
    then its TPDOs - the frames of the SYNC in the order the nodes one by one send them.
    ``entries``: ``(node, taxels)`` in channel order, ``taxels`` the node's readings in the
    channel's vector (a slice or an index array)."""

    def __init__(self, entries):
        self._nodes = []
        for node, taxels in entries:
            if isinstance(taxels, slice):
                taxels = np.arange(taxels.start or 0, taxels.stop)
            self._nodes.append((node, node.detector, node.sync, node.nmt, node.pdo.on_sync,
                                np.asarray(taxels, dtype=np.intp)))
        self._layout: _BatchLayout | None = None

    @staticmethod
    def batchable(node) -> bool:
        """A patch node whose SYNC consumer and detector are the ones this batch stands in for."""
        return (isinstance(node, PatchNode) and type(node.detector) is PatchDetector
                and type(node.sync) is SyncConsumer and "on_sync" not in vars(node.sync)
                and "sample" not in vars(node.detector))

    def on_sync(self, cycle: int, readings: np.ndarray, counter: int | None) -> None:
        """SYNC ``cycle`` (``counter``: its counter byte, None without) with the channel's
        readings: every node as its SYNC consumer would (class docstring)."""
        sampling = []
        for entry in self._nodes:
            if entry[0].silent:
                continue
            state = entry[3].state
            if state == INITIALISING:
                continue
            sampling.append((entry, state))
        if not sampling:
            return
        configs = [entry[1].config() for entry, _ in sampling]
        layout = self._layout
        if layout is None or not layout.current(configs):
            layout = self._layout = _BatchLayout([entry[1] for entry, _ in sampling],
                                                 [entry[5] for entry, _ in sampling], configs)
        x = readings[layout.gather]
        last_raw, same = layout.state()
        raw, same, open_circuit, faulted, present, any_faulted = detect(
            x, layout.zeta, layout.noise, layout.full_scale, layout.stuck_after, layout.stuck_min,
            last_raw, same, layout.valid)
        decisions = np.packbits(present, bitorder="little").tobytes()
        faults = np.packbits(faulted, bitorder="little").tobytes() if any_faulted else None
        handed = []
        for ((node, detector, sync, nmt, tpdos_on_sync, _), state), (a, b, p, q) in zip(sampling, layout.spans):
            sync.last_cycle = cycle
            sync.last_counter = counter
            node_raw, node_same = raw[a:b], same[a:b]
            handed.append((node_raw, node_same))
            if any_faulted or detector.fault:
                node_faulted = faulted[a:b]
                detector.record(x[a:b], node_raw, node_same, decisions[p:q], counter, node_faulted,
                                open_circuit[a:b], any_faulted and np.count_nonzero(node_faulted) > 0,
                                faults[p:q] if faults is not None else None)
            else:
                detector.record(x[a:b], node_raw, node_same, decisions[p:q], counter, None, None, False)
            if state == OPERATIONAL:
                tpdos_on_sync(counter)
        layout.raw, layout.same, layout.handed = raw, same, handed


__all__ = ["PatchSyncBatch"]
