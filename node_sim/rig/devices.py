"""The rig's devices: the node twins of a scene's taxels and patches on the rig's channels.

Start-up (what a real node has in its non-volatile memory; a master that configures nothing still
gets working nodes): each node's OD is written from the scene (taxel nodes:
:func:`node_sim.taxel.startup.taxel_startup_values`; patch nodes:
:func:`node_sim.patch.startup.patch_startup_values`); these values are what NMT reset-node /
reset-communication restore. Then every node sends its boot-up.

LSS (CiA 305, :mod:`node_sim.lss`): every taxel is a device with an LSS slave whose address is its
0x1018 (the EDS's vendor-ID, product code and revision, :func:`identity_serial`). With ``[master]
assign_ids = "lss"`` the devices start non-configured (node-ID 0xFF): no node twin, no boot-up,
only LSS, until a master gives each a node-ID (Fastscan, configure node-ID, switch state global);
the device then boots as a node twin under that node-ID, with the start-up values of its taxel for
that node-ID. An NMT reset that activates another node-ID (configured over LSS) starts the device
again in the same way. One LSS request reaches every slave of the channel; identical answers leave
as one frame, as on a CAN bus.

:class:`SceneDevices` is that part of :class:`~node_sim.rig.Rig` (a mixin).
"""

from __future__ import annotations

import logging

import numpy as np

from taxel_net import patches

from .. import lss as lssx
from .. import od as odx
from ..node import TaxelNode
from ..patch import PatchNode, patch_startup_values
from ..taxel.startup import identity_serial, taxel_startup_values
from .channel import Channel

logger = logging.getLogger("node_sim.rig")


class SceneDevices:
    """The node twins of :class:`~node_sim.rig.Rig` (module docstring): created, configured, renumbered."""

    def _create_devices(self) -> None:
        """Every device of the served channels: a patch node per patch device, else an LSS slave per
        taxel and, unless the master assigns the node-IDs over LSS, its node twin."""
        unconfigured = self.scene.master.assign_ids == "lss"
        identity, bit_rates = self._lss_device()
        for device in self.devices or ():   # patch nodes (the scene loader refuses LSS for them)
            if device.channel in self._channel_at:
                self._new_patch_node(self._channel_at[device.channel], device)
        for i, t in enumerate(self.scene.taxels if self.devices is None else ()):
            if t.channel not in self._channel_at:
                continue
            ch = self._channel_at[t.channel]
            ch.lss[i] = lssx.LssSlave(
                identity + (identity_serial(self.scene, t),),
                lssx.UNCONFIGURED if unconfigured else t.node_id, self.bitrate or self.scene.bus.bitrate,
                bit_rates=bit_rates, activate=lambda node_id, ch=ch, i=i: self._renumber(ch, i, None, node_id),
                call_later=ch.scheduler.call_later)
            if not unconfigured:
                self._new_node(ch, i, t.node_id)

    def _power_on(self) -> None:
        """Every node's boot-up (its silence applied first)."""
        for ch in self._channels:
            with ch.lock:
                for node in ch.nodes.values():
                    self._apply_silence(ch.index, node, 0)
                    node.power_on()

    def _lss_device(self) -> tuple[tuple[int, int, int], frozenset[int]]:
        """What the EDS says of every device: 0x1018:1-3 (vendor-ID, product code, revision
        number) and the bit rates it supports ([DeviceInfo] BaudRate_*), bit/s."""
        od = odx.load_od(1, self.eds_path)
        identity = tuple(int(odx.variable(od, odx.IDENTITY, sub).default) for sub in (1, 2, 3))
        return identity, frozenset(od.device_information.allowed_baudrates)

    def _new_node(self, ch: Channel, index: int, node_id: int) -> TaxelNode:
        """The node twin of taxel ``index`` under ``node_id``, configured with its start-up values."""
        node = TaxelNode(node_id, ch.link, eds_path=self.eds_path, lss=ch.lss[index],
                         renumber=lambda old, new, command: self._renumber(ch, index, old, new, command),
                         fd=self.scene.bus.fd)
        node.configure(self._startup_values(self.scene.taxels[index], node_id))
        if node_id in ch.nodes:
            logger.warning("node-sim channel %s: two nodes with node-ID %d: frames to it reach one only",
                           ch.name, node_id)
        ch.nodes[node_id] = node
        ch.scene_index[node_id] = index
        ch._sync_map = None
        return node

    def _new_patch_node(self, ch: Channel, device: patches.Device) -> PatchNode:
        """The patch node twin of ``device``, configured with its start-up values."""
        node = PatchNode(device.node_id, ch.link, len(device.taxels), eds_path=self.patch_eds_path,
                         fd=self.scene.bus.fd)
        serial = identity_serial(self.scene, self.scene.taxels[device.taxels[0]])
        node.configure(patch_startup_values(self.scene, device, serial))
        if device.node_id in ch.nodes:
            logger.warning("node-sim channel %s: two nodes with node-ID %d", ch.name, device.node_id)
        taxels = device.taxels
        contiguous = list(taxels) == list(range(taxels[0], taxels[0] + len(taxels)))
        ch.nodes[device.node_id] = node
        ch.scene_index[device.node_id] = (slice(taxels[0], taxels[0] + len(taxels)) if contiguous
                                          else np.asarray(taxels, dtype=np.intp))
        ch.patch = True
        ch._sync_map = None
        return node

    def _renumber(self, ch: Channel, index: int, old: TaxelNode | None, node_id: int, command: int = 0) -> None:
        """CiA 305: taxel ``index`` starts again under ``node_id`` (LSS switch state global of a
        non-configured node, or an NMT reset with another pending / stored node-ID): its old node
        leaves the bus; unless ``node_id`` is 0xFF (non-configured: LSS only) a new node boots
        with the start-up values of that node-ID (after a reset communication the application
        area 0x2000-0xFFFF keeps its values)."""
        if old is not None:
            old.shutdown()
            if ch.nodes.get(old.node_id) is old:
                del ch.nodes[old.node_id]
                ch.scene_index.pop(old.node_id, None)
            ch._sync_map = None
        if node_id == lssx.UNCONFIGURED:
            return
        node = self._new_node(ch, index, node_id)
        if old is not None and command != 0x81:  # reset communication: the application area stays
            store = node.local.data_store
            store.update({i: dict(subs) for i, subs in old.local.data_store.items() if i not in odx.COMM_AREA})
            node.detector.invalidate()
        self._apply_silence(ch.index, node, ch.cycle if ch.cycle is not None else 0)
        ch.refresh_filters()
        node.power_on()

    def _startup_values(self, t, node_id: int | None = None) -> dict[tuple[int, int], object]:
        """Start-up values of taxel ``t`` running under ``node_id`` (default: the scene's)."""
        return taxel_startup_values(self.scene, t, node_id)
