"""``node-sim`` as its own process on python-can's udp_multicast interface, driven by a
canopen master in the test process (loopback only: TTL 0, a test-specific group and port);
the CLI's exit codes; socketcan by name (skipped without a vcan interface)."""

from __future__ import annotations

import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import can
import canopen
import pytest

from node_sim.od import EDS_PATH

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from process_helpers import abort_with_stacks, multicast_group_port, start_node_sim, stop, udp_loopback, wait_ready  # noqa: E402

pytestmark = pytest.mark.multiprocess

SCENE = """
[scene]
name = "mp3"
seed = 3
cycles = 10

[bus]
heartbeat_producer_ms = 50
channels = ["taxel0"]

[kinds.R]
zeta_mv = 1.5
noise_mv = 0.5
noise_sigma_mv = 0.0
signal_mv = 0.0

[[taxels]]
node_id = 4
kind = "R"

[[taxels]]
node_id = 9
kind = "R"

[[taxels]]
node_id = 17
kind = "R"

[object]
model = "script"
present = [[0, 1000]]
readings_mv = [2.0, 0.5, 1.5]

[fusion]
tuple = "pm1"

[[faults]]
node_id = 17
fault = "open_circuit"
from_cycle = 2
"""


def start_on_multicast(tmp_path, group, port):
    """``node-sim`` on the mp3 scene, on udp_multicast ``group:port`` (loopback: hop limit 0)."""
    scene = tmp_path / "mp3.toml"
    scene.write_text(SCENE)
    return start_node_sim("--scene", str(scene), *udp_loopback(group, port))


def heartbeat_states(received: list[can.Message]) -> dict[int, int]:
    """Latest heartbeat state byte per node-ID."""
    return {m.arbitration_id - 0x700: m.data[0] for m in list(received)
            if 0x700 < m.arbitration_id < 0x780 and len(m.data) == 1}


def wait_until(pred, describe, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(describe())
        time.sleep(0.02)


@pytest.fixture
def multicast():
    return multicast_group_port()


def test_node_sim_process_serves_a_canopen_master(tmp_path, multicast):
    group, port = multicast
    proc = start_on_multicast(tmp_path, group, port)
    network = canopen.Network()
    try:
        network.connect(interface="udp_multicast", channel=group, port=port, hop_limit=0)
        received: list[can.Message] = []
        network.notifier.add_listener(received.append)
        wait_ready(proc)
        nodes = {}
        for nid in (4, 9, 17):
            rn = canopen.RemoteNode(nid, str(EDS_PATH))
            rn.sdo.RESPONSE_TIMEOUT = 3.0
            network.add_node(rn)
            nodes[nid] = rn
        assert nodes[9].sdo[0x1000].raw == 0
        assert nodes[17].sdo[0x2001][1].raw == pytest.approx(1.5)
        assert nodes[4].sdo[0x1017].raw == 50
        nodes[9].sdo[0x1800][2].raw = 255        # node 9: event-driven TPDO1
        network.nmt.send_command(0x01)
        wait_until(lambda: all(heartbeat_states(received).get(n) == 0x05 for n in nodes),
                   lambda: f"heartbeat states {heartbeat_states(received)}")
        for _ in range(3):
            network.sync.transmit()
            time.sleep(0.05)
        # script readings Y = [2.0, 0.5, 1.5] vs ζ = 1.5; node 17 open circuit from cycle 2 (absent);
        # node 9 event-driven: sent once on entering operational (-1), never changes after
        expected = {0x184: [1, 1, 1], 0x189: [-1], 0x191: [1, 1, -1]}

        def tpdos():
            return {cob: [struct.unpack("<b", bytes(m.data))[0] for m in list(received)
                          if m.arbitration_id == cob] for cob in expected}

        wait_until(lambda: sum(map(len, tpdos().values())) >= 7, lambda: f"TPDOs {tpdos()}")
        time.sleep(0.2)                          # nothing more may follow
        assert tpdos() == expected
        wait_until(lambda: [e.code for e in nodes[17].emcy.active] == [0x5000],
                   lambda: f"EMCY {nodes[17].emcy.log}")
        emcy = [bytes(m.data) for m in list(received) if m.arbitration_id == 0x80 + 17]
        assert len(emcy) == 1 and emcy[0][:4] == bytes([0x00, 0x50, 0x21, 0x02])   # code LE, 0x1001, fault
        assert nodes[17].sdo[0x1001].raw == 0x21 and nodes[17].sdo[0x1003][1].raw & 0xFFFF == 0x5000
        with pytest.raises(canopen.SdoAbortedError) as info:
            nodes[4].sdo[0x2001][1].raw = -1.0
        assert info.value.code == 0x06090032
        # reset node 17: a new boot-up, pre-operational, start-up values back
        t0 = time.time()
        network.send_message(0x000, bytes([0x81, 17]))
        wait_until(lambda: [bytes(m.data) for m in list(received)
                            if m.arbitration_id == 0x711 and m.timestamp > t0][:1] == [b"\x00"],
                   lambda: "no boot-up of node 17 after reset-node")
        wait_until(lambda: heartbeat_states(received).get(17) == 0x7F, lambda: "node 17 not pre-operational")
        assert nodes[17].sdo[0x1001].raw == 0 and nodes[17].sdo[0x1003][0].raw == 0
        assert heartbeat_states(received).get(4) == 0x05   # addressed: the others stay operational
    finally:
        network.disconnect()
        rc = stop(proc, 30)
    assert rc == 0, proc.stderr.read()


def test_node_sim_sigint_clean_exit(tmp_path, multicast):
    group, port = multicast
    proc = start_on_multicast(tmp_path, group, port)
    try:
        wait_ready(proc)
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(timeout=30)
        except subprocess.TimeoutExpired:  # once, in a loaded suite run: where it hangs, for next time
            abort_with_stacks(proc)
            raise AssertionError(f"node-sim still running 30 s after SIGINT; its threads:\n{proc.stderr.read()}")
        assert rc == 0
    finally:
        stop(proc)
    assert proc.stderr.read() == ""


@pytest.mark.parametrize("args, names", [
    (["--interface", "no_such_bus"], "interface"),
    (["--interface", "udp_multicast", "--channel", "not-a-group"], "channel"),
    (["--eds", "/nonexistent/taxel_node.eds"], "eds"),
])
def test_node_sim_errors_exit_2_with_one_line(tmp_path, args, names):
    scene = tmp_path / "mp3.toml"
    scene.write_text(SCENE)
    proc = subprocess.run([sys.executable, "-m", "node_sim.cli", "--scene", str(scene), *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and names in lines[0]


def test_node_sim_bad_scene_exit_2(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(SCENE.replace('node_id = 9', 'node_id = 200'))
    proc = subprocess.run([sys.executable, "-m", "node_sim.cli", "--scene", str(bad)], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "node_id" in proc.stderr


def test_socketcan_by_name():
    if not Path("/sys/class/net/vcan0").exists():
        pytest.skip("no SocketCAN interface vcan0 on this machine (create one with "
                    "`ip link add dev vcan0 type vcan && ip link set up vcan0`)")
    from taxel_net.scene import BusSpec, Scene, TaxelSpec
    from node_sim.rig import Rig

    scene = Scene(path="<t>", name="sc", taxels=(TaxelSpec(node_id=1, kind="R"),),
                  bus=BusSpec(channels=("vcan0",)))
    mon = can.Bus(interface="socketcan", channel="vcan0")
    try:
        with Rig(scene, interface="socketcan"):
            msg = mon.recv(5.0)
            assert msg is not None and msg.arbitration_id == 0x701 and bytes(msg.data) == b"\x00"
    finally:
        mon.shutdown()
