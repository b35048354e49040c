"""``fusion-center dcf`` of patch scenes (``[bus] patch_nodes``): one DCF per patch node, made
from eds/taxel_patch.eds with the values ``patch_configuration`` writes, read back by canopen."""

from __future__ import annotations

import dataclasses
import re
import struct
import sys
from pathlib import Path

import canopen
import pytest

from fusion_center.cli import main
from fusion_center.commands.dcf import configured_values, dcf_text, file_name
from fusion_center.service.node_config import patch_configuration
from node_sim.rig import identity_serial
from taxel_net.patches import devices
from taxel_net.resources import patch_eds_path
from taxel_net.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_inprocess import run_cli  # noqa: E402
from test_service_patch import booted_by_the_centre, small_skin  # noqa: E402 - shared test set-ups



def real32(x):
    return struct.pack("<f", x)


def is_variable(entry):
    return isinstance(entry, canopen.objectdictionary.ODVariable)


def dcf_values(od) -> dict[tuple[int, int], object]:
    """(index, sub) -> value of every entry of ``od`` that has one (a ParameterValue)."""
    return {(v.index, v.subindex): v.value for obj in od.values()
            for v in ([obj] if is_variable(obj) else obj.values()) if v.value is not None}


def last_writes(scene, device) -> dict[tuple[int, int], object]:
    last = {}
    for obj, sub, value, _ in patch_configuration(scene, device):
        last[(obj, sub)] = value
    return last


def assert_same(got: dict, wanted: dict):
    assert set(got) == set(wanted), (set(got) ^ set(wanted))
    for key, value in wanted.items():
        if isinstance(value, float):
            assert real32(got[key]) == real32(value), (key, got[key], value)
        else:
            assert got[key] == value, (key, got[key], value)


def check_patch_dcf(path: Path, scene, index: int) -> dict[tuple[int, int], object]:
    """canopen reads the commissioning and a ParameterValue for exactly the entries the master
    writes, each equal to its last write. Returns what canopen read."""
    d = devices(scene)[index]
    od = canopen.import_od(str(path))
    assert od.node_id == d.node_id and od.bitrate == scene.bus.bitrate
    assert od[0x1200][1].default == 0x600 + d.node_id   # $NODEID resolved for this node
    got = dcf_values(od)
    wanted = last_writes(scene, d)
    assert configured_values(scene, index) == {k: v for k, v in wanted.items()}
    assert_same(got, wanted)
    # the per-taxel arrays: one entry per taxel of the device, sub k + 1 for its taxel k
    assert {sub for obj, sub in got if obj == 0x2010} == set(range(1, len(d.taxels) + 1))
    text = path.read_text()
    assert "FileName=" + path.name + "\nLastEDS=taxel_patch.eds\n" in text
    commissioning = (f"[DeviceComissioning]\nNodeID={d.node_id}\nNodeName=patch node {d.label} "
                     f"({len(d.taxels)} taxels)\nBaudrate={scene.bus.bitrate // 1000}\n"
                     f"NetNumber={d.channel + 1}\nNetworkName={scene.bus.channels[d.channel]}\n"
                     f"CANopenManager=0\n"
                     # what the patch twin reports in 0x1018:4 (node_sim.rig._new_patch_node)
                     f"LSS_SerialNumber=0x{identity_serial(scene, scene.taxels[d.taxels[0]]):08X}\n")
    assert commissioning in text
    return got


@pytest.mark.parametrize("name", ["skin4096", "skin4096_fd", "skin4096_raw"])
def test_patch_dcf_holds_the_last_write_of_every_configured_entry(tmp_path, name):
    scene = small_skin(name, channels=1)
    eds = patch_eds_path().read_text()
    n = len(devices(scene))
    assert n == 3
    for index in (range(n) if name == "skin4096" else (n - 1,)):  # the last: 128 taxels, a shorter last TPDO
        path = tmp_path / file_name(scene, index)
        path.write_text(dcf_text(scene, index, eds, path.name))
        got = check_patch_dcf(path, scene, index)
        if name == "skin4096_raw":
            assert real32(got[(0x2032, 0)]) == real32(scene.bus.raw_lsb_mv)
    # every EDS line is kept, in order: the DCF is the EDS plus the commissioning
    dcf = iter(path.read_text().splitlines())
    assert all(any(line == x for x in dcf) for line in eds.splitlines()
               if not line.startswith(("FileName=", "Description=")))


def test_patch_dcf_is_what_the_twin_holds_after_the_master_booted_it(tmp_path):
    """Independent of patch_configuration's list: the values a canopen master left in a patch
    twin over SDO (virtual bus) are the DCF's, entry by entry."""
    scene = small_skin("skin4096_raw", channels=1)
    scene = dataclasses.replace(scene, taxels=tuple(t for t in scene.taxels if t.node_id == 3))
    (d,) = devices(scene)
    path = tmp_path / "p.dcf"
    path.write_text(dcf_text(scene, 0, patch_eds_path().read_text(), path.name))
    got = check_patch_dcf(path, scene, 0)
    with booted_by_the_centre(scene) as (svc, rig):
        m = svc.master
        assert m.sdo_writes == len(patch_configuration(scene, d)) and m.sdo_aborts == 0 and m.sdo_timeouts == 0
        sdo = rig.node(d.node_id, d.channel).local.sdo
        held = {(obj, sub): (sdo[obj] if is_variable(sdo.od[obj]) else sdo[obj][sub]).raw for obj, sub in got}
    assert_same(held, got)


def test_all_writes_one_dcf_per_patch_node(tmp_path, capsys):
    scene = load_scene("skin4096")
    devs = devices(scene)
    out = tmp_path / "out"
    assert main(["dcf", "--scene", "skin4096", "--all", "-o", str(out)]) == 0
    files = sorted(out.iterdir())
    assert len(files) == len(devs) == 24 and len({f.name for f in files}) == 24
    assert {f.name for f in files} == {file_name(scene, i) for i in range(len(devs))}
    assert capsys.readouterr().out == (f"24 DCFs of scene 'skin4096' written to {out} "
                                       f"(one per patch node, 4096 taxels)\n")
    seen = set()
    for i, d in enumerate(devs):
        text = (out / file_name(scene, i)).read_text()
        net = int(re.search(r"^NetNumber=(\d+)$", text, re.M).group(1))
        node = int(re.search(r"^NodeID=(\d+)$", text, re.M).group(1))
        taxels = int(re.search(r"^NodeName=patch node \S+ \((\d+) taxels\)$", text, re.M).group(1))
        assert (net - 1, node, taxels) == (d.channel, d.node_id, len(d.taxels))
        seen.add((net, node))
    assert len(seen) == 24 and sum(len(d.taxels) for d in devs) == 4096
    i = len(devs) - 1  # a node off channel 0, read back in full
    check_patch_dcf(out / file_name(scene, i), scene, i)


def test_node_of_a_patch_scene_to_stdout_and_to_a_file(tmp_path, capsys):
    scene = load_scene("skin4096")
    index = next(i for i, d in enumerate(devices(scene)) if (d.channel, d.node_id) == (2, 3))
    assert main(["dcf", "--scene", "skin4096", "--node", "2:3", "-o", "-"]) == 0
    text = capsys.readouterr().out
    assert text == dcf_text(scene, index, patch_eds_path().read_text(), file_name(scene, index))
    assert "NodeName=patch node 2:3 (128 taxels)\n" in text
    out = tmp_path / "p.dcf"
    assert main(["dcf", "--scene", "skin4096", "--node", "1", "-o", str(out)]) == 0
    n = text.count("ParameterValue=")
    m = out.read_text().count("ParameterValue=")
    assert capsys.readouterr().out == (f"DCF of patch node 1 (192 taxels) of scene 'skin4096' written to {out}: "
                                       f"{m} parameter values\n")
    assert m == len(configured_values(scene, 0)) and n == len(configured_values(scene, index)) and m > n


@pytest.mark.parametrize("node, message", [
    ("4", "--node '4': no node 4 on channel 0 (use C:N for another channel) of scene 'skin4096'"),
    ("8:1", "--node '8:1': no node 1 on channel 8 of scene 'skin4096'"),
])
def test_a_node_that_is_no_patch_node_exits_2_with_one_line(tmp_path, capsys, node, message):
    # in this process (tests/cli_inprocess.py): the exit status and stderr are main()'s
    run = run_cli(capsys, "dcf", "--scene", "skin4096", "--node", node, "-o", "x.dcf", cwd=tmp_path)
    assert run.returncode == 2 and run.stdout == "", run
    assert run.stderr == f"fusion-center dcf: error: {message}\n"
    assert not (tmp_path / "x.dcf").exists()
