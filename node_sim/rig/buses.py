"""The rig's buses: ONE python-can bus object per served scene channel, and its receive thread.

``Rig(scene, ...)`` opens one bus object per scene channel (``scene.bus.channels``; more than 127
taxels need several, each its own CANopen network) and puts all that channel's node twins on it
(:class:`~node_sim.rig.channel.Channel`): python-can's ``virtual`` interface deep-copies every
frame once per *receiving bus object*, so one bus per node would multiply the work by the node
count. One receive thread serves all the channels' buses (:func:`taxel_net.receiver.notifiers_for`).

:class:`ChannelBuses` is that part of :class:`~node_sim.rig.Rig` (a mixin).
"""

from __future__ import annotations

import logging

import can

from taxel_net.canmsg import tune_udp_multicast
from taxel_net.errors import ParameterError
from taxel_net.receiver import notifiers_for

from .channel import Channel

logger = logging.getLogger("node_sim.rig")


class ChannelBuses:
    """The buses of :class:`~node_sim.rig.Rig` (module docstring): opened, received from, closed."""

    def _bus_kwargs(self) -> dict:
        """The keywords of every ``can.Bus`` of the rig (its channels' and the gripper drive's)."""
        kwargs = dict(self.bus_kwargs)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        if self.scene.bus.fd:
            kwargs.setdefault("fd", True)   # udp_multicast / socketcan refuse FD frames without it
        return kwargs

    def _open_channels(self) -> None:
        """A bus object and a :class:`Channel` per served scene channel."""
        for index, name in enumerate(self.channel_names):
            if index not in self.served:
                continue
            kwargs = self._bus_kwargs()
            try:
                bus = can.Bus(interface=self.interface, channel=name, **kwargs)
            except Exception as exc:  # noqa: BLE001 - any backend failure is "cannot open"
                raise ParameterError("channel", name,
                                     f"cannot be opened with python-can interface {self.interface!r}: "
                                     f"{type(exc).__name__}: {exc}") from None
            tune_udp_multicast(bus)  # udp_multicast: its own group only, room for bursts (57 SDO clients)
            self._channels.append(Channel(self, index, name, bus))
            self._channel_at[index] = self._channels[-1]

    def _start_receiving(self) -> None:
        """One receive thread for all the channels' buses (udp_multicast, socketcan, virtual:
        taxel_net/receiver.py), else a python-can Notifier each; the channels' filters first."""
        for ch in self._channels:
            ch.refresh_filters()
        handles = notifiers_for([(ch.bus, [ch]) for ch in self._channels], timeout=0.05, name="node-sim-receive")
        for ch, handle in zip(self._channels, handles):
            ch.notifier = handle

    def _close_channels(self) -> None:
        """Every node shut down, the receive threads and the buses stopped; no channel left."""
        for ch in self._channels:
            with ch.lock:
                for node in ch.nodes.values():
                    node.shutdown()
            if ch.notifier is not None:
                ch.notifier.stop(timeout=2)
            try:
                ch.bus.shutdown()
            except Exception:  # noqa: BLE001
                logger.exception("node-sim: bus shutdown failed")
        self._channels = []
        self._channel_at = {}
