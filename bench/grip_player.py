"""A grasp scene's taxel nodes at hardware speed, its gripper drive a twin (bench/grip_latency.py's
``player`` transport).

    .venv/bin/python bench/grip_player.py --scene S --group G --port P --frames FILE

The node twins (node_sim) answer a SYNC after their Python has run - the world's sample, the
detectors, the packing, the sends - on the same two cores as the centre: 0.9-1.4 ms p50, 2.6-3.0
ms p99 on a quiet host for the patch grasp scenes (docs/grip-control.md), where CAN nodes answer
within their TPDO's transmission time. This process stands in for such nodes, the way
bench/patch_player.py does for scenes/skin4096.toml, on the scene's one udp_multicast channel:

* **the taxel nodes** (``taxel_net.patches.devices``: one patch node a pad, or the one-taxel
  nodes): NMT reset (node or broadcast) -> their boot-up, NMT start / stop / pre-operational ->
  their heartbeat state, the heartbeats at the scene's producer time, every SDO expedited
  download answered with its confirmation (so the centre configures them as it configures the
  twins: ``FusionService.boot`` unchanged), any other SDO request with an abort; and **each SYNC
  answered at once with that cycle's recorded TPDOs** (``--frames``: the taxel TPDOs of a demo
  run of the same scene, :func:`record_answers`; a tagged patch TPDO's first byte replaced with
  the SYNC's counter) - python-can datagrams written straight on the socket
  (:func:`taxel_net.udp_wire.udp_multicast_burst_sender`), from a receive thread that the
  kernel wakes for NMT, SYNC and these nodes' SDO requests only (its bus filters). Cycles count
  from 0 at the NMT reset of all nodes, as the twins' world does; past the recording, the
  recording again from its start.
* **the gripper drive**: the scene's twin (:class:`node_sim.gripper.host.DriveHost`, the same
  class ``node-sim`` runs, on a bus object of its own): the centre boots it over SDO, runs its
  CiA 402 state machine to OPERATION ENABLED and commands it every cycle as in ``run``. Without
  the grasp world (``--world`` adds it: :class:`node_sim.world_runner.WorldRunner` on the
  drive, its own clock, but its readings reach no taxel here): the jaws meet no object, the
  drive's torque actual follows the command as its actuator model makes it.

So the centre's records are a real function of the recorded answers (presence, slip, the law's
states from grasp to release, as in the demo) and of the drive's state: a real command each
cycle, not a reaction of the pads to the grip (the recorded taxels do not feel the jaws here).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path

import can

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from taxel_net import patches  # noqa: E402
from taxel_net.canmsg import tune_udp_multicast  # noqa: E402
from taxel_net.receiver import notifiers_for  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402
from taxel_net.udp_filter import set_filters  # noqa: E402
from taxel_net.udp_wire import udp_multicast_burst_sender  # noqa: E402

COB_SYNC = 0x080
PRE_OPERATIONAL, OPERATIONAL, STOPPED = 0x7F, 0x05, 0x04
NMT_STATE = {0x01: OPERATIONAL, 0x02: STOPPED, 0x80: PRE_OPERATIONAL, 0x81: PRE_OPERATIONAL, 0x82: PRE_OPERATIONAL}
SDO_ABORT_COMMAND = 0x05040001  # CiA 301: client/server command specifier not valid or unknown


def _taxel_tpdos(scene) -> dict[int, patches.Tpdo]:
    """COB-ID -> the taxel TPDO that uses it (the drive's frames are not the player's)."""
    out = {}
    for device in patches.devices(scene):
        for tpdo in device.tpdos:
            if tpdo.encoding == patches.ENC_TAGGED:
                raise SystemExit(f"{scene.path}: one-taxel nodes with a cycle tag in the decision byte: not played")
            out[tpdo.cob_id] = tpdo
    return out


def record_answers(scene, frames: list[can.Message]) -> list[list[tuple[int, str]]]:
    """Per cycle k (the k-th SYNC of ``frames``, a bus observer's frames of a demo run in order),
    the taxel TPDOs between SYNC k and SYNC k + 1: ``(cob_id, data hex)``, as sent."""
    tpdos = _taxel_tpdos(scene)
    cycles: list[list[tuple[int, str]]] = []
    for msg in frames:
        if msg.arbitration_id == COB_SYNC:
            cycles.append([])
        elif cycles and msg.arbitration_id in tpdos:
            cycles[-1].append((msg.arbitration_id, bytes(msg.data).hex()))
    return cycles


class TaxelNodes(can.Listener):
    """The scene's taxel nodes on one bus (module docstring): NMT, SDO, SYNC -> recorded TPDOs."""

    def __init__(self, scene, cycles: list[list[tuple[int, str]]], send_many):
        tpdos = _taxel_tpdos(scene)
        self.node_ids = sorted({d.node_id for d in patches.devices(scene)})
        self.node_set = frozenset(self.node_ids)
        self.send_many = send_many
        self.state = {n: PRE_OPERATIONAL for n in self.node_ids}
        # per cycle: the burst as send_many takes it; a tagged TPDO's tag byte is the SYNC's
        self.cycles = [[(cob, bytes.fromhex(data), tpdos[cob].fd, tpdos[cob].tagged) for cob, data in cycle]
                       for cycle in cycles]
        self.tagged = any(t.tagged for t in tpdos.values())
        self.cycle = 0
        self.lock = threading.Lock()
        self.bursts = [[(cob, data, True) if fd else (cob, data) for cob, data, fd, _ in c] for c in self.cycles]

    def filters(self) -> list[dict]:
        ids = [0x000, COB_SYNC] + [0x600 + n for n in self.node_ids]
        return [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids]

    def on_message_received(self, msg: can.Message) -> None:
        can_id, data = msg.arbitration_id, bytes(msg.data)
        if can_id == COB_SYNC:
            with self.lock:
                cycle = self.cycle
                self.cycle += 1
                live = all(s == OPERATIONAL for s in self.state.values())
            if live and self.cycles:
                k = cycle % len(self.cycles)
                burst = self.bursts[k]
                if self.tagged and data:  # the SYNC's counter as the cycle tag
                    burst = [(cob, data[:1] + body[1:], *frame[2:]) if tagged else frame
                             for frame, (cob, body, _, tagged) in zip(burst, self.cycles[k])]
                self.send_many(burst)
        elif can_id == 0x000 and len(data) == 2 and data[0] in NMT_STATE:
            targets = [n for n in self.node_ids if data[1] in (0, n)]
            with self.lock:
                for node_id in targets:
                    self.state[node_id] = NMT_STATE[data[0]]
                if data[1] == 0 and data[0] in (0x81, 0x82):
                    self.cycle = 0  # the recording starts with the master's cycle 0, as the twins' world
            if data[0] in (0x81, 0x82):
                self.send_many([(0x700 + n, b"\x00") for n in targets])  # boot-up
        elif 0x601 <= can_id <= 0x67F and len(data) == 8 and can_id - 0x600 in self.node_set:
            node_id = can_id - 0x600  # (the drive's SDO is its twin's: never answered here)
            if data[0] & 0xE0 == 0x20:  # initiate download: accepted (expedited: the value is in the request)
                answer = b"\x60" + data[1:4] + b"\x00\x00\x00\x00"
            else:
                answer = b"\x80" + data[1:4] + SDO_ABORT_COMMAND.to_bytes(4, "little")
            self.send_many([(0x580 + node_id, answer)])

    def heartbeats(self) -> None:
        with self.lock:
            frames = [(0x700 + n, bytes((s,))) for n, s in self.state.items()]
        self.send_many(frames)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, type=Path)
    ap.add_argument("--group", required=True, help="the udp_multicast group of the scene's one channel")
    ap.add_argument("--port", required=True, type=int)
    ap.add_argument("--frames", type=Path, help="JSON: record_answers' per-cycle TPDOs (the taxel nodes')")
    ap.add_argument("--part", choices=("all", "nodes", "drive"), default="all",
                    help="the taxel nodes, the drive or both in this process (module docstring)")
    ap.add_argument("--world", action="store_true", help="run the grasp world on the drive (module docstring)")
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    if len(scene.bus.channels) != 1 or scene.gripper is None:
        ap.error(f"--scene {args.scene}: one channel and a [gripper] table needed")
    from node_sim.gripper.host import DriveHost

    kwargs = {"port": args.port, "hop_limit": 0, "fd": scene.bus.fd}
    bus = drive = world = nodes = None
    if args.part in ("nodes", "all"):
        if args.frames is None:
            ap.error("--frames: needed for the taxel nodes")
        cycles = json.loads(args.frames.read_text())
        bus = can.Bus(interface="udp_multicast", channel=args.group, **kwargs)
        tune_udp_multicast(bus)
        send_many = udp_multicast_burst_sender(bus)
        if send_many is None:
            raise SystemExit("grip_player: not a python-can 4.x udp_multicast bus")
        nodes = TaxelNodes(scene, cycles, send_many)
        set_filters(bus, nodes.filters())
    if args.part in ("drive", "all"):
        drive = DriveHost.for_scene(scene, "udp_multicast", args.group, kwargs).start()
        if args.world:
            from node_sim.world_runner import WorldRunner

            world = WorldRunner(scene, drive.drive, drive.lock, sync_state=lambda: (None, drive.cycle)).start()
    handles = notifiers_for([(bus, [nodes])], name="player-receive") if nodes is not None else []
    signal.signal(signal.SIGTERM, _interrupt)  # the bench's terminate(): shut down as at Ctrl-C
    print("ready", flush=True)
    period = scene.bus.heartbeat_producer_ms / 1000.0
    try:
        while True:
            time.sleep(period)
            if nodes is not None:
                nodes.heartbeats()
    except KeyboardInterrupt:
        pass
    finally:
        for handle in handles[:1]:
            handle.stop()
        if world is not None:
            world.stop()
        if drive is not None:
            drive.stop()
        if bus is not None:
            bus.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
