"""The SDO configuration the fusion centre's master writes to each node from the scene (CiA 301;
:meth:`fusion_center.service.master.Master.configure_node`, ``fusion-center dcf``).

Object dictionary entries written to every node (``eds/taxel_node.eds``):

========  ===  =====================================================================
index     sub  value
========  ===  =====================================================================
0x2001    1-5  ζ (REAL32 mV, eq 3), N_i (eq 4), kind code, x, y (x/y only if given)
0x6126    1    calibration slope m (eq 23), only when the scene gives one
0x6127    1    calibration intercept c (eq 23), only when the scene gives one
0x1017    0    heartbeat producer time (ms)
0x1016    1    heartbeat consumer: master node-ID << 16 | 3 x the master's heartbeat period
                (at least 300 ms), so a node whose master died reports EMCY 0x8130 and takes
                the state of its 0x1029:1 (default: pre-operational); 0 when the master
                sends no heartbeat
0x1800    1-5  TPDO1: COB-ID invalid -> transmission type, inhibit time, event timer
                -> COB-ID 0x180+id valid (CiA 301: sub 3 only while the PDO is invalid);
                left invalid in raw mode: the node sends its reading *instead of* u_i
0x1801    1-5  TPDO2: the same; left invalid unless the scene is in raw mode
========  ===  =====================================================================

Patch nodes (``[bus] patch_nodes``, ``eds/taxel_patch.eds``, :func:`patch_configuration`): one
node per device of :func:`taxel_net.patches.devices`, configured with the same heartbeat,
0x1016, 0x1019 and 0x1007 entries, then every TPDO k of the device as its
:class:`~taxel_net.patches.Tpdo` says, in CiA 301's order: 0x1800+k:1 invalid (bit 31, bit 30
no RTR), :2 transmission type, :3 inhibit time, :5 event timer, 0x1A00+k:0 = 0, the mapping
entries (0x2021:00 the UNSIGNED8 cycle tag when tagged, then 0x2020:sub UNSIGNED8 decision
bytes, or 0x2030:sub INTEGER8 / 0x2031:sub INTEGER16 readings, one per taxel), 0x1A00+k:0 = n,
0x1800+k:1 valid; in raw mode 0x2032 (mV per count) first. The per-taxel detector arrays
(0x2010 ζ, 0x2011 N_i: two SDO writes per taxel, 8,192 for skin4096) come first: measured on
the virtual bus, skin4096's boot takes 2.7 s with them (9,504 writes, 8 SDO clients in
parallel) against 0.5 s without (1,312), so they are written (``Master.detector_writes =
False`` leaves the nodes their stored values), docs/service.md.
"""

from __future__ import annotations

from taxel_net import patches
from taxel_net.scene import TAXEL_KINDS, Scene

from .decoder import BASE_TPDO1, BASE_TPDO2

COB_INVALID = 0x8000_0000
COB_NO_RTR = 0x4000_0000  # TPDO COB-ID bit 30 (CiA 301): no remote transmission request
HEARTBEAT_PRODUCER = 0x1017
CONSUMER_HEARTBEAT = 0x1016
CONSUMER_TIME_MIN_MS = 300  # the nodes' consumer time for the master: 3 x its period, at least this
TPDO_COMM = (0x1800, 0x1801)
TPDO_MAP = (0x1A00, 0x1A01)
SYNC_WINDOW = 0x1007
SYNC_OVERFLOW = 0x1019
LOCAL_DECISION = 0x2000
TAGGED_DECISION = 0x2003
DETECTOR = 0x2001
AI_SCALING_FACTOR = 0x6126
AI_SCALING_OFFSET = 0x6127


def node_configuration(scene: Scene, index: int) -> list[tuple[int, int, object]]:
    """The SDO downloads (index, subindex, value) that configure taxel ``index`` of ``scene``."""
    t = scene.taxels[index]
    bus = scene.bus
    writes: list[tuple[int, int, object]] = [
        (DETECTOR, 1, float(t.zeta_mv)),
        (DETECTOR, 2, float(t.noise_mv)),
        (DETECTOR, 3, TAXEL_KINDS[t.kind]),
    ]
    if t.x is not None:
        writes.append((DETECTOR, 4, float(t.x)))
    if t.y is not None:
        writes.append((DETECTOR, 5, float(t.y)))
    if t.slope is not None:
        writes.append((AI_SCALING_FACTOR, 1, float(t.slope)))
    if t.intercept is not None:
        writes.append((AI_SCALING_OFFSET, 1, float(t.intercept)))
    writes.append((HEARTBEAT_PRODUCER, 0, int(bus.heartbeat_producer_ms)))
    writes.append((CONSUMER_HEARTBEAT, 1, master_consumer_entry(scene)))
    writes.append((SYNC_OVERFLOW, 0, int(bus.sync_counter)))
    writes.append((SYNC_WINDOW, 0, int(bus.sync_window)))
    for comm, base, enabled in ((TPDO_COMM[0], BASE_TPDO1, bus.mode != "raw"),
                                (TPDO_COMM[1], BASE_TPDO2, bus.mode == "raw")):
        cob = COB_NO_RTR | base + t.node_id  # bit 30: no RTR, as the EDS defaults and the twins' start-up values
        writes.append((comm, 1, cob | COB_INVALID))
        writes.append((comm, 2, int(bus.transmission_type)))
        writes.append((comm, 3, int(bus.inhibit_time_100us)))
        writes.append((comm, 5, int(bus.event_timer_ms)))
        if comm == TPDO_COMM[0]:
            # TPDO1 maps the tagged decision 0x2003 when the SYNC carries a counter (the cycle
            # tag), else u_i 0x2000; CiA 301: mapping only while the PDO is invalid, sub 0 first
            entry = (TAGGED_DECISION if bus.cycle_tag else LOCAL_DECISION) << 16 | 8
            writes += [(TPDO_MAP[0], 0, 0), (TPDO_MAP[0], 1, entry), (TPDO_MAP[0], 0, 1)]
        if enabled:
            writes.append((comm, 1, cob))
    return writes


def patch_configuration(scene: Scene, device: patches.Device, *, detector: bool = True
                        ) -> list[tuple[int, int, int | float, str]]:
    """The SDO downloads ``(index, subindex, value, struct format)`` that configure the patch
    node ``device`` (module docstring): communication objects, then every TPDO's parameters
    and mapping as its :class:`~taxel_net.patches.Tpdo` describes. ``detector``: also ζ and
    N_i of every taxel (0x2010 / 0x2011 sub k + 1 for the device's taxel k)."""
    bus = scene.bus
    writes: list[tuple[int, int, int | float, str]] = []
    if detector:
        for k, i in enumerate(device.taxels):
            t = scene.taxels[i]
            writes.append((patches.PATCH_ZETA, k + 1, float(t.zeta_mv), "f"))
            writes.append((patches.PATCH_NOISE, k + 1, float(t.noise_mv), "f"))
    if bus.mode == "raw":
        writes.append((patches.PATCH_RAW_LSB, 0, float(bus.raw_lsb_mv), "f"))
    writes.append((HEARTBEAT_PRODUCER, 0, int(bus.heartbeat_producer_ms), "H"))
    writes.append((CONSUMER_HEARTBEAT, 1, master_consumer_entry(scene), "I"))
    writes.append((SYNC_OVERFLOW, 0, int(bus.sync_counter), "B"))
    writes.append((SYNC_WINDOW, 0, int(bus.sync_window), "I"))
    for tpdo in device.tpdos:
        comm, mapping = 0x1800 + tpdo.number, 0x1A00 + tpdo.number
        cob = COB_NO_RTR | tpdo.cob_id
        writes.append((comm, 1, cob | COB_INVALID, "I"))
        writes.append((comm, 2, int(bus.transmission_type), "B"))
        writes.append((comm, 3, int(bus.inhibit_time_100us), "H"))
        writes.append((comm, 5, int(bus.event_timer_ms), "H"))
        entries = patch_mapping(tpdo)
        writes.append((mapping, 0, 0, "B"))
        writes += [(mapping, sub, entry, "I") for sub, entry in enumerate(entries, start=1)]
        writes.append((mapping, 0, len(entries), "B"))
        writes.append((comm, 1, cob, "I"))
    return writes


def patch_mapping(tpdo: patches.Tpdo) -> list[int]:
    """The PDO mapping entries (index << 16 | sub << 8 | bits) of a patch TPDO."""
    entries = [patches.PATCH_CYCLE_TAG << 16 | 8] if tpdo.tagged else []
    if tpdo.encoding == patches.ENC_BITS:
        first = tpdo.first // 8  # a decision frame starts on a byte of the array
        entries += [patches.PATCH_DECISIONS << 16 | (first + j + 1) << 8 | 8 for j in range(tpdo.payload_bytes)]
    elif tpdo.encoding == patches.ENC_INT8:
        entries += [patches.PATCH_READINGS_I8 << 16 | (tpdo.first + j + 1) << 8 | 8 for j in range(tpdo.count)]
    elif tpdo.encoding == patches.ENC_INT16:
        entries += [patches.PATCH_READINGS_I16 << 16 | (tpdo.first + j + 1) << 8 | 16 for j in range(tpdo.count)]
    else:
        raise ValueError(f"TPDO 0x{tpdo.cob_id:03X}: {tpdo.encoding} is not a patch encoding")
    return entries


def master_consumer_entry(scene: Scene) -> int:
    """0x1016:1 of every node: ``master node-ID << 16 | consumer time ms`` with a generous
    consumer time (3 x the master's heartbeat period, at least :data:`CONSUMER_TIME_MIN_MS`;
    the scene loader keeps it within 16 bits), or 0 (off) when the master sends no heartbeat."""
    period = scene.master_heartbeat_ms
    if period <= 0:
        return 0
    return scene.master.node_id << 16 | min(0xFFFF, max(CONSUMER_TIME_MIN_MS, 3 * period))
