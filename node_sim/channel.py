"""Where the rig's channel was: it lives in :mod:`node_sim.rig.channel` (the rig's package, issue
22); re-exported here so that ``node_sim.channel`` imports keep working."""

from __future__ import annotations

from .rig.channel import CONSUMED_FILTERS, Channel, virtual_burst_sender  # noqa: F401 - re-exported
