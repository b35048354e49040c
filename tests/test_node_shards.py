"""A scene sharded over several node-sim processes (``--serve``, issue 14): each runs the nodes
of its channels only; with the centre in a third process on udp_multicast every cycle's decisions
match the physics of that cycle (the readings are a function of scene and cycle, so shards agree)."""

from __future__ import annotations

import sys
from contextlib import ExitStack
from pathlib import Path

import pytest

from node_sim.cli import parse_channel_indices
from node_sim.rig import Rig
from taxel_net.errors import ParameterError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
GROUPS = ["239.74.163.11", "239.74.163.12"]

SCENE = """
[scene]
name = "two_patch_buses"
seed = 11
cycles = 60
[bus]
sync_period_ms = 40.0
sync_counter = 64
channels = ["a", "b"]
patch_nodes = true
[kinds.C]
zeta_mv = 3.5
noise_sigma_mv = 0.8
signal_mv = 6.0
[object]
model = "large"
x = 20.0
y = 0.0
radius = 12.0
present = [[10, 40]]
[fusion]
rules = ["k-of-n"]
decide_with = "k-of-n"
tuple = "pm1"
k = 2
"""


def _scene_file(tmp_path: Path) -> Path:
    rows = []
    for channel in (0, 1):
        for k in range(40):  # node 1: taxels 0-29, node 2: 30-39 of each channel
            rows.append(f"[[taxels]]\nnode_id = {1 if k < 30 else 2}\nkind = 'C'\nchannel = {channel}\n"
                        f"x = {2.0 * k + 80.0 * channel}\ny = 0.0\n")
    path = tmp_path / "two_patch_buses.toml"
    path.write_text(SCENE + "".join(rows))
    return path


def test_serve_parses_ranges_and_lists():
    assert parse_channel_indices("0-3") == [0, 1, 2, 3]
    assert parse_channel_indices("0,2,5") == [0, 2, 5]
    assert parse_channel_indices("0-1,7") == [0, 1, 7]
    for bad in ("", "a", "3-1", "-1"):
        with pytest.raises(Exception):
            parse_channel_indices(bad)


def test_a_rig_serving_one_channel_opens_its_bus_and_creates_its_nodes_only(tmp_path):
    scene = load_scene(_scene_file(tmp_path))
    rig = Rig(scene, interface="virtual", channel=["shard-a", "shard-b"], serve_channels=[1])
    with rig:
        assert [b.channel_info for b in rig.buses] and len(rig.buses) == 1
        assert sorted(rig.nodes) == [(1, 1), (1, 2)]
        with pytest.raises(ParameterError, match="not served"):
            rig.node(1, channel=0)
    with pytest.raises(ParameterError, match="serve_channels"):
        Rig(scene, interface="virtual", serve_channels=[2])


def test_two_node_sim_shards_and_the_centre_on_udp_multicast(tmp_path):
    sys.path.insert(0, str(ROOT / "tests"))
    sys.path.insert(0, str(ROOT / "bench"))
    from skin_scale import check_records
    from process_helpers import node_sim, wait_ready
    from test_service_multiprocess import multicast_port

    from fusion_center.service import FusionService

    port = multicast_port()
    path = _scene_file(tmp_path)
    scene = load_scene(path)
    with ExitStack() as running:
        shards = [running.enter_context(node_sim("--scene", str(path), "-i", "udp_multicast", "-c", ",".join(GROUPS),
                                                 "--bus-kwargs", f"port={port}", "hop_limit=0", "--serve", serve,
                                                 ready=False)) for serve in ("0", "1")]
        for shard, name in zip(shards, GROUPS):
            line = wait_ready(shard)
            assert "ready: 2 patch nodes (40 taxels)" in line and name in line, line
        with FusionService(scene, interface="udp_multicast", channels=GROUPS,
                           bus_kwargs={"port": port, "hop_limit": 0}) as service:
            service.boot(5.0)
            assert not service.summary().missing_at_boot
            service.run(60)
    figures = check_records(scene, service.records)
    print(figures)
    assert figures["misattributed"] == 0
    assert figures["complete"] + figures["degraded"] > 0  # both shards' decisions crossed processes
    # every complete record holds both shards' nodes: the four devices, 80 taxels
    assert all(r["n_received"] == 80 for r in service.records if r["closed_by"] == "complete")


def test_udp_multicast_buses_on_two_groups_and_one_port_do_not_hear_each_other():
    """python-can binds ("", port): without IP_MULTICAST_ALL = 0 a bus on group A also receives
    group B's datagrams for that port (two scene channels would be one bus)."""
    import can

    from taxel_net.canmsg import tune_udp_multicast

    sys.path.insert(0, str(ROOT / "tests"))
    from test_service_multiprocess import multicast_port

    port = multicast_port()
    if not sys.platform.startswith("linux"):
        pytest.skip("IP_MULTICAST_ALL is a Linux socket option")
    a = can.Bus(interface="udp_multicast", channel=GROUPS[0], port=port, hop_limit=0)
    b = can.Bus(interface="udp_multicast", channel=GROUPS[1], port=port, hop_limit=0)
    a2 = can.Bus(interface="udp_multicast", channel=GROUPS[0], port=port, hop_limit=0)
    try:
        for bus in (a, b, a2):
            tune_udp_multicast(bus)
        b.send(can.Message(arbitration_id=0x123, data=b"\x02", is_extended_id=False))
        a2.send(can.Message(arbitration_id=0x124, data=b"\x01", is_extended_id=False))
        heard = set()
        while (msg := a.recv(0.5)) is not None:
            heard.add(msg.arbitration_id)
        assert heard == {0x124}  # its own group's frame, not group B's
    finally:
        for bus in (a, b, a2):
            bus.shutdown()
