"""The taxel node's start-up values: what a real node has in its non-volatile memory.

A master that configures nothing still gets working nodes: the rig (:mod:`node_sim.rig`) writes
each taxel node's OD from the scene with :func:`taxel_startup_values` - ζ, N_i, kind, x, y
(0x2001), slope/intercept (0x6126/0x6127), serial number (0x1018:4, :func:`identity_serial`),
heartbeat time (0x1017 = ``bus.heartbeat_producer_ms``), SYNC counter overflow (0x1019 =
``bus.sync_counter``), TPDO transmission type / inhibit time / event timer (0x1800/0x1801 from
``bus``), TPDO2 enabled iff ``bus.mode == "raw"``, and the stuck-reading detector switched off
(0x2002:2 = 0) for a taxel simulated without noise (``noise_sigma_mv == 0``: its readings are
legitimately identical). These values are what NMT reset-node / reset-communication restore.
"""

from __future__ import annotations

from taxel_net.identity import identity_serial  # noqa: F401 - 0x1018:4, importable from here as before
from taxel_net.scene import TAXEL_KINDS, Scene

from .. import od as odx
from ..od import COB_INVALID


def taxel_startup_values(scene: Scene, t, node_id: int | None = None) -> dict[tuple[int, int], object]:
    """Start-up values of taxel ``t`` of ``scene`` running under ``node_id`` (default: the scene's)."""
    node_id = t.node_id if node_id is None else node_id
    bus = scene.bus
    values: dict[tuple[int, int], object] = {
        odx.ZETA: float(t.zeta_mv),
        odx.NOISE_ESTIMATE: float(t.noise_mv),
        odx.TAXEL_KIND: TAXEL_KINDS[t.kind],
        (odx.HEARTBEAT_PRODUCER, 0): int(bus.heartbeat_producer_ms),
        (odx.SYNC_OVERFLOW, 0): int(bus.sync_counter),
        (odx.IDENTITY, 4): identity_serial(scene, t),
    }
    if t.x is not None:
        values[odx.POS_X] = float(t.x)
    if t.y is not None:
        values[odx.POS_Y] = float(t.y)
    if t.slope is not None:
        values[(odx.AI_SCALING_FACTOR, 1)] = float(t.slope)
    if t.intercept is not None:
        values[(odx.AI_SCALING_OFFSET, 1)] = float(t.intercept)
    if t.noise_sigma_mv == 0:
        values[odx.STUCK_SAMPLES] = 0
    for pdo, comm in enumerate(odx.TPDO_COMM):
        values[(comm, 2)] = int(bus.transmission_type)
        values[(comm, 3)] = int(bus.inhibit_time_100us)
        values[(comm, 5)] = int(bus.event_timer_ms)
    # raw mode: the node sends its reading (TPDO2) *instead of* its decision (TPDO1)
    raw = bus.mode == "raw"
    # bit 30 set: no RTR (the twins never answer a remote frame), as in the EDS defaults
    tpdo1_cob, tpdo2_cob = odx.COB_NO_RTR | 0x180 + node_id, odx.COB_NO_RTR | 0x280 + node_id
    values[(odx.TPDO_COMM[0], 1)] = tpdo1_cob | COB_INVALID if raw else tpdo1_cob
    # the cycle tag (decision mode with a SYNC counter): TPDO1 maps 0x2003 instead of 0x2000
    values[(odx.TPDO_MAP[0], 1)] = (odx.TAGGED_DECISION if bus.cycle_tag else odx.LOCAL_DECISION) << 16 | 8
    values[(odx.SYNC_WINDOW, 0)] = int(bus.sync_window)
    values[(odx.TPDO_COMM[1], 1)] = tpdo2_cob if raw else tpdo2_cob | COB_INVALID
    return values
