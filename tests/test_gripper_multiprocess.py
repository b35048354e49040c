"""The gripper drive in ANOTHER process: ``node-sim --scene grasp_drive -i udp_multicast`` (the drive
on the rig beside six taxel nodes), driven by canopen's ``BaseNode402`` in the test process
(loopback only: hop limit 0, a test-specific group and port; every wait bounded). The master
produces SYNC every 10 ms and its heartbeat every 50 ms, sends RPDO1 every 10 ms (BaseNode402
sends a synchronous RPDO only on ``transmit()``), and reads the statusword from TPDO1 (it times
out when the statusword is older than 0.2 s: udp_multicast on loopback stays well below).

Expected values by hand from scenes/grasp_drive.toml: profile torque at start-up, rated force
140.0 N per jaw, max torque 800 ‰, slope 40 ‰ per SYNC, stroke 2..60 mm, velocity 0.4 mm per
SYNC, 0x6007 = 0; the drive watches node 127's heartbeat for 150 ms (3 x 50 ms)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import canopen
import pytest
from canopen.profiles.p402 import BaseNode402

from node_sim.gripper.drive import GRIPPER_EDS_PATH

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from process_helpers import multicast_group_port, node_sim, udp_loopback  # noqa: E402

pytestmark = pytest.mark.multiprocess

DRIVE = 32
MASTER = 127
SYNC_S = 0.01
WAIT_S = 10.0


class Master:
    """canopen's BaseNode402 on the group, with SYNC, heartbeat and periodic RPDO1."""

    def __init__(self, group: str, port: int):
        self.net = canopen.Network()
        self.net.connect(interface="udp_multicast", channel=group, port=port, hop_limit=0)
        self.heartbeat = self.net.send_periodic(0x700 + MASTER, b"\x05", 0.05)
        self.node = BaseNode402(DRIVE, str(GRIPPER_EDS_PATH))
        self.node.sdo.RESPONSE_TIMEOUT = 2.0
        self.net.add_node(self.node)
        self.net.sync.start(SYNC_S)
        self.rpdo = None
        self.node.nmt.wait_for_heartbeat(WAIT_S)
        self.node.setup_402_state_machine()
        self.node.nmt.state = "OPERATIONAL"
        self.rpdo = self.node.rpdo[1]
        self.rpdo.start(SYNC_S)

    def wait(self, condition, what: str) -> None:
        deadline = time.monotonic() + WAIT_S
        while not condition():
            assert time.monotonic() < deadline, f"{what} not reached (statusword 0x{self.node.statusword:04X}, " \
                                                f"{self.node.tpdo_values})"
            # canopen's own TPDO wait (0.2 s) raised on a host that held the process longer
            self.node.check_statusword(timeout=max(0.01, deadline - time.monotonic()))

    @property
    def values(self) -> dict[int, int]:
        return self.node.tpdo_values

    def close(self) -> None:
        if self.rpdo is not None:
            self.rpdo.stop()
        self.heartbeat.stop()
        self.net.sync.stop()
        self.net.disconnect()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def test_base_node_402_drives_the_drive_of_node_sim_over_udp_multicast():
    group, port = multicast_group_port()
    with node_sim("--scene", "grasp_drive", *udp_loopback(group, port), stop_s=30) as proc, \
            Master(group, port) as master:
        assert "gripper drive 32" in proc.ready_line, proc.ready_line
        node, values = master.node, master.values
        master.wait(lambda: node.state == "SWITCH ON DISABLED", "SWITCH ON DISABLED")
        assert node.sdo[0x2103].raw == 1400 and node.sdo[0x6072].raw == 800      # the scene's start-up values

        # profile torque (the scene's start-up mode): no part between the jaws -> closed to 2 mm, NO_PART
        assert node.op_mode == "PROFILED TORQUE"
        node.state = "OPERATION ENABLED"
        assert node.state == "OPERATION ENABLED"
        node.rpdo_pointers[0x6071].raw = 500
        master.wait(lambda: values[0x6077] == 500 and values[0x2100] == 2 and values[0x6064] == 2000,
                    "torque 500 ‰, closed to the stroke limit")
        assert values[0x2101] == 0 and node.statusword & 0x0800             # no part: no force, at a limit

        # quick stop (0x605A = 2) from 500 ‰: the torque ramps to 0 at 40 ‰ a SYNC, then SWITCH ON DISABLED
        torques: list[int] = []
        node.tpdo[1].add_callback(lambda m: torques.append(node.tpdo_values[0x6077]))
        node.state = "QUICK STOP ACTIVE"
        master.wait(lambda: node.state == "SWITCH ON DISABLED", "SWITCH ON DISABLED after the quick stop")
        ramp = [t for t in torques if 0 < t < 500]
        assert ramp and set(ramp) <= set(range(460, 0, -40)) and values[0x6077] == 0

        # profile position: open to 30 mm at 0.4 mm a SYNC
        node.rpdo_pointers[0x6071].raw = 0
        node.op_mode = "PROFILED POSITION"
        assert node.op_mode == "PROFILED POSITION"
        node.state = "OPERATION ENABLED"
        node.rpdo_pointers[0x607A].raw = 30000
        node.controlword = 0x1F                                             # new set-point
        master.wait(lambda: node.statusword & 0x1000, "set-point acknowledge")
        node.controlword = 0x0F
        master.wait(lambda: values[0x6064] == 30000 and node.statusword & 0x0400, "at 30 mm, target reached")

        # a fault, then reset_from_fault()
        node.state = "OPERATION ENABLED"
        node.emcy.reset()
        node.sdo[0x2110].raw = 0x2310
        master.wait(lambda: node.state == "FAULT", "FAULT")
        master.wait(lambda: any(e.code == 0x2310 for e in node.emcy.log), "EMCY 0x2310")
        master.wait(lambda: values[0x603F] == 0x2310, "0x603F in TPDO2 (it follows TPDO1)")
        node.reset_from_fault()
        assert node.state == "OPERATION ENABLED"
        master.wait(lambda: values[0x603F] == 0, "error code cleared")

        # a lost master (0x6007 = 0, the default): the drive keeps its set-points
        node.op_mode = "PROFILED TORQUE"
        node.state = "OPERATION ENABLED"
        node.rpdo_pointers[0x6071].raw = 400
        master.wait(lambda: values[0x6077] == 400 and values[0x2100] == 2, "torque 400 ‰")
        node.emcy.reset()
        master.rpdo.stop()                       # the master falls silent: no RPDO, no heartbeat ...
        master.heartbeat.stop()                  # ... (SYNC from elsewhere keeps the TPDOs coming)
        master.wait(lambda: any(e.code == 0x8130 for e in node.emcy.log), "EMCY 0x8130")
        master.wait(lambda: node.statusword & 0x0080, "warning bit 7")
        for _ in range(30):                      # 0.3 s later
            node.check_statusword(timeout=WAIT_S)
        assert node.state == "OPERATION ENABLED" and values[0x6077] == 400 and values[0x603F] == 0x8130
        master.heartbeat = master.net.send_periodic(0x700 + MASTER, b"\x05", 0.05)   # back
        master.wait(lambda: not node.statusword & 0x0080, "warning cleared")
    assert proc.returncode == 0, proc.stderr.read()
