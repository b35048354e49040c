"""``fusion-center dcf`` for a scene's gripper drive (``[gripper]``): the DCF of eds/gripper_drive.eds
with the drive's start-up values, read back by canopen; ``--all`` writes it beside the taxels'."""

from __future__ import annotations

from pathlib import Path

import canopen

from fusion_center.cli import main
from fusion_center.commands.dcf import drive_dcf_text, drive_file_name
from taxel_net.gripper import identity_serial, startup_values
from taxel_net.resources import gripper_eds_path
from taxel_net.scene import load_scene


def check_drive_dcf(path: Path, scene) -> None:
    """canopen reads the node-ID, bit rate and every start-up value back; nothing else has one."""
    od = canopen.import_od(str(path))
    assert od.node_id == 32 and od.bitrate == scene.bus.bitrate
    assert od[0x1200][1].default == 0x600 + 32                   # $NODEID resolved for node 32
    wanted = startup_values(scene)
    for (obj, sub), value in wanted.items():
        var = od[obj] if isinstance(od[obj], canopen.objectdictionary.ODVariable) else od[obj][sub]
        assert var.value == value, (hex(obj), sub, var.value, value)
    # by hand from scenes/grasp_drive.toml
    assert od[0x2103].value == 1400 and od[0x607D][1].value == 2000 and od[0x607D][2].value == 60000
    assert od[0x6060].value == 4 and od[0x6072].value == 800 and od[0x1016][1].value == 127 << 16 | 150
    others = [(v.index, v.subindex) for obj in od.values()
              for v in ([obj] if isinstance(obj, canopen.objectdictionary.ODVariable) else obj.values())
              if v.value is not None and (v.index, v.subindex) not in wanted]
    assert others == []


def test_drive_dcf_reads_back_with_the_start_up_values(tmp_path, capsys):
    scene = load_scene("grasp_drive")
    out = tmp_path / "drive.dcf"
    assert main(["dcf", "--scene", "grasp_drive", "--node", "32", "-o", str(out)]) == 0
    check_drive_dcf(out, scene)
    assert capsys.readouterr().out == (f"DCF of gripper drive 32 (CiA 402) of scene 'grasp_drive' written to {out}: "
                                       f"{len(startup_values(scene))} parameter values\n")
    text = out.read_text()
    assert "[DeviceComissioning]\nNodeID=32\nNodeName=gripper drive 32 (CiA 402)\n" in text
    assert f"LSS_SerialNumber=0x{identity_serial(scene):08X}\n" in text
    assert "FileName=drive.dcf\nLastEDS=gripper_drive.eds\n" in text
    eds = gripper_eds_path().read_text().splitlines()
    kept = iter(text.splitlines())
    assert all(any(line == d for d in kept) for line in eds if not line.startswith(("FileName=", "Description=")))


def test_all_writes_the_drive_beside_the_taxels_and_stdout(tmp_path, capsys):
    scene = load_scene("grasp_drive")
    assert main(["dcf", "--scene", "grasp_drive", "--all", "-o", str(tmp_path / "out")]) == 0
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == sorted([f"grasp_drive_node{i:03d}.dcf" for i in range(1, 7)] + ["grasp_drive_gripper_node032.dcf"])
    assert drive_file_name(scene) == "grasp_drive_gripper_node032.dcf"
    assert capsys.readouterr().out.endswith(", and the gripper drive's (grasp_drive_gripper_node032.dcf)\n")
    check_drive_dcf(tmp_path / "out" / drive_file_name(scene), scene)
    assert main(["dcf", "--scene", "grasp_drive", "--node", "0:32", "-o", "-"]) == 0
    assert capsys.readouterr().out == drive_dcf_text(scene, gripper_eds_path().read_text(), drive_file_name(scene))
    # a scene without [gripper]: node 32 is no node of it
    assert main(["dcf", "--scene", "gripper18", "--node", "32", "-o", "-"]) == 2


def test_eds_given_for_the_drive_is_the_one_its_dcf_is_made_from(tmp_path, capsys):
    """``--eds`` with ``--node`` naming the drive: the DCF is made from that file (it was checked
    as a taxel EDS and then dropped for the shipped drive EDS)."""
    scene = load_scene("grasp_drive")
    mine = tmp_path / "my_drive.eds"
    mine.write_text(gripper_eds_path().read_text().replace("ProductName=", "ProductName=my ", 1))
    out = tmp_path / "drive.dcf"
    assert main(["dcf", "--scene", "grasp_drive", "--node", "32", "--eds", str(mine), "-o", str(out)]) == 0
    assert "ProductName=my " in out.read_text()
    check_drive_dcf(out, scene)
