"""Patch node twins (node_sim.patch, issue 14) on a virtual bus: their TPDOs equal
taxel_net.patches.pack of the detector decisions / readings_to_counts of the readings computed
here from node_sim.physics.sample_readings (not through the twin's code), classic and CAN FD,
tagged and untagged; faults, silent nodes, FD one-taxel nodes."""

from __future__ import annotations

import dataclasses
import itertools
import time
from pathlib import Path

import can
import numpy as np
import pytest

from node_sim import physics
from node_sim.rig import Rig
from taxel_net import patches as P
from taxel_net.scene import load_scene

_names = itertools.count()

HEAD = """
[scene]
name = "patchtest"
seed = 11
cycles = 10
[bus]
bitrate = 1000000
sync_period_ms = 10.0
sync_counter = {sync_counter}
heartbeat_producer_ms = 0
mode = "{mode}"
transmission_type = 1
channels = ["a", "b"]
{extra}
[kinds.C]
zeta_mv = 2.5
noise_mv = 0.3
noise_sigma_mv = 0.8
signal_mv = 4.6
[object]
model = "slipping"
x = 10.0
y = 10.0
radius = 8.0
present = [[0, 10]]
velocity = [0.5, 0.0]
slip_onset_cycle = 3
[fusion]
tuple = "pm1"
"""


def write_scene(tmp_path, sizes=((0, 1, 10), (1, 3, 70)), mode="decision", sync_counter=16, fd=False,
                raw_format="int16", patch=True, extra=""):
    lines = []
    if patch:
        extra += "\npatch_nodes = true"
        if mode == "raw":
            extra += f"\nraw_format = '{raw_format}'\nraw_lsb_mv = 0.05"
    if fd:
        extra += "\nfd = true\ndata_bitrate = 5000000"
    text = HEAD.format(sync_counter=sync_counter, mode=mode, extra=extra)
    k = 0
    for channel, node, n in sizes:
        for j in range(n):
            nid = node if patch else node + j
            lines.append(f"[[taxels]]\nnode_id = {nid}\nchannel = {channel}\nkind = 'C'\n"
                         f"x = {2.5 * (k % 10)}\ny = {2.5 * (k // 10)}\n")
            k += 1
    p = tmp_path / f"s{next(_names)}.toml"
    p.write_text(text + "".join(lines))
    return load_scene(p)


class Master:
    """A bus object per channel of the rig (the master side)."""

    def __init__(self, names):
        self.buses = [can.Bus(interface="virtual", channel=n) for n in names]

    def send_all(self, can_id, data):
        for b in self.buses:
            b.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def drain(self):
        out = []
        for i, b in enumerate(self.buses):
            while (m := b.recv(0)) is not None:
                out.append((i, m))
        return out

    def close(self):
        for b in self.buses:
            b.shutdown()


@pytest.fixture
def rig_of():
    made = []

    def make(scene, **kw):
        # no synchronous window (0x1007 = 0): a SYNC handled late on a loaded CI host still answers
        scene = dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, sync_window_us=0))
        names = [f"patch{next(_names)}-{c}" for c in scene.bus.channels]
        rig = Rig(scene, channel=names, **kw).start()
        master = Master(names)
        made.append((rig, master))
        deadline = time.monotonic() + 5
        while any(n.state != 0x7F for n in rig.nodes.values()) and time.monotonic() < deadline:
            time.sleep(0.01)
        master.send_all(0x000, bytes([0x01, 0]))
        while any(n.state != 0x05 for n in rig.nodes.values()) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
        master.drain()
        return rig, master, scene

    yield make
    for rig, master in made:
        rig.stop()
        master.close()


def sync(rig, master, cycle, counter, channels):
    master.send_all(0x080, bytes([counter]) if counter is not None else b"")
    for ch in range(channels):
        assert rig.wait_cycle(cycle, ch, timeout=5)
    time.sleep(0.05)
    return master.drain()


def expected_frames(scene, cycle, counter):
    """(channel, COB-ID) -> data, from the physics and the shared layout only."""
    x = physics.sample_readings(scene, cycle)
    # the node stores ζ and N_i as REAL32 (its OD): the same rounding here
    zeta = np.array([np.float32(t.zeta_mv) for t in scene.taxels], dtype=np.float64)
    noise = np.array([np.float32(t.noise_mv) for t in scene.taxels], dtype=np.float64)
    u = np.where((x - noise) >= zeta, 1, -1)
    out = {}
    for dev in P.devices(scene):
        idx = np.asarray(dev.taxels)
        for t in dev.tpdos:
            sel = idx[t.first: t.first + t.count]
            tag = counter if t.tagged else None
            if t.encoding == P.ENC_BITS:
                data = P.pack(t, u[sel], tag)
            else:
                counts, _ = P.readings_to_counts(t, x[sel], scene.bus.raw_lsb_mv)
                data = P.pack(t, counts, tag)
            out[(dev.channel, t.cob_id)] = (data, t.fd)
    return out


@pytest.mark.parametrize("mode, raw_format, sync_counter, fd", [
    ("decision", "int16", 16, False),
    ("decision", "int16", 0, True),
    ("decision", "int16", 16, True),
    ("raw", "int8", 16, False),
    ("raw", "int16", 16, True),
    ("raw", "int16", 0, False),
])
def test_patch_frames_equal_the_shared_packing(tmp_path, rig_of, mode, raw_format, sync_counter, fd):
    scene = write_scene(tmp_path, mode=mode, raw_format=raw_format, sync_counter=sync_counter, fd=fd)
    rig, master, scene = rig_of(scene)
    seen_present = 0
    for cycle in range(4):
        counter = cycle + 1 if sync_counter else None
        frames = sync(rig, master, cycle, counter, 2)
        got = {(ch, m.arbitration_id): (bytes(m.data), m.is_fd) for ch, m in frames if 0x181 <= m.arbitration_id <= 0x57F}
        assert all(m.bitrate_switch == fd and m.is_fd == fd for _, m in frames if 0x181 <= m.arbitration_id <= 0x57F)
        assert got == expected_frames(scene, cycle, counter), ([ch.late_syncs for ch in rig._channels], cycle)
        seen_present += sum(n.decision.tolist().count(1) for n in rig.nodes.values())
    assert seen_present > 0            # the contact shows: not all-absent frames
    if mode == "decision" and not fd and sync_counter:
        # 10 taxels: one 3-byte TPDO; 70 taxels: 56 + 14 -> 8 + 3 bytes
        lengths = sorted((d.channel, [t.length for t in d.tpdos]) for d in P.devices(scene))
        assert lengths == [(0, [3]), (1, [8, 3])]


def test_open_circuit_taxel_decides_absent_with_emcy_and_fault_bits(tmp_path, rig_of):
    scene = write_scene(tmp_path, sizes=((0, 1, 10), (1, 3, 12)))

    def source(cycle):
        x = physics.sample_readings(scene, cycle)
        x[:] = 10.0                                   # every taxel present...
        if cycle >= 1:
            x[3] = np.nan                             # ...but taxel 3 opens at cycle 1
        x[10 + (cycle % 2)] += 0.25                   # (no stuck reading on channel 1)
        x[12 + cycle % 5] += 0.5
        return x

    rig, master, scene = rig_of(scene, reading_source=source)
    node = rig.node(1, 0)
    frames = sync(rig, master, 0, 1, 2)
    assert [bytes(m.data) for ch, m in frames if ch == 0 and m.arbitration_id == 0x181] == [bytes([1, 0xFF, 0x03])]
    frames = sync(rig, master, 1, 2, 2)
    emcy = [bytes(m.data) for ch, m in frames if ch == 0 and m.arbitration_id == 0x81]
    assert len(emcy) == 1 and emcy[0][:3] == bytes([0x00, 0x50, 0x21])    # 0x5000, error register
    assert [bytes(m.data) for ch, m in frames if ch == 0 and m.arbitration_id == 0x181] == [bytes([2, 0xF7, 0x03])]
    assert node.faulted.tolist() == [i == 3 for i in range(10)]
    assert node.read(0x2022, 1) == 0x08 and node.read(0x1001) != 0


def test_silent_node_sends_nothing(tmp_path, rig_of):
    scene = write_scene(tmp_path)
    rig, master, scene = rig_of(scene)
    rig.drop_node(3, channel=1)
    frames = sync(rig, master, 0, 1, 2)
    assert {(ch, m.arbitration_id) for ch, m in frames} == {(0, 0x181)}
    rig.restore_node(3, channel=1)
    frames = sync(rig, master, 1, 2, 2)
    assert {(ch, m.arbitration_id) for ch, m in frames} == {(0, 0x181), (1, 0x181), (1, 0x182)}


def test_one_taxel_nodes_of_an_fd_scene_send_fd_tpdos(tmp_path, rig_of):
    scene = write_scene(tmp_path, sizes=((0, 1, 3), (1, 1, 2)), patch=False, fd=True)
    rig, master, scene = rig_of(scene)
    frames = sync(rig, master, 0, 1, 2)
    tpdos = [m for _, m in frames if 0x181 <= m.arbitration_id <= 0x1FF]
    assert len(tpdos) == 5 and all(m.is_fd and m.bitrate_switch and m.dlc == 1 for m in tpdos)
    assert len(frames) == 5


@pytest.mark.parametrize("name, frames, fd", [("skin4096", 88, False), ("skin4096_fd", 24, True)])
def test_skin4096_rig_answers_a_sync(rig_of, name, frames, fd):
    scene = load_scene(f"scenes/{name}.toml")
    rig, master, scene = rig_of(scene)
    assert len(rig.nodes) == 24
    got = sync(rig, master, 0, 1, 8)
    tpdos = [(ch, m) for ch, m in got if 0x181 <= m.arbitration_id <= 0x57F]
    assert len(tpdos) == frames and all(m.is_fd == fd for _, m in tpdos)
    assert {(ch, m.arbitration_id): (bytes(m.data), m.is_fd) for ch, m in tpdos} == expected_frames(scene, 0, 1)


@pytest.mark.parametrize("name", ["skin4096", "skin4096_fd"])
def test_patch_player_sends_what_the_twins_send(name):
    """bench/patch_player.py (the patch nodes at hardware speed, for measuring the centre alone)
    answers a SYNC with the frames the twins send for that cycle: the same COB-IDs, data and
    frame format, the SYNC counter as the tag (reference: the physics and the shared layout)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
    from patch_player import cycle_frames

    scene = load_scene(f"scenes/{name}.toml")
    frames = cycle_frames(scene, 121)
    for cycle, counter in ((0, 1), (40, 41), (120, 57)):   # before, under and after the contact
        got = {(ch, cob): (bytes((counter,)) + body, fd) for ch, per_cycle in enumerate(frames)
               for cob, body, fd in per_cycle[cycle]}
        assert got == expected_frames(scene, cycle, counter)
