"""The channel-level batch of patch-node detectors (node_sim.patch_batch.PatchSyncBatch) against the
per-node reference: the same frames, byte for byte and in the same order, the same EMCYs and
the same process images.

Two rigs run one script of SYNCs, NMT commands, SDO writes and silences on readings with NaN,
+-inf, values beyond full scale and beyond REAL32, stuck taxels (repeated REAL32 patterns) and
patches of 1, 5, 7, 9, 13 and 192 taxels (channel 1's two nodes interleaved: index arrays).
The reference rig samples node by node through each SyncConsumer with :func:`reference_sample`
(the detector as it was before the batch, kept here) and the general TPDO engine loop
(``TpdoEngine.on_sync``); the candidate rig is the default (batched, the every-SYNC TPDO
path), or node by node with the production ``PatchDetector.sample``.
"""

from __future__ import annotations

import dataclasses
import itertools
import struct
import types

import can
import numpy as np
import pytest

from node_sim import patch as patchx
from node_sim import patch_batch
from node_sim.pdo import TpdoEngine
from node_sim.rig import Rig
from taxel_net import patches as P
from taxel_net.scene import load_scene

_names = itertools.count()

HEAD = """
[scene]
name = "batchtest"
seed = 3
cycles = 40
[bus]
bitrate = 1000000
sync_period_ms = 10.0
sync_counter = 16
heartbeat_producer_ms = 0
mode = "{mode}"
transmission_type = {tt}
channels = ["a", "b"]
patch_nodes = true
{extra}
[kinds.C]
zeta_mv = 2.5
noise_mv = 0.3
noise_sigma_mv = 0.8
signal_mv = 4.6
[kinds.R]
zeta_mv = 1.5
noise_mv = 0.0
noise_sigma_mv = 0.0
signal_mv = 4.0
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

# (channel, node-ID, taxels, kind); channel 1's nodes take turns taxel by taxel (not a slice)
NODES = ((0, 1, 1, "C"), (0, 2, 7, "C"), (0, 3, 13, "R"), (0, 4, 192, "C"), (1, 1, 9, "C"), (1, 2, 5, "R"))
HIGH = 1 + 7 + 13 + 100          # taxel 101 of node 4 on channel 0: reads 10 mV, present
STUCK = (0, 3, 9, 25, 60, 220)   # scene indices whose readings repeat their REAL32 pattern
N_CYCLES = 40


def write_scene(tmp_path, mode="decision", tt=1, fd=False):
    extra = "raw_format = 'int8'\nraw_lsb_mv = 0.05" if mode == "raw" else ""
    if fd:
        extra += "\nfd = true\ndata_bitrate = 5000000"
    lines = []
    k = 0

    def taxel(channel, node, kind):
        nonlocal k
        lines.append(f"[[taxels]]\nnode_id = {node}\nchannel = {channel}\nkind = '{kind}'\n"
                     f"x = {2.5 * (k % 10)}\ny = {2.5 * (k // 10)}\n")
        k += 1

    for channel, node, n, kind in NODES[:4]:
        for _ in range(n):
            taxel(channel, node, kind)
    (_, a, na, ka), (_, b, nb, kb) = NODES[4:]
    for j in range(max(na, nb)):
        if j < na:
            taxel(1, a, ka)
        if j < nb:
            taxel(1, b, kb)
    p = tmp_path / f"batch{next(_names)}.toml"
    p.write_text(HEAD.format(mode=mode, tt=tt, extra=extra) + "".join(lines))
    scene = load_scene(p)
    return dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, sync_window_us=0))


def readings(n: int, cycle: int) -> np.ndarray:
    """X (mV) of ``cycle``: noise about the thresholds, faults of every kind at known cycles."""
    x = np.random.default_rng([7, cycle]).normal(2.0, 2.0, n)
    x[HIGH] = 10.0 + 1e-3 * cycle
    if 4 <= cycle < 30:
        # a new float64 each cycle, the same REAL32: the node's stuck check sees one pattern
        x[list(STUCK)] = 1.25 + 1e-12 * cycle
    if cycle % 7 == 3:
        x[[5, 40, 200]] = np.nan
    if cycle % 11 == 4:
        x[30], x[31] = np.inf, -np.inf
    if cycle in (9, 10, 22):
        x[50], x[51], x[52], x[222] = 3e38, 1500.0, -1000.0, 999.99   # |X| >= full scale (1000 mV)
    return x


def reference_sample(self, readings, counter=None):
    """PatchDetector.sample before the batch (eqs 1-4: u_i = +1 iff X_i - N_i >= zeta_i;
    open circuit, stuck), on the detector's own state."""
    zeta, noise, full_scale, stuck_after = self.config()
    x = np.asarray(readings, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        raw = x.astype("<f4").view("<u4").astype(np.int64)
    same = self._same.astype(np.int64)       # (a copy: the candidate shares read-only arrays)
    np.add(same, 1, out=same)
    same[raw != self._last_raw] = 1
    self._same = same
    self._last_raw = raw
    with np.errstate(invalid="ignore"):
        open_circuit = ~(np.abs(x) < full_scale)
        present = (x - noise) >= zeta
    faulted = open_circuit
    if stuck_after > 0:
        faulted = open_circuit | (same >= stuck_after)
    if faulted.any() or self.fault != patchx.FAULT_NONE:
        self._faults_changed(faulted, open_circuit, x)
        present &= ~faulted
    self._image.update(x, np.packbits(present, bitorder="little").tobytes(),
                       np.packbits(faulted, bitorder="little").tobytes(), counter or 0)


def reference_tpdos(self, counter):
    """The general TPDO engine loop (``TpdoEngine.on_sync``) after the patch node's over-range
    check of the mapped readings (its EMCY before the frames of the SYNC)."""
    if self._active is None:
        self._activate()
    if self._watch is not None:
        self._node.check_over_range(*self._watch)
    TpdoEngine.on_sync(self, counter)


def make_reference(rig):
    for ch in rig._channels:
        ch.batch_patch_sync = False
        ch._sync_map = None
        for node in ch.nodes.values():
            node.sync._sample = types.MethodType(reference_sample, node.detector)
            node.sync._tpdos_on_sync = types.MethodType(reference_tpdos, node.pdo)


def per_node(rig):
    for ch in rig._channels:
        ch.batch_patch_sync = False
        ch._sync_map = None


def sdo_download(node_id: int, index: int, sub: int, data: bytes) -> tuple[int, bytes]:
    command = 0x23 | (4 - len(data)) << 2
    return 0x600 + node_id, bytes([command]) + struct.pack("<HB", index, sub) + data.ljust(4, b"\0")


REAL32 = struct.Struct("<f").pack

# cycle -> what happens before that cycle's SYNC: a frame to a channel (channel, COB-ID, data), an
# SDO request handed to the node itself ("node-sdo", channel, COB-ID, data: the node's entry point,
# which leaves the channel's SYNC map and batch as they are) or a drop / restore (channel, node-ID)
SCRIPT = {
    0: [(c, 0x000, b"\x01\x00") for c in (0, 1)],                               # start all
    1: [(0, *sdo_download(2, 0x2002, 2, b"\x03\x00"))],                           # node 2: stuck after 3
    3: [("drop", 0, 3)],
    5: [(0, 0x000, b"\x80\x02"), (1, 0x000, b"\x80\x01")],                      # pre-operational
    6: [("restore", 0, 3)],
    7: [("node-sdo", 0, *sdo_download(4, P.PATCH_ZETA, HIGH - 21 + 1, REAL32(100.0)))],   # ζ of the 10 mV taxel
    8: [(0, 0x000, b"\x01\x02"), (1, 0x000, b"\x01\x01"), (0, 0x000, b"\x02\x04")],   # start; stop node 4
    11: [(0, 0x000, b"\x81\x03"), (1, 0x000, b"\x82\x02")],                     # reset node / communication
    12: [(0, *sdo_download(1, 0x2002, 1, REAL32(0.5)))],                          # node 1: full scale 0.5 mV
    13: [(c, 0x000, b"\x01\x00") for c in (0, 1)],
    17: [("node-sdo", 0, *sdo_download(4, P.PATCH_ZETA, HIGH - 21 + 1, REAL32(2.5))), ("drop", 1, 2)],
    20: [(0, 0x000, b"\x81\x00")],                                                # reset every node of channel 0
    21: [(0, 0x000, b"\x01\x00"), ("restore", 1, 2)],
    26: [("node-sdo", 1, *sdo_download(1, P.PATCH_NOISE, 4, REAL32(-3.0)))],
}


def run_script(rig, masters, script=SCRIPT, cycles=N_CYCLES):
    """Frames each step puts on the buses, per step: [(channel, COB-ID, data, FD)]."""
    out = []

    def drain():
        frames = []
        for c, bus in enumerate(masters):
            while (m := bus.recv(0)) is not None:
                frames.append((c, m.arbitration_id, bytes(m.data), m.is_fd))
        return frames

    drain()
    for cycle in range(cycles):
        for action in script.get(cycle, ()):
            if action[0] == "drop":
                rig.drop_node(action[2], action[1])
            elif action[0] == "restore":
                rig.restore_node(action[2], action[1])
            elif action[0] == "node-sdo":
                _, channel, can_id, data = action
                ch = rig._channels[channel]
                with ch.lock:
                    ch.nodes[can_id - 0x600].on_sdo_request(data)
            else:
                channel, can_id, data = action
                ch = rig._channels[channel]
                with ch.lock:
                    ch._dispatch(can_id, data)
            out.append(("action", cycle, drain()))
        for ch in rig._channels:
            with ch.lock:
                ch._dispatch(0x080, bytes([cycle % 16 + 1]))
        out.append(("sync", cycle, drain()))
    return out


def node_states(rig):
    """What each node holds after the script: image, fault state, EMCY history."""
    out = {}
    for key, node in sorted(rig.nodes.items()):
        image = node.image
        out[key] = dict(decisions=image.decisions, faults=image.faults, tag=image.tag,
                        readings=image.readings.tolist(), fault=node.detector.fault,
                        faulted=node.detector.faulted.tolist(), state=node.state,
                        errors=[node.read(0x1003, s) for s in range(node.read(0x1003, 0) + 1)],
                        register=node.read(0x1001), last_cycle=node.last_cycle,
                        i8=image.data(P.PATCH_READINGS_I8))
    return out


@pytest.fixture
def rigs():
    made = []

    def make(scene):
        names = [f"batch{next(_names)}-{c}" for c in scene.bus.channels]
        rig = Rig(scene, channel=names, reading_source=lambda c: readings(scene.n, c)).start()
        masters = [can.Bus(interface="virtual", channel=n) for n in names]
        made.append((rig, masters))
        return rig, masters

    yield make
    for rig, masters in made:
        rig.stop()
        for bus in masters:
            bus.shutdown()


def assert_same_run(got, wanted):
    assert len(got) == len(wanted)
    for (kind, cycle, frames), (_, _, reference) in zip(got, wanted):
        assert frames == reference, f"{kind} of cycle {cycle}"


def emcy_codes(run):
    return {(c, i, d[:2]) for _, _, frames in run for c, i, d, _ in frames if 0x081 <= i <= 0x0FF}


CASES = [("decision", 1, False), ("decision", 254, False), ("raw", 1, False), ("decision", 1, True)]


@pytest.mark.parametrize("mode,tt,fd", CASES)
@pytest.mark.parametrize("candidate", ["batch", "per-node"])
def test_same_frames_emcys_and_images_as_the_reference(tmp_path, rigs, mode, tt, fd, candidate):
    scene = write_scene(tmp_path, mode, tt, fd)
    reference, reference_buses = rigs(scene)
    make_reference(reference)
    rig, buses = rigs(scene)
    if candidate == "per-node":
        per_node(rig)
    wanted = run_script(reference, reference_buses)
    got = run_script(rig, buses)
    assert_same_run(got, wanted)
    assert node_states(rig) == node_states(reference)
    # the script reached what it is about
    batched = [b for ch in rig._channels for b in ch._sync_batches.values()]
    assert bool(batched) == (candidate == "batch")
    codes = emcy_codes(wanted)
    for ok in (b"\x00\x50", b"\x00\x73", b"\x00\x00"):    # open circuit, stuck, error reset
        assert any(d == ok for _, _, d in codes), ok
    if mode == "raw":     # INTEGER8 counts of 0.05 mV: readings beyond +-6.35 mV over range
        assert any(d == b"\x00\x30" for _, _, d in codes)
    pdos = [f for _, _, frames in wanted for f in frames if 0x181 <= f[1] <= 0x57F]
    assert len(pdos) > 50
    if fd:
        assert all(f[3] for f in pdos)


def test_a_stale_batch_is_caught(tmp_path, rigs, monkeypatch):
    """A batch that keeps its concatenated configuration after a write (here: ζ of one taxel,
    cycle 7, through the node's SDO entry point) sends other frames: the comparison of the test
    above fails, at the SYNC after the write."""
    scene = write_scene(tmp_path)
    reference, reference_buses = rigs(scene)
    make_reference(reference)
    wanted = run_script(reference, reference_buses, cycles=12)
    monkeypatch.setattr(patch_batch._BatchLayout, "current",     # the same nodes: current, whatever was re-read
                        lambda self, configs: len(configs) == len(self.configs))
    rig, buses = rigs(scene)
    with pytest.raises(AssertionError, match="sync of cycle 7"):
        assert_same_run(run_script(rig, buses, cycles=12), wanted)


def test_detect_matches_the_reference_on_random_patches():
    """detect over the concatenation of patches of 1, 7, 13, 192 taxels (padded to whole bytes,
    the padding masked) against reference_sample node by node, 60 SYNCs of random readings
    with NaN, +-inf, beyond full scale / REAL32 and stuck runs; per node full scale, stuck count
    (0: off) and noise."""
    rng = np.random.default_rng(5)
    sizes = (1, 7, 13, 192)
    configs = [(rng.uniform(0, 3, n), rng.choice([0.0, 0.3], n), fs, stuck)
               for n, fs, stuck in zip(sizes, (1000.0, 5.0, 1000.0, 7.5), (3, 0, 1, 20))]

    class Ref:   # what reference_sample needs of a PatchDetector
        def __init__(self, n, cfg):
            self.n, self._cfg, self.fault = n, cfg, patchx.FAULT_NONE
            self._last_raw = np.zeros(n, np.uint32)
            self._same = np.zeros(n, np.int64)
            self.faulted = np.zeros(n, bool)
            self._image = patchx.PatchImage(n)
            self.faults_told = []

        def config(self):
            return self._cfg

        def _on_fault(self, fault, reading):
            self.faults_told.append((fault, reading))

    refs = [Ref(n, c) for n, c in zip(sizes, configs)]
    for r in refs:
        r._faults_changed = types.MethodType(patchx.PatchDetector._faults_changed, r)
    padded = [-(-n // 8) * 8 for n in sizes]
    offsets = np.concatenate(([0], np.cumsum(padded)[:-1]))

    def cat(arrays, fill):
        return np.concatenate([np.concatenate((a, np.full(m - len(a), fill, dtype=np.asarray(a).dtype)))
                               for a, m in zip(arrays, padded)])

    zeta, noise = cat([c[0] for c in configs], 0.0), cat([c[1] for c in configs], 0.0)
    full_scale = np.repeat([c[2] for c in configs], padded)
    stuck = np.repeat([patchx.stuck_limit(c[3]) for c in configs], padded)
    valid = cat([np.ones(n, bool) for n in sizes], False)
    last_raw, same = np.zeros(len(valid), np.uint32), np.zeros(len(valid), np.int64)
    held = rng.normal(0, 3, sum(sizes))
    alone = [(np.zeros(n, np.uint32), np.zeros(n, np.int64)) for n in sizes]
    for step in range(60):
        x_nodes = rng.normal(1.5, 1.0, sum(sizes))
        if step % 3:    # else a clean SYNC: no repeated sample, every reading in range
            repeat = rng.random(sum(sizes)) < 0.6
            x_nodes[repeat] = held[repeat] + 1e-13                  # the same REAL32 as last time
            x_nodes[rng.random(sum(sizes)) < 0.03] = np.nan
            x_nodes[rng.random(sum(sizes)) < 0.02] = np.inf * rng.choice([-1, 1])
            x_nodes[rng.random(sum(sizes)) < 0.02] = rng.choice([7.5, -5.0, 1e39, 2000.0])
        held = x_nodes
        x = cat(np.split(x_nodes, np.cumsum(sizes)[:-1]), 0.0)
        raw, same, open_circuit, faulted, present, any_faulted = patchx.detect(
            x, zeta, noise, full_scale, stuck, int(stuck.min()), last_raw, same, valid)
        last_raw = raw
        assert any_faulted == bool(faulted.any())
        assert not (present & ~valid).any() and not (faulted & ~valid).any()
        packed_present = np.packbits(present, bitorder="little").tobytes()
        packed_faulted = np.packbits(faulted, bitorder="little").tobytes()
        for k, (r, a, n, m, part) in enumerate(zip(refs, offsets, sizes, padded,
                                                   np.split(x_nodes, np.cumsum(sizes)[:-1]))):
            reference_sample(r, part)
            # detect of this node alone (PatchDetector.sample's call: one full scale, no padding)
            zeta_k, noise_k, fs_k, stuck_k = configs[k]
            limit = patchx.stuck_limit(stuck_k)
            raw_k, same_k, _, faulted_k, present_k, _ = patchx.detect(
                part, zeta_k, noise_k, fs_k, limit, limit, *alone[k])
            alone[k] = (raw_k, same_k)
            assert np.packbits(present_k, bitorder="little").tobytes() == r._image.decisions, (step, n)
            assert np.packbits(faulted_k, bitorder="little").tobytes() == r._image.faults, (step, n)
            assert packed_present[a // 8:(a + m) // 8] == r._image.decisions, (step, n)
            assert packed_faulted[a // 8:(a + m) // 8] == r._image.faults, (step, n)
            assert np.array_equal(same[a:a + n], r._same), (step, n)
    assert all(r.faults_told for r in refs[1:])      # faults came and went on every larger patch
