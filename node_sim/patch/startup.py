"""Start-up values of a patch node (:func:`patch_startup_values`): what :meth:`PatchNode.configure`
gets so that the node sends exactly the frames :func:`taxel_net.patches.devices` describes for the
device; :func:`tpdo_mapping`, the mapping entries of one of its TPDOs.
"""

from __future__ import annotations

from taxel_net import patches as P
from taxel_net.scene import TAXEL_KINDS

from .. import od as odx
from .objects import TPDO_COMM, TPDO_MAP


def patch_startup_values(scene, device: P.Device, identity_serial: int) -> dict[tuple[int, int], object]:
    """Start-up values of ``device`` (a patch of ``scene``, :func:`taxel_net.patches.devices`):
    its taxels' arrays, the communication parameters of ``scene.bus`` and the TPDOs the device
    describes (COB-ID, mapping: tag, then the array entries of its taxels; the other TPDOs
    keep the EDS defaults: not valid). In an order :meth:`TaxelNode.configure` accepts (mapping entries before sub 0)."""
    bus = scene.bus
    taxels = [scene.taxels[i] for i in device.taxels]
    values: dict[tuple[int, int], object] = {
        (odx.HEARTBEAT_PRODUCER, 0): int(bus.heartbeat_producer_ms),
        (odx.SYNC_OVERFLOW, 0): int(bus.sync_counter),
        (odx.IDENTITY, 4): identity_serial,
        (odx.SYNC_WINDOW, 0): int(bus.sync_window),
        (P.PATCH_RAW_LSB, 0): float(bus.raw_lsb_mv),
    }
    for sub, t in enumerate(taxels, start=1):
        values[(P.PATCH_ZETA, sub)] = float(t.zeta_mv)
        values[(P.PATCH_NOISE, sub)] = float(t.noise_mv)
        values[(P.PATCH_KIND, sub)] = TAXEL_KINDS[t.kind]
        if t.x is not None:
            values[(P.PATCH_X, sub)] = float(t.x)
        if t.y is not None:
            values[(P.PATCH_Y, sub)] = float(t.y)
    if any(t.noise_sigma_mv == 0 for t in taxels):
        values[odx.STUCK_SAMPLES] = 0   # a noiseless taxel repeats its readings legitimately
    for tpdo in device.tpdos:
        comm, mapping = TPDO_COMM[tpdo.number], TPDO_MAP[tpdo.number]
        values[(comm, 1)] = odx.COB_NO_RTR | tpdo.cob_id
        values[(comm, 2)] = int(bus.transmission_type)
        values[(comm, 3)] = int(bus.inhibit_time_100us)
        values[(comm, 5)] = int(bus.event_timer_ms)
        entries = tpdo_mapping(tpdo)
        for sub, entry in enumerate(entries, start=1):
            values[(mapping, sub)] = entry
        values[(mapping, 0)] = len(entries)
    return values


def tpdo_mapping(tpdo: P.Tpdo) -> list[int]:
    """The mapping entries (index << 16 | sub << 8 | bits) of a patch TPDO: the cycle tag when
    tagged, then its taxels' decision bytes / readings."""
    entries = [P.PATCH_CYCLE_TAG << 16 | 8] if tpdo.tagged else []
    if tpdo.encoding == P.ENC_BITS:
        first = tpdo.first // 8 + 1
        entries += [P.PATCH_DECISIONS << 16 | sub << 8 | 8 for sub in range(first, first + tpdo.payload_bytes)]
    elif tpdo.encoding in P.RAW_BYTES:
        index, bits = ((P.PATCH_READINGS_I8, 8) if tpdo.encoding == P.ENC_INT8 else (P.PATCH_READINGS_I16, 16))
        entries += [index << 16 | sub << 8 | bits for sub in range(tpdo.first + 1, tpdo.first + tpdo.count + 1)]
    else:
        raise ValueError(f"{tpdo.encoding}: not a patch encoding")
    return entries

