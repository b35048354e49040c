"""bench/grip_latency.py's floors: what the cycle takes on a real CAN bus (the wire floor) and one
thread's wake-up on this host (the echo floor). See that module's docstring."""

from __future__ import annotations

import random
import struct
import subprocess
import sys
import threading
import time
import uuid

import can

COB_SYNC = 0x080


def scene_for(name: str):
    from taxel_net.resources import resolve_scene
    from taxel_net.scene import load_scene

    return load_scene(resolve_scene(name))


def _patch_free_mask(tpdo) -> int:
    """The data bits of a patch TPDO that carry taxel values (``pdo_frames``' mask: bit 8n-1 =
    byte 0's most significant bit); the tag byte and the padding are not free."""
    from taxel_net import patches as P

    n = tpdo.length
    first = int(tpdo.tagged)
    mask = 0
    for j in range(first, first + tpdo.payload_bytes):
        bits = 0xFF
        if tpdo.encoding == P.ENC_BITS and j == first + tpdo.payload_bytes - 1 and tpdo.count % 8:
            bits = (1 << (tpdo.count % 8)) - 1      # the last byte's low bits (bit k % 8 = taxel k)
        mask |= bits << (8 * (n - 1 - j))
    return mask


def wire_floor_ms(name: str) -> tuple[float, float, int]:
    """(SYNC + the answers, + the command) in ms on a real bus at the scene's bit rates, and the
    number of answer frames (module docstring). One-taxel nodes: their TPDO1 of 1 byte (decision)
    or TPDO2 of 4 (raw) with exact stuff bits for a representative value; patch nodes
    (``[bus] patch_nodes``): each TPDO of ``taxel_net.patches.devices``, the mean over its
    payloads with every value bit 1 with probability 1/2 (``fusion_center.core.pdo_frames``),
    CAN FD frames with the data phase at ``[bus] data_bitrate``."""
    from fusion_center.core.bus_timing import frame_bits
    from fusion_center.core.pdo_frames import pdo_frame_stats
    from taxel_net import patches as P

    scene = scene_for(name)
    bus = scene.bus
    nominal = bus.bitrate / 1e3  # bits per ms
    data_rate = (bus.data_bitrate if bus.fd else bus.bitrate) / 1e3
    sync = frame_bits(COB_SYNC, b"" if not bus.sync_counter else b"\x01") / nominal
    answers, frames = 0.0, 0
    if bus.patch_nodes:
        tags = tuple(range(1, bus.sync_counter + 1)) if bus.sync_counter else ()
        for device in P.devices(scene):
            for tpdo in device.tpdos:
                stats = pdo_frame_stats(tpdo.cob_id, tpdo.length, _patch_free_mask(tpdo), 0.5, fd=tpdo.fd,
                                        tag_values=tags if tpdo.tagged else ())
                answers += stats.mean_nominal / nominal + stats.mean_data / data_rate
                frames += 1
    else:
        raw = bus.mode == "raw"
        answers = sum(frame_bits((0x280 if raw else 0x180) + t.node_id,
                                 struct.pack("<f", 100.0) if raw else b"\x01") for t in scene.taxels) / nominal
        frames = scene.n
    command = frame_bits(0x200 + scene.gripper.node_id, struct.pack("<Hhi", 0x0F, 100, 0)) / nominal
    return sync + answers, sync + answers + command, frames


def wire_floor(name: str) -> str:
    """The cycle's frames on a real bus at the scene's bit rate (module docstring), as a line."""
    from taxel_net.patches import devices

    scene = scene_for(name)
    answers, total, frames = wire_floor_ms(name)
    rates = f"{scene.bus.bitrate / 1e6:g}" + (f"/{scene.bus.data_bitrate / 1e6:g} (FD)" if scene.bus.fd else "")
    layout = f"{len(devices(scene))} patch nodes, " if scene.bus.patch_nodes else ""
    return (f"wire floor at {rates} Mbit/s: SYNC + {frames} answers ({layout}{scene.n} taxels) "
            f"{answers:.2f} ms, + the command {total:.2f} ms")


# --------------------------------------------------------------------------- the echo floor
def echo_virtual(n: int) -> list[float]:
    """send (the frame's stamp) -> a receive thread blocked in ``recv`` has it, ms."""
    channel = f"echo-{uuid.uuid4().hex[:8]}"
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel)
    out: list[float] = []
    done = threading.Event()

    def receive():
        while len(out) < n:
            msg = rx.recv(1.0)
            if msg is None:
                break
            out.append((time.time() - msg.timestamp) * 1e3)
        done.set()

    thread = threading.Thread(target=receive, daemon=True)
    thread.start()
    for _ in range(n):
        tx.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        time.sleep(0.002)  # the receiver is asleep again before the next one, as in a 10 ms cycle
    done.wait(10)
    tx.shutdown()
    rx.shutdown()
    return out


def echo_udp(n: int) -> list[float]:
    """Another process sends a frame every 2 ms over udp_multicast; this one blocks in ``recv``:
    the kernel's receive stamp -> this thread has it, and the sender's send -> the kernel stamp."""
    group = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    port = random.randint(40000, 60000)
    rx = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=0)
    code = ("import can, time, sys\n"
            f"b = can.Bus(interface='udp_multicast', channel='{group}', port={port}, hop_limit=0)\n"
            "print('ready', flush=True); time.sleep(0.5)\n"
            f"for i in range({n}):\n"
            "    b.send(can.Message(arbitration_id=0x81, data=[1], is_extended_id=False)); time.sleep(0.002)\n"
            "b.shutdown()\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    proc.stdout.readline()
    out = []
    try:
        while len(out) < n:
            msg = rx.recv(2.0)
            if msg is None:
                break
            if msg.arbitration_id == 0x81:
                out.append((time.time() - msg.timestamp) * 1e3)
    finally:
        proc.wait(30)
        rx.shutdown()
    return out


