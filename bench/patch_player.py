"""Patch nodes at hardware speed, for measuring the centre alone (bench/skin_scale.py --twins player).

    .venv/bin/python bench/patch_player.py --scene scenes/skin4096.toml --groups G0,G1,... --port P
                                           [--cycles N]

The node twins (node_sim) are the project's CANopen slaves; on a 2-core host that also runs the
centre they need ~7 ms to answer a SYNC of 4,096 taxels (bench/twin_response.py), where patch
microcontrollers answer as soon as the bus lets them. This player stands in for that hardware
on udp_multicast: for every scene device (patch node) it answers NMT reset communication with
its boot-up, NMT start/stop/pre-operational with its heartbeat state, sends the heartbeats at
the scene's producer time, and answers each SYNC on a channel, at once, with that channel's
TPDOs of the cycle - the decisions of eqs 1-4 on node_sim.physics' readings of the cycle (what
the twins decide, computed ahead for ``--cycles`` cycles), the SYNC counter as the cycle tag -
as python-can datagrams straight on the socket (taxel_net.udp_wire). It has no object
dictionary and no SDO server: the centre is booted without configuration (``boot(configure=False)``,
the scene's defaults being what the player sends). Decision-mode scenes of patch nodes with a
cycle tag only. Cycles count from 0 at the NMT reset of all nodes, as the twins' world does.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from fusion_center.core.encoding import local_decision  # noqa: E402
from node_sim import physics  # noqa: E402
from taxel_net import patches  # noqa: E402
from taxel_net.canmsg import tune_udp_multicast  # noqa: E402
from taxel_net.receiver import notifiers_for  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402
from taxel_net.udp_filter import set_filters  # noqa: E402
from taxel_net.udp_wire import udp_multicast_burst_sender  # noqa: E402

PRE_OPERATIONAL, OPERATIONAL, STOPPED = 0x7F, 0x05, 0x04
NMT_STATE = {0x01: OPERATIONAL, 0x02: STOPPED, 0x80: PRE_OPERATIONAL, 0x81: PRE_OPERATIONAL, 0x82: PRE_OPERATIONAL}


def cycle_frames(scene, cycles: int) -> list[list[list[tuple[int, bytes, bool]]]]:
    """frames[channel][cycle]: ``(cob_id, data after the tag byte, fd)`` of every TPDO."""
    devices = patches.devices(scene)
    if scene.bus.mode != "decision" or not all(t.tagged and t.encoding == patches.ENC_BITS
                                               for d in devices for t in d.tpdos):
        raise SystemExit(f"{scene.path}: the player sends tagged packed decisions only (patch nodes, decision "
                         "mode, a SYNC counter)")
    # the nodes hold zeta and N_i as REAL32 (their object dictionary): the same rounding here
    zeta = np.array([t.zeta_mv for t in scene.taxels], dtype=np.float32).astype(np.float64)
    noise = np.array([t.noise_mv for t in scene.taxels], dtype=np.float32).astype(np.float64)
    readings = physics.sample_readings_batch(scene, np.arange(cycles))
    out = [[[] for _ in range(cycles)] for _ in scene.bus.channels]
    for c in range(cycles):
        present = local_decision(readings[c], noise, zeta, "pm1") == 1
        for d in devices:
            members = present[list(d.taxels)]
            for t in d.tpdos:
                data = patches.pack(t, members[t.first:t.first + t.count], tag=0)
                out[d.channel][c].append((t.cob_id, data[1:], t.fd))
    return out


class ChannelPlayer(can.Listener):
    """One channel's devices: NMT, SYNC -> the cycle's TPDOs, heartbeat state."""

    def __init__(self, bus: can.BusABC, devices, frames, send_many):
        self.bus, self.devices, self.frames, self.send_many = bus, devices, frames, send_many
        self.state = {d.node_id: PRE_OPERATIONAL for d in devices}
        self.cycle = 0
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        can_id, data = msg.arbitration_id, bytes(msg.data)
        if can_id == 0x080 and data:
            with self.lock:
                cycle = self.cycle
                self.cycle += 1
                live = all(s == OPERATIONAL for s in self.state.values())
            if live and cycle < len(self.frames):
                tag = data[:1]
                self.send_many([(cob, tag + body, True) if fd else (cob, tag + body)
                                for cob, body, fd in self.frames[cycle]])
        elif can_id == 0x000 and len(data) == 2 and data[0] in NMT_STATE:
            targets = [d.node_id for d in self.devices if data[1] in (0, d.node_id)]
            with self.lock:
                for node_id in targets:
                    self.state[node_id] = NMT_STATE[data[0]]
                if data[1] == 0 and data[0] in (0x81, 0x82):
                    self.cycle = 0  # the world restarts with the master's cycle 0, as the twins'
            if data[0] in (0x81, 0x82):
                self.send_many([(0x700 + node_id, b"\x00") for node_id in targets])  # boot-up

    def heartbeats(self) -> None:
        with self.lock:
            frames = [(0x700 + node_id, bytes((state,))) for node_id, state in self.state.items()]
        self.send_many(frames)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, type=Path)
    ap.add_argument("--groups", required=True, help="udp_multicast groups, one per scene channel, comma-separated")
    ap.add_argument("--port", required=True, type=int)
    ap.add_argument("--cycles", type=int, default=1000, help="cycles computed ahead (later SYNCs get no TPDO)")
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    groups = args.groups.split(",")
    if len(groups) != len(scene.bus.channels):
        ap.error(f"--groups: {len(groups)} given, the scene has {len(scene.bus.channels)} channels")
    frames = cycle_frames(scene, args.cycles)
    devices = patches.devices(scene)
    buses = [can.Bus(interface="udp_multicast", channel=g, port=args.port, hop_limit=0, fd=scene.bus.fd)
             for g in groups]
    players = []
    for k, bus in enumerate(buses):
        tune_udp_multicast(bus)
        # NMT and SYNC only, dropped in the kernel (the centre's other frames and the group's
        # looped-back TPDOs never wake the player: it stands in for hardware, beside the centre)
        set_filters(bus, [{"can_id": 0x000, "can_mask": 0x7FF, "extended": False},
                          {"can_id": 0x080, "can_mask": 0x7FF, "extended": False}])
        players.append(ChannelPlayer(bus, [d for d in devices if d.channel == k], frames[k],
                                     udp_multicast_burst_sender(bus)))
    handles = notifiers_for([(bus, [p]) for bus, p in zip(buses, players)], name="player-receive")
    print("ready", flush=True)
    period = scene.bus.heartbeat_producer_ms / 1000.0
    try:
        while True:
            time.sleep(period)
            for p in players:
                p.heartbeats()
    except KeyboardInterrupt:
        pass
    finally:
        handles[0].stop()
        for bus in buses:
            bus.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
