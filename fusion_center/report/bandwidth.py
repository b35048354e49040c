"""Exact bus cost of raw-data vs decision streaming for a scene (``fusion-center bandwidth``).

The chapter's sec. 1 trade-off - streaming raw observations to a central detector "requires a
large bandwidth", deciding locally "suffers from loss of information" - priced in bits on the
CAN bus for the scene's taxels, at a given bit rate. Three modes:

* ``raw``: TPDO2 (COB-ID 0x280 + node-ID) carries X_i as REAL32 (0x6130:1, 4 bytes, little
  endian), every SYNC. The data differ from cycle to cycle, and so do the stuff bits: every
  frame of every simulated cycle is priced with its actual payload.
* ``decision_sync``: TPDO1 (0x180 + node-ID) carries u_i (0x2000, INTEGER8: +1 = 0x01,
  -1 = 0xFF, eqs 2-3), every SYNC.
* ``decision_event``: the same TPDO1, event-driven (transmission type 254/255): a node sends
  when u_i differs from the value it last sent, no sooner than the inhibit time (0x1800:3,
  the scene's ``inhibit_time_100us``) after its previous frame, and - with an event timer
  (0x1800:5) - also when that much time passed without a frame. Every node sends once at
  cycle 0 (its first value). Changes are counted on the scene's simulated decision sequence
  (``node_sim.physics``, canonical readings, eqs 1-4), evaluated once per SYNC period.

The TPDOs are the scene's own (``taxel_net.patches.devices``): with a SYNC counter the
one-taxel TPDO1 is the tagged byte 0x2003 (u_i in bits 0-1, the counter mod 64 in bits 2-7);
patch nodes (``[bus] patch_nodes``) send their packed TPDOs (decision bits or INTEGER8/16
readings behind the one-byte cycle tag), and an event-driven patch TPDO goes out when one of
the values it carries changed. On CAN FD (``[bus] fd``) a frame's length is given in bit
times at ``--bitrate``: its nominal bits plus its data-phase bits x bitrate / data_bitrate
(``bus_timing.fd_frame_bits``), so loads, rates and latencies read as for classic frames.

Every cycle also carries the SYNC frame (COB-ID 0x080, no data, or one counter byte when
``sync_counter`` > 0: the counter 1..overflow of that cycle) on each channel; every node's heartbeat (0x700 + node-ID, one byte,
0x05 = operational) every ``heartbeat_producer_ms`` is counted pro rata per cycle.

Figures per mode, per channel (each channel is its own bus at ``--bitrate``) and for the
busiest channel: exact bits per cycle (``fusion_center.core.bus_timing.frame_bits``: stuff bits,
CRC, ACK, EOF and the 3-bit intermission), bus load at the scene's SYNC period, the highest
SYNC rate the traffic fits (worst-case cycle: (bitrate - heartbeat bit/s) / bits of the
cycle's frames) and the latency from the start of the SYNC frame to the end of the cycle's
last PDO, assuming the frames go back to back in CAN-ID priority order right after SYNC
(TPDO IDs 0x18x/0x28x all win arbitration against heartbeats 0x70x, so heartbeats add at most
one frame of blocking, reported separately as ``blocking_ms``).
"""

from __future__ import annotations

import dataclasses
import struct

import numpy as np

from ..core.bus_timing import fd_frame_bits, frame_bits
from ..core.encoding import local_decision
from taxel_net.errors import ParameterError

MODES = ("raw", "decision_sync", "decision_event")
SYNC_COB_ID = 0x080
TPDO1_BASE = 0x180
TPDO2_BASE = 0x280
HEARTBEAT_BASE = 0x700
NMT_OPERATIONAL = 0x05


def _decision_byte(u: int) -> bytes:
    return struct.pack("<b", int(u))  # INTEGER8: +1 -> 0x01, -1 -> 0xFF


def _raw_bytes(x: float) -> bytes:
    return struct.pack("<f", float(x))  # REAL32, little endian (CiA 301)


def simulate_bus_inputs(scene, cycles: int) -> tuple[np.ndarray, np.ndarray]:
    """Readings X (cycles, n) - the canonical ones the node twins send - and decisions u (pm1)."""
    from node_sim import physics

    x = physics.sample_readings_batch(scene, np.arange(cycles))
    noise = np.array([t.noise_mv for t in scene.taxels])
    zeta = np.array([t.zeta_mv for t in scene.taxels])
    return x, local_decision(x, noise, zeta, "pm1")


def event_transmissions(u: np.ndarray, sync_period_ms: float, inhibit_time_100us: int,
                        event_timer_ms: int) -> np.ndarray:
    """Bool (cycles, n): which node sends its event-driven TPDO1 in which cycle (module doc)."""
    cycles, n = u.shape
    period = float(sync_period_ms)
    inhibit = inhibit_time_100us / 10.0
    sends = np.zeros((cycles, n), dtype=bool)
    last_sent = u[0].copy()
    last_time = np.zeros(n)
    sends[0] = True
    for c in range(1, cycles):
        t = c * period
        allowed = (t - last_time) >= inhibit - 1e-9
        due = (u[c] != last_sent)
        if event_timer_ms > 0:
            due |= (t - last_time) >= event_timer_ms - 1e-9
        fire = due & allowed
        sends[c] = fire
        last_sent[fire] = u[c][fire]
        last_time[fire] = t
    return sends


def _channel_figures(frames_per_cycle: list[list[int]], sync_bits: int, heartbeat_bits: list[int],
                     scene, bitrate: int) -> dict:
    period_s = scene.bus.sync_period_ms / 1000.0
    hb_bits_per_s = sum(heartbeat_bits) / (scene.bus.heartbeat_producer_ms / 1000.0) if scene.bus.heartbeat_producer_ms else 0.0
    hb_per_cycle = hb_bits_per_s * period_s
    pdo_bits = np.array([sum(f) for f in frames_per_cycle], dtype=float)
    frames = np.array([len(f) for f in frames_per_cycle], dtype=float)
    sync_per_cycle = np.broadcast_to(np.asarray(sync_bits, dtype=float), pdo_bits.shape)
    cycle_bits = pdo_bits + sync_per_cycle
    worst = float(cycle_bits.max())
    mean_bits = float(cycle_bits.mean() + hb_per_cycle)
    active = cycle_bits[frames > 0]
    capacity = bitrate - hb_bits_per_s
    return {
        "frames_per_cycle": float(frames.mean() + 1),
        "pdo_frames_per_cycle": float(frames.mean()),
        "bits_per_cycle": mean_bits,
        "bits_per_cycle_worst": worst + hb_per_cycle,
        "sync_bits": float(sync_per_cycle.max()),
        "heartbeat_bits_per_cycle": hb_per_cycle,
        "bus_time_per_cycle_ms": 1000.0 * mean_bits / bitrate,
        "bus_load": mean_bits / (period_s * bitrate),
        "bus_load_worst": (worst + hb_per_cycle) / (period_s * bitrate),
        "max_cycle_rate_hz": capacity / worst if capacity > 0 else 0.0,
        "latency_ms": 1000.0 * worst / bitrate,
        "latency_mean_ms": 1000.0 * float((active if active.size else sync_per_cycle).mean()) / bitrate,
        "blocking_ms": 1000.0 * (max(heartbeat_bits) if heartbeat_bits else 0) / bitrate,
    }


def _frame_time_bits(can_id: int, data: bytes, fd: bool, bitrate: int, data_bitrate: int) -> float:
    """A frame's length in bit times at ``bitrate``: exact bits of a classic frame; of a CAN FD
    frame (bit-rate switch on) its nominal bits plus its data-phase bits x bitrate / data_bitrate."""
    if not fd:
        return float(frame_bits(can_id, data))
    nominal, data_phase = fd_frame_bits(can_id, data, brs=True)
    return nominal + data_phase * bitrate / data_bitrate


def _tpdo_bits(scene, mode: str, x: np.ndarray, u: np.ndarray, bitrate: int) -> dict[int, list]:
    """Per channel: ``[(tpdo, bits, signature)]`` in CAN-ID priority order - the exact length of
    every TPDO of every device (taxel_net.patches.devices) in every simulated cycle (``bits``,
    shape (cycles,)) and what its values are (``signature``: changes when a value it carries
    changes - the event-driven trigger). ``mode``: ``raw`` or ``decision``."""
    from taxel_net.patches import (ENC_BITS, ENC_INTEGER8, ENC_REAL32, ENC_TAGGED, devices, pack,
                                   readings_to_counts)

    bus = dataclasses.replace(scene.bus, mode=mode)
    cycles = x.shape[0]
    counters = (np.arange(cycles) % bus.sync_counter + 1) if bus.sync_counter > 0 else np.zeros(cycles, int)
    rate = (bitrate, bus.data_bitrate)
    out: dict[int, list] = {}
    cache: dict[tuple[int, bytes], float] = {}

    def bits_of(tpdo, data: bytes) -> float:
        key = (tpdo.cob_id, data)
        if key not in cache:
            cache[key] = _frame_time_bits(tpdo.cob_id, data, tpdo.fd, *rate)
        return cache[key]

    for dev in devices(dataclasses.replace(scene, bus=bus)):
        for tpdo in dev.tpdos:
            idx = np.asarray(dev.taxels[tpdo.first: tpdo.first + tpdo.count])
            if tpdo.encoding == ENC_REAL32:
                datas = [_raw_bytes(x[c, idx[0]]) for c in range(cycles)]
                signature = x[:, idx[0]]
            elif tpdo.encoding == ENC_INTEGER8:
                datas = [_decision_byte(u[c, idx[0]]) for c in range(cycles)]
                signature = u[:, idx[0]]
            elif tpdo.encoding == ENC_TAGGED:  # 0x2003: u_i in bits 0-1, counter mod 64 in bits 2-7
                datas = [bytes(((int(counters[c]) & 0x3F) << 2 | (0b01 if u[c, idx[0]] > 0 else 0b11),))
                         for c in range(cycles)]
                signature = u[:, idx[0]]
            elif tpdo.encoding == ENC_BITS:
                datas = [pack(tpdo, u[c, idx], int(counters[c]) if tpdo.tagged else None) for c in range(cycles)]
                signature = np.array([hash(d[int(tpdo.tagged):]) for d in datas])
            else:  # packed INTEGER8 / INTEGER16 counts
                datas = [pack(tpdo, readings_to_counts(tpdo, x[c, idx], bus.raw_lsb_mv)[0],
                              int(counters[c]) if tpdo.tagged else None) for c in range(cycles)]
                signature = np.array([hash(d[int(tpdo.tagged):]) for d in datas])
            bits = np.array([bits_of(tpdo, d) for d in datas])
            out.setdefault(dev.channel, []).append((tpdo, bits, signature))
    for frames in out.values():
        frames.sort(key=lambda f: f[0].cob_id)
    return out


def bandwidth_figures(scene, bitrate: int | None = None, cycles: int | None = None,
                      inputs: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """The figures of every mode (module docstring); JSON-ready dict with a ``modes`` key."""
    from taxel_net.patches import devices

    bitrate = scene.bus.bitrate if bitrate is None else bitrate
    if isinstance(bitrate, bool) or not isinstance(bitrate, (int, np.integer)) or not 1 <= bitrate <= 1_000_000:
        raise ParameterError("bitrate", bitrate, "must be an integer bit/s in 1..1000000 (classic CAN)")
    cycles = scene.cycles if cycles is None else cycles
    if isinstance(cycles, bool) or not isinstance(cycles, (int, np.integer)) or cycles < 1:
        raise ParameterError("cycles", cycles, "must be an integer >= 1")
    x, u = simulate_bus_inputs(scene, int(cycles)) if inputs is None else inputs
    bus = scene.bus
    if bus.sync_counter > 0:  # the SYNC carries the counter 1..overflow, cycle by cycle
        sync_per_cycle = np.array([frame_bits(SYNC_COB_ID, bytes((c % bus.sync_counter + 1,)))
                                   for c in range(int(cycles))], dtype=float)
    else:
        sync_per_cycle = np.full(int(cycles), float(frame_bits(SYNC_COB_ID, b"")))
    channels = sorted({t.channel for t in scene.taxels})
    heartbeats: dict[int, list[int]] = {}
    for dev in devices(scene):
        heartbeats.setdefault(dev.channel, []).append(frame_bits(HEARTBEAT_BASE + dev.node_id,
                                                                 bytes([NMT_OPERATIONAL])))
    tpdos = {"raw": _tpdo_bits(scene, "raw", x, u, int(bitrate)),
             "decision": _tpdo_bits(scene, "decision", x, u, int(bitrate))}
    modes: dict[str, dict] = {}
    for mode in MODES:
        per_channel = []
        for ch in channels:
            frames_of = tpdos["raw" if mode == "raw" else "decision"][ch]
            bits = np.stack([b for _, b, _ in frames_of], axis=1)          # (cycles, TPDOs)
            if mode == "decision_event":
                signatures = np.stack([sig for _, _, sig in frames_of], axis=1)
                sends = event_transmissions(signatures, bus.sync_period_ms, bus.inhibit_time_100us,
                                            bus.event_timer_ms)
            else:
                sends = np.ones_like(bits, dtype=bool)
            frames = [bits[c][sends[c]].tolist() for c in range(int(cycles))]
            fig = _channel_figures(frames, sync_per_cycle, heartbeats.get(ch, []), scene, int(bitrate))
            fig["channel"] = scene.bus.channels[ch] if ch < len(scene.bus.channels) else str(ch)
            fig["taxels"] = sum(t.count for t, _, _ in frames_of)
            fig["nodes"] = len(heartbeats.get(ch, []))
            per_channel.append(fig)
        busiest = max(per_channel, key=lambda f: f["bits_per_cycle_worst"])
        summary = {k: v for k, v in busiest.items() if k not in ("channel", "taxels", "nodes")}
        summary["busiest_channel"] = busiest["channel"]
        summary["channels"] = per_channel
        modes[mode] = summary
    return {
        "scene": scene.name,
        "taxels": scene.n,
        "nodes": len(devices(scene)),
        "patch_nodes": bus.patch_nodes,
        "fd": bus.fd,
        "data_bitrate": bus.data_bitrate if bus.fd else None,
        "bitrate": int(bitrate),
        "sync_period_ms": bus.sync_period_ms,
        "heartbeat_producer_ms": bus.heartbeat_producer_ms,
        "inhibit_time_100us": bus.inhibit_time_100us,
        "event_timer_ms": bus.event_timer_ms,
        "cycles_simulated": int(cycles),
        "channels": [scene.bus.channels[c] for c in channels],
        "modes": modes,
        "raw_over_decision_sync": modes["raw"]["bits_per_cycle"] / modes["decision_sync"]["bits_per_cycle"],
    }


# --------------------------------------------------------------------------- layouts compared
LAYOUT_RAW_PAYLOADS = ("raw8", "raw16", "real32")
DEFAULT_PATCH = 192
DEFAULT_DATA_BITRATE = 5_000_000
DEFAULT_P_CHANGE = 0.01


def layout_figures(n_taxels: int, *, nominal_bitrate: int, data_bitrate: int = DEFAULT_DATA_BITRATE,
                   sync_period_ms: float = 10.0, heartbeat_ms: float | None = 100.0, patch: int = DEFAULT_PATCH,
                   raw: str = "raw8", p_change: float = DEFAULT_P_CHANGE, p_one: float = 0.5,
                   channels: int | None = None, sync_counter: int = 0) -> dict:
    """What decisions save over raw data for ``n_taxels`` taxels, layout by layout (JSON-ready).

    Layouts (``fusion_center.core.layouts``): one-taxel nodes (``per-taxel``) and patch nodes of
    ``patch`` taxels, decisions packed one bit per taxel against ``raw`` readings, classic CAN at
    ``nominal_bitrate`` against CAN FD at ``nominal_bitrate`` / ``data_bitrate`` (BRS), every
    TPDO every SYNC (``sync``) and, for decisions, event-driven (``event``: each taxel's
    decision changes with probability ``p_change`` per cycle; raw readings, noisy, change every
    cycle, so event-driven raw data is the synchronous row). With a SYNC counter
    (``sync_counter`` 2..240) every SYNC carries its counter byte and every patch PDO leads with
    the cycle tag byte (``tag_bytes=1``); one-taxel nodes keep one byte per frame. Channels:
    ``channels`` (a scene's), raised to the fewest that hold the layout (<= 127 nodes, <= 1023
    PDO COB-IDs per channel) and lowered to one node per channel. Per row: exact bits per cycle
    over all channels (mean over payloads with P(bit = 1) = ``p_one``, and worst case), the
    busiest channel's load (heartbeats every ``heartbeat_ms`` included) and worst-case load, the
    highest SYNC rate every channel's worst-case cycle fits, the latency (SYNC start to the end
    of the channel's last PDO, worst case) of the slowest channel, and every channel's figures.
    ``ratios``: raw / decision bus time per synchronous cycle over all channels (mean, worst).
    """
    from ..core.layouts import layout_bus_use, skin_layout

    if raw not in LAYOUT_RAW_PAYLOADS:
        raise ParameterError("raw", raw, f"must be one of {', '.join(LAYOUT_RAW_PAYLOADS)}")
    period_s = sync_period_ms / 1000.0
    hb_s = heartbeat_ms / 1000.0 if heartbeat_ms else None
    label = {1: "per-taxel"}
    label.setdefault(patch, f"patch{patch}")
    rows, seconds = [], {}
    for per_node in dict.fromkeys((1, patch)):
        tag = 1 if sync_counter and per_node > 1 else 0
        for payload in ("decision", raw):
            for fd in (False, True):
                kw = dict(taxels_per_node=per_node, payload=payload, fd=fd, tag_bytes=tag)
                layout = skin_layout(n_taxels, **kw)
                if channels is not None and channels > len(layout.channels):
                    layout = skin_layout(n_taxels, channels=min(channels, layout.n_nodes), **kw)
                rates = dict(nominal_bitrate=nominal_bitrate, data_bitrate=data_bitrate if fd else None,
                             sync_period_s=period_s, heartbeat_period_s=hb_s, p_one=p_one,
                             sync_counter=sync_counter)
                for mode in ("sync", "event") if payload == "decision" else ("sync",):
                    use = layout_bus_use(layout, p_change=p_change if mode == "event" else None, **rates)
                    if mode == "sync":
                        seconds[label[per_node], payload, fd] = (use.mean_cycle_s,
                                                                 sum(c.worst_cycle_s for c in use.channels))
                    busiest = use.busiest
                    rows.append({
                        "layout": label[per_node], "taxels_per_node": per_node, "payload": payload,
                        "bus": "FD" if fd else "classic", "mode": mode, "tag_bytes": tag,
                        "channels": len(layout.channels), "nodes": layout.n_nodes,
                        "pdo_frames_per_cycle": sum(c.bits.expected_frames for c in use.channels),
                        "bits_per_cycle": use.mean_bits, "bits_per_cycle_worst": use.worst_bits,
                        "busiest_channel": busiest.bits.channel,
                        "bus_load": busiest.load, "bus_load_worst": max(c.worst_load for c in use.channels),
                        "max_sync_hz": use.max_sync_hz, "latency_ms": 1000.0 * use.latency_s,
                        "per_channel": [{
                            "channel": c.bits.channel, "nodes": c.bits.nodes, "taxels": c.bits.taxels,
                            "pdo_frames": c.bits.frames, "bits_per_cycle": c.bits.mean_bits,
                            "bits_per_cycle_worst": c.bits.worst_bits, "bus_load": c.load,
                            "bus_load_worst": c.worst_load, "max_sync_hz": c.max_sync_hz,
                            "latency_ms": 1000.0 * c.latency_s} for c in use.channels],
                    })
    ratios = {}
    for name in dict.fromkeys(label[k] for k in (1, patch)):
        for fd in (False, True):
            r, d = seconds[name, raw, fd], seconds[name, "decision", fd]
            ratios[f"{name} {'FD' if fd else 'classic'}"] = {"mean": r[0] / d[0], "worst": r[1] / d[1]}
    return {
        "taxels": n_taxels, "nominal_bitrate": int(nominal_bitrate), "data_bitrate": int(data_bitrate),
        "sync_period_ms": sync_period_ms, "heartbeat_ms": heartbeat_ms, "sync_counter": sync_counter,
        "patch": patch, "raw": raw, "p_change": p_change, "p_one": p_one, "channels_asked": channels,
        "rows": rows, "raw_over_decision": ratios,
    }
