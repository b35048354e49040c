"""The rig: every node twin of a scene on its CAN bus(es), configured and booted (:class:`Rig`).

``Rig(scene, ...)`` opens ONE python-can bus object per served scene channel and puts all that
channel's node twins on it (:mod:`.buses`, :mod:`.channel`); creates and configures every device
of the scene - taxel nodes with their LSS slaves, or patch nodes (:mod:`.devices`) - then every
node sends its boot-up; feeds them their readings (:mod:`.readings`); and runs the scene's gripper
drive and grasp world (:mod:`.drive`). :class:`Rig` composes those parts (mixins, one module per
job: what each owns is set up by its ``_init_*`` / ``_start_*``) and is the public API: life
cycle, silence faults, introspection.

SYNC cycle number: the nodes of a channel sample X_i for cycle ``c`` = the number of SYNCs
the rig has seen on that channel since :meth:`Rig.start` (the first SYNC is cycle 0). When
the SYNC carries a counter byte (the nodes' 0x1019 = overflow value 2..240, start-up value
``bus.sync_counter``; a SYNC whose length does not match 0x1019 is a length error), a jump of
the counter is read as lost SYNCs: the cycle number advances by the counter difference and
``lost_syncs`` counts the gap, so the nodes stay aligned with the master's cycles.

"silent" faults (scene) and :meth:`Rig.drop_node` make a node dead (no frame out, none
processed) until the fault ends / :meth:`Rig.restore_node`.

SYNC hot path: the frames of one SYNC leave as one burst after every node has sampled
(``NodeLink.hold``/``release``; inhibit times start when the burst is sent), on a ``virtual``
bus without python-can's per-receiver deep copy (:func:`node_sim.rig.channel.virtual_burst_sender`).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Mapping, Sequence

import can

from taxel_net import gcfreeze, patches
from taxel_net.errors import ParameterError
from taxel_net.scene import Scene

from .. import lss as lssx
from .. import od as odx
from ..gripper.host import GRIPPER_EDS_PATH
from ..node import TaxelNode
from ..patch import PATCH_EDS_PATH
from .buses import ChannelBuses
from .channel import Channel
from .devices import SceneDevices
from .drive import DriveAndWorld
from .readings import ReadingFeed, ReadingSource


class Rig(ChannelBuses, SceneDevices, ReadingFeed, DriveAndWorld):
    """All node twins of ``scene`` (see module docstring).

    ``interface``: any python-can interface name ("virtual", "udp_multicast", "socketcan", …).
    ``channel``: None = the scene's channel names; a string (one scene channel) or a sequence
    (one per scene channel). ``bitrate`` is passed to ``can.Bus`` when given.
    ``bus_kwargs``: extra keyword arguments for every ``can.Bus`` (e.g. ``port`` of udp_multicast).
    ``serve_channels``: scene channel indices this rig runs (default all): a scene sharded over
    several rigs (``node-sim --serve``) opens only these buses and creates only their nodes.
    """

    def __init__(self, scene: Scene, interface: str = "virtual", channel: str | Sequence[str] | None = None,
                 bitrate: int | None = None, reading_source: ReadingSource | None = None,
                 seed: int | None = None, eds_path=odx.EDS_PATH, bus_kwargs: Mapping | None = None,
                 patch_eds_path=PATCH_EDS_PATH, serve_channels: Sequence[int] | None = None,
                 gripper_eds_path=GRIPPER_EDS_PATH, on_truth=None):
        if not isinstance(scene, Scene):
            raise ParameterError("scene", type(scene).__name__, "must be a taxel_net.scene.Scene")
        if scene.n == 0:
            raise ParameterError("scene.taxels", (), "a rig needs at least one taxel")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= 2**63 - 1):
            raise ParameterError("seed", seed, "must be an integer 0..2^63-1 (the scene's [scene] seed range)")
        self.scene = scene if seed is None else dataclasses.replace(scene, seed=seed)
        self.interface = interface
        names = list(scene.bus.channels)
        if channel is None:
            self.channel_names = names
        elif isinstance(channel, str):
            if len(names) != 1:
                raise ParameterError("channel", channel,
                                     f"the scene has {len(names)} channels: give one bus channel per scene channel")
            self.channel_names = [channel]
        else:
            if len(channel) != len(names):
                raise ParameterError("channel", list(channel), f"need exactly {len(names)} (one per scene channel)")
            self.channel_names = [str(c) for c in channel]
        if serve_channels is None:
            self.served = tuple(range(len(names)))
        else:
            served = sorted(set(int(c) for c in serve_channels))
            if not served or any(not 0 <= c < len(names) for c in served):
                raise ParameterError("serve_channels", list(serve_channels),
                                     f"scene channel indices 0..{len(names) - 1}, at least one")
            self.served = tuple(served)
        self.bitrate = bitrate
        self.bus_kwargs = dict(bus_kwargs or {})
        self.eds_path = odx.check_eds(eds_path)
        # patch nodes (issue 14): one twin per device of taxel_net.patches.devices
        self.devices = patches.devices(self.scene) if scene.bus.patch_nodes else None
        self.patch_eds_path = (odx.check_eds(patch_eds_path, "patch node")
                               if self.devices is not None else None)
        self._reading_source = reading_source
        self._init_drive(gripper_eds_path, on_truth)   # the gripper drive and grasp world (.drive)
        self._channels: list[Channel] = []             # the served channels, in index order
        self._channel_at: dict[int, Channel] = {}       # scene channel index -> its channel
        self._dropped: set[tuple[int, int]] = set()
        self._silent_faults = [f for f in getattr(self.scene, "faults", ()) if f.fault == "silent"]
        self._init_readings()   # the readings cache and read-ahead thread (.readings)
        self._gc_held = False  # holds taxel_net.gcfreeze while started
        self.started = False
        for i, t in enumerate(scene.taxels):
            if not 0 <= t.channel < len(names):
                raise ParameterError(f"taxels[{i}].channel", t.channel, f"must index bus.channels (0..{len(names) - 1})")
        g = scene.gripper
        if g is not None and (not 0 <= g.channel < len(names)
                              or any(t.node_id == g.node_id and t.channel == g.channel for t in scene.taxels)):
            raise ParameterError("gripper", (g.channel, g.node_id), "the drive needs a channel of bus.channels and a "
                                 "node-ID no taxel has on that channel (the scene loader checks this)")

    # ------------------------------------------------------------------ life cycle
    def __enter__(self) -> "Rig":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> "Rig":
        """Open the buses, create and configure every node, send the boot-ups."""
        if self.started:
            return self
        try:
            self._open_channels()
            self._create_devices()
            if self._reading_source is None:
                self._start_prefetch()
            self._start_receiving()
            self._power_on()
            self._start_gripper()
        except BaseException:
            self.stop()
            raise
        self.started = True
        # the set-up (EDS imports, ODs, scene arrays) is not traversed by the cyclic collector
        # while the rig runs: a full collection of it is a pause of tens of ms on a SYNC path
        gcfreeze.hold()
        self._gc_held = True
        return self

    def stop(self) -> None:
        """Stop timers, notifiers and buses (idempotent)."""
        self._stop_drive()
        for ch in self._channels:
            ch.scheduler.stop()
        self._stop_prefetch()
        self._close_channels()
        self.started = False
        if self._gc_held:
            self._gc_held = False
            gcfreeze.release()

    # ------------------------------------------------------------------ faults
    def _apply_silence(self, channel: int, node: TaxelNode, cycle: int) -> None:
        if not self._dropped and not self._silent_faults:
            node.silent = False
            return
        key = (channel, node.node_id)
        silent = key in self._dropped or any(
            f.channel == channel and f.node_id == node.node_id and f.active(cycle) for f in self._silent_faults)
        node.silent = silent

    def drop_node(self, node_id: int, channel: int = 0) -> None:
        """Make a node dead (silent) until :meth:`restore_node`."""
        node = self._node(node_id, channel)
        with self._channel_at[channel].lock:
            self._dropped.add((channel, node_id))
            node.silent = True

    def restore_node(self, node_id: int, channel: int = 0) -> None:
        """End a :meth:`drop_node`; the node resumes in the NMT state it had (no new boot-up)."""
        node = self._node(node_id, channel)
        ch = self._channel_at[channel]
        with ch.lock:
            self._dropped.discard((channel, node_id))
            self._apply_silence(channel, node, ch.cycle if ch.cycle is not None else 0)

    # ------------------------------------------------------------------ introspection
    def _node(self, node_id: int, channel: int) -> TaxelNode:
        if not self._channels:
            raise ParameterError("rig", "stopped", "start() the rig first")
        if channel not in self._channel_at:
            raise ParameterError("channel", channel, f"not served by this rig (serves {list(self.served)})")
        node = self._channel_at[channel].nodes.get(node_id)
        if node is None:
            raise ParameterError("node_id", node_id, f"no such node on channel {channel}")
        return node

    def node(self, node_id: int, channel: int = 0) -> TaxelNode:
        return self._node(node_id, channel)

    @property
    def nodes(self) -> dict[tuple[int, int], TaxelNode]:
        """``{(channel, node_id): TaxelNode}`` of every node (scene order)."""
        return {(ch.index, nid): n for ch in self._channels for nid, n in ch.nodes.items()}

    @property
    def lss_slaves(self) -> dict[int, lssx.LssSlave]:
        """``{taxel index (scene order): LssSlave}``: every device's LSS slave (CiA 305), with
        or without a node-ID (a non-configured one has no entry in :attr:`nodes`)."""
        return {i: s for ch in self._channels for i, s in sorted(ch.lss.items())}

    @property
    def buses(self) -> list[can.BusABC]:
        return [ch.bus for ch in self._channels]

    def cycle(self, channel: int = 0) -> int | None:
        """Cycle number of the last SYNC processed on ``channel`` (None before the first)."""
        return self._channel_at[channel].cycle

    def lost_syncs(self, channel: int = 0) -> int:
        return self._channel_at[channel].lost_syncs

    def frames_sent(self) -> int:
        return sum(ch.frames_sent for ch in self._channels)

    def wait_cycle(self, cycle: int, channel: int = 0, timeout: float = 10.0) -> bool:
        """Block until ``channel`` has processed the SYNC of ``cycle``: every node has sampled it
        and sent the TPDOs it triggers (test/demo helper). False on timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            c = self._channel_at[channel].cycle
            if c is not None and c >= cycle:
                return True
            time.sleep(0.001)
        return False
