"""Where every taxel of a scene is on the buses: the static layout the cycle assembler
(:mod:`.cycles`) looks frames up in.

Devices (CANopen nodes: one per taxel in the chapter's layout, or patch nodes of many taxels,
:func:`taxel_net.patches.devices`), their labels as records name them, the device of every
taxel, the device of every node-ID per channel, each channel's devices, the COB-ID tables per
channel (:func:`.decoder.build_cob_tables`) and, with patch nodes, one *slot* per TPDO (its
device, its taxels, its decoder). A function of the scene alone: built once, never changed.
"""

from __future__ import annotations

import numpy as np

from taxel_net.patches import ENC_BITS, devices as scene_devices, node_label
from taxel_net.scene import Scene
from .decoder import SlotDecoder, build_cob_tables


def taxel_index(taxels: tuple[int, ...]):
    """A slice when the taxels are consecutive (cheap views), else an index array."""
    if taxels and list(taxels) == list(range(taxels[0], taxels[0] + len(taxels))):
        return slice(taxels[0], taxels[0] + len(taxels))
    return np.array(taxels, dtype=np.intp)


class CycleLayout:
    """The layout of ``scene`` (module docstring); attributes only."""

    def __init__(self, scene: Scene):
        bus = scene.bus
        # devices (CANopen nodes): node states, liveness and SDO bookkeeping are per device;
        # decisions and readings per taxel. One-taxel scenes: device index == taxel index.
        self.devices = devs = scene_devices(scene)
        self.n_devices = len(devs)
        self.tables = build_cob_tables(scene, devs)
        self.labels = [node_label(d.channel, d.node_id) for d in devs]  # as records name the devices
        self.taxel_device = np.zeros(scene.n, dtype=np.intp)  # device index of every taxel
        for d, dev in enumerate(devs):
            self.taxel_device[list(dev.taxels)] = d
        self.index_by_node: list[dict[int, int]] = [dict() for _ in bus.channels]  # node-ID -> device
        for d, dev in enumerate(devs):
            self.index_by_node[dev.channel][dev.node_id] = d
        self.channel_members = [
            np.array([d for d, dev in enumerate(devs) if dev.channel == c], dtype=np.intp)
            for c in range(len(bus.channels))
        ]
        # patch TPDOs: one slot each, numbered over the devices in order (decoder.build_cob_tables)
        patch = bool(bus.patch_nodes)
        self.slot_tpdo = [tpdo for dev in devs for tpdo in dev.tpdos] if patch else []
        self.slot_device = np.array([d for d, dev in enumerate(devs) for _ in dev.tpdos] if patch else [],
                                    dtype=np.intp)
        self.slot_taxels = [taxel_index(dev.taxels[t.first:t.first + t.count])
                            for dev in devs for t in dev.tpdos] if patch else []
        self.slot_is_bits = [t.encoding == ENC_BITS for t in self.slot_tpdo]
        self.slot_decoders = [SlotDecoder(t, bus.raw_lsb_mv) for t in self.slot_tpdo]
        self.device_slots = np.array([len(dev.tpdos) for dev in devs], dtype=np.int64)  # TPDOs per device
