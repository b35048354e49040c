"""The master side on a patch node twin: canopen's RemoteNode / SDO client reads and writes the
patch arrays and the PDO mapping; bad writes get their CiA 301 abort codes."""

from __future__ import annotations

import dataclasses
import itertools
import time

import can
import canopen
import pytest
from canopen.sdo import SdoAbortedError

from node_sim.patch import load_patch_od
from node_sim.rig import Rig
from taxel_net import patches as P
from taxel_net.scene import TAXEL_KINDS

from test_node_patch import write_scene

_names = itertools.count()


@pytest.fixture
def patch_net(tmp_path):
    scene = write_scene(tmp_path, sizes=((0, 1, 10), (0, 2, 70)), sync_counter=16)
    scene = dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, channels=("a",), sync_window_us=0))
    name = f"patchsdo{next(_names)}"
    rig = Rig(scene, channel=name).start()
    net = canopen.Network()
    net.connect(interface="virtual", channel=name)
    # the master's dictionary: the same EDS (import cached, as the twins' own)
    nodes = {nid: net.add_node(canopen.RemoteNode(nid, load_patch_od(nid))) for nid in (1, 2)}
    for n in nodes.values():
        n.sdo.RESPONSE_TIMEOUT = 2.0
    try:
        yield rig, net, nodes
    finally:
        net.disconnect()
        rig.stop()


def abort_code(fn) -> int:
    with pytest.raises(SdoAbortedError) as e:
        fn()
    return e.value.code


def test_arrays_read_and_write_over_sdo(patch_net):
    rig, net, nodes = patch_net
    small, big = nodes[1], nodes[2]
    assert small.sdo[P.PATCH_ZETA][0].raw == 10 and big.sdo[P.PATCH_ZETA][0].raw == 70
    assert small.sdo[P.PATCH_DECISIONS][0].raw == 2 and big.sdo[P.PATCH_DECISIONS][0].raw == 9
    assert small.sdo[P.PATCH_ZETA][3].raw == pytest.approx(2.5)
    assert small.sdo[P.PATCH_KIND][10].raw == TAXEL_KINDS["C"]
    small.sdo[P.PATCH_ZETA][3].raw = 1.25
    assert small.sdo[P.PATCH_ZETA][3].raw == 1.25
    assert rig.node(1).detector.config()[0][2] == 1.25                   # the detector uses it
    assert small.sdo[0x1008].raw == "taxel patch node twin"              # segmented upload
    assert small.sdo[0x1018][2].raw == 0x7A02
    # CiA 301 aborts
    assert abort_code(lambda: small.sdo[P.PATCH_ZETA][11].raw) == 0x06090011          # no taxel 11 here
    assert abort_code(lambda: setattr(small.sdo[P.PATCH_ZETA][11], "raw", 1.0)) == 0x06090011
    assert abort_code(lambda: setattr(small.sdo[P.PATCH_ZETA][2], "raw", -1.0)) == 0x06090032
    assert abort_code(lambda: setattr(small.sdo[P.PATCH_KIND][2], "raw", 9)) == 0x06090031
    assert abort_code(lambda: setattr(small.sdo[P.PATCH_ZETA][0], "raw", 3)) == 0x06010002   # sub 0 read-only
    assert abort_code(lambda: setattr(small.sdo[P.PATCH_DECISIONS][1], "raw", 1)) == 0x06010002
    assert abort_code(lambda: setattr(small.sdo[P.PATCH_RAW_LSB], "raw", 0.0)) == 0x06090032
    assert abort_code(lambda: small.sdo[P.PATCH_DECISIONS][3].raw) == 0x06090011


def test_mapping_read_and_remapped_by_the_master(patch_net):
    rig, net, nodes = patch_net
    big = nodes[2]
    tpdo = big.tpdo[2]                                    # 0x1801 / 0x1A01: taxels 56..69
    tpdo.read(from_od=False)
    assert tpdo.cob_id == 0x183 and tpdo.enabled
    assert [(v.index, v.subindex) for v in tpdo.map] == [(P.PATCH_CYCLE_TAG, 0), (P.PATCH_DECISIONS, 8),
                                                          (P.PATCH_DECISIONS, 9)]
    mapping = big.sdo[0x1A01]
    # mapping while the PDO is valid, beyond the node's taxels, too long
    assert abort_code(lambda: setattr(mapping[0], "raw", 0)) == 0x06010000
    big.sdo[0x1801][1].raw = 0xC0000183                   # not valid
    mapping[0].raw = 0
    assert abort_code(lambda: setattr(mapping[1], "raw", P.PATCH_DECISIONS << 16 | 10 << 8 | 8)) == 0x06040041
    for sub in range(1, 9):
        mapping[sub].raw = P.PATCH_READINGS_I16 << 16 | sub << 8 | 16
    assert abort_code(lambda: setattr(mapping[0], "raw", 5)) == 0x06040042    # 80 bits on classic CAN
    assert abort_code(lambda: setattr(mapping[0], "raw", 9)) == 0x06090031    # 8 entries on classic CAN
    # remap with canopen's PDO API: the tag and taxel 0..2 as INTEGER16 counts
    tpdo.clear()
    tpdo.add_variable(P.PATCH_CYCLE_TAG)
    for sub in (1, 2, 3):
        tpdo.add_variable(P.PATCH_READINGS_I16, sub)
    tpdo.cob_id = 0x190
    tpdo.enabled = True
    tpdo.trans_type = 1
    tpdo.save()
    frames = []
    net.subscribe(0x190, lambda can_id, data, ts: frames.append(bytes(data)))
    net.nmt.send_command(0x01)
    time.sleep(0.1)
    net.sync.transmit(5)
    deadline = time.monotonic() + 3
    while not frames and time.monotonic() < deadline:
        time.sleep(0.01)
    node = rig.node(2)
    counts, _ = P.readings_to_counts(P.Tpdo(0, 0, 0, 3, P.ENC_INT16, False, 0, False),
                                     node.image.readings[:3], node.image.lsb_mv)
    assert frames[0] == bytes([5]) + counts.tobytes()


def test_nmt_start_reads_only_the_tpdos_the_master_changed(patch_net):
    """A patch node has 85 TPDOs; its NMT start used to read every one's configuration from the
    data store (~1,000 canopen reads for two patches, 12-34 ms on a loaded host: the centre's
    first SYNC, sent right after the NMT start, was handled past its synchronous window and got
    no patch frame - scenes/grasp_lift_patch.toml's cycle 0). Read at boot now, and after an SDO
    download only the written TPDO again."""
    rig, net, nodes = patch_net
    big = nodes[2]
    big.sdo[0x1801][1].raw = 0xC0000183                   # TPDO2 not valid: the master disables it
    node = rig.node(2)
    # the download's own re-read (TpdoEngine.reconfigure, on the node's scheduler just after the
    # SDO answer) done before counting: on a loaded host it ran after the NMT start (a second,
    # correct read of 0x1801:1 counted as the start's)
    deadline = time.monotonic() + 3
    while node.pdo._dirty and time.monotonic() < deadline:
        time.sleep(0.005)
    assert not node.pdo._dirty
    reads = []
    original = node.objects.read

    def counting(index, subindex=0):
        reads.append((index, subindex))
        return original(index, subindex)

    node.objects.read = counting
    try:
        frames = []
        net.subscribe(0x182, lambda can_id, data, ts: frames.append(bytes(data)))
        net.subscribe(0x183, lambda can_id, data, ts: frames.append(("tpdo2", bytes(data))))
        net.nmt.send_command(0x01)
        deadline = time.monotonic() + 3
        while node.state != 0x05 and time.monotonic() < deadline:
            time.sleep(0.01)
        nmt_reads = list(reads)
        net.sync.transmit(5)
        while not frames and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
    finally:
        node.objects.read = original
    tpdo_reads = [r for r in nmt_reads if 0x1800 <= r[0] <= 0x1BFF]
    assert node.state == 0x05
    assert len(tpdo_reads) <= 1, tpdo_reads               # 0x1801:1 only (not valid: nothing more)
    assert len(frames) == 1 and frames[0][0] == 5         # TPDO1 sent on the SYNC, the disabled one not
