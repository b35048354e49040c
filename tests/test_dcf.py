"""``fusion-center dcf``: CiA 306 DCFs of a scene's nodes, read back by canopen (and the
other EDS tools within their documented limits)."""

from __future__ import annotations

import re
import struct
import subprocess
import sys
from pathlib import Path

import canopen
import pytest

from fusion_center.cli import main
from cli_inprocess import run_cli
from fusion_center.commands.dcf import configured_values, dcf_text, file_name
from fusion_center.service.node_config import node_configuration
from node_sim.rig import identity_serial
from taxel_net.resources import eds_path
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent


def real32(x):
    return struct.pack("<f", x)


def check_dcf(path: Path, scene, index: int) -> int:
    """canopen reads back the node-ID, bit rate and every configured value; nothing else has
    a ParameterValue. Returns the number of values checked."""
    t = scene.taxels[index]
    od = canopen.import_od(str(path))
    assert od.node_id == t.node_id and od.bitrate == scene.bus.bitrate
    # $NODEID defaults resolved for this node-ID (the commissioning's)
    assert od[0x1200][1].default == 0x600 + t.node_id
    wanted = configured_values(scene, index)
    # the last write of each object of the master's SDO configuration
    last = {}
    for obj, sub, value in node_configuration(scene, index):
        last[(obj, sub)] = value
    assert wanted == last
    for (obj, sub), value in wanted.items():
        var = od[obj] if isinstance(od[obj], canopen.objectdictionary.ODVariable) else od[obj][sub]
        if isinstance(value, float):
            assert real32(var.value) == real32(value), (obj, sub, var.value, value)
        else:
            assert var.value == value, (obj, sub)
    others = [(v.index, v.subindex) for obj in od.values()
              for v in ([obj] if isinstance(obj, canopen.objectdictionary.ODVariable) else obj.values())
              if v.value is not None and (v.index, v.subindex) not in wanted]
    assert others == []
    return len(wanted)


def test_node_dcf_reads_back_with_the_configured_values(tmp_path, capsys):
    scene = load_scene("matrix57")
    out = tmp_path / "n17.dcf"
    assert main(["dcf", "--scene", "matrix57", "--node", "17", "-o", str(out)]) == 0
    index = next(i for i, t in enumerate(scene.taxels) if t.node_id == 17)
    n = check_dcf(out, scene, index)
    assert n >= 18  # zeta, N, kind, x, y, heartbeat, 0x1019, 0x1007, TPDOs, mapping, calibration
    assert capsys.readouterr().out == (f"DCF of node 17 ({scene.taxels[index].kind}) of scene 'matrix57' "
                                       f"written to {out}: {n} parameter values\n")
    text = out.read_text()
    assert "[DeviceComissioning]\nNodeID=17\n" in text
    assert f"LSS_SerialNumber=0x{identity_serial(scene, scene.taxels[index]):08X}\n" in text
    assert "FileName=n17.dcf\nLastEDS=taxel_node.eds\n" in text
    # every EDS line is kept, in order: the DCF is the EDS plus the commissioning
    eds = eds_path().read_text().splitlines()
    dcf = text.splitlines()
    kept = iter(dcf)
    assert all(any(line == d for d in kept) for line in eds if not line.startswith(("FileName=", "Description=")))


def test_all_writes_one_dcf_per_node_on_every_channel(tmp_path, capsys):
    scene = load_scene("two_buses_200")
    assert main(["dcf", "--scene", "two_buses_200", "--all", "-o", str(tmp_path / "out")]) == 0
    files = sorted((tmp_path / "out").iterdir())
    assert len(files) == scene.n == len({f.name for f in files})
    assert capsys.readouterr().out == f"{scene.n} DCFs of scene 'two_buses_200' written to {tmp_path / 'out'}\n"
    for index in (0, scene.n - 1):  # one of each channel
        t = scene.taxels[index]
        path = tmp_path / "out" / file_name(scene, index)
        check_dcf(path, scene, index)
        assert f"NetNumber={t.channel + 1}\nNetworkName={scene.bus.channels[t.channel]}\n" in path.read_text()
    assert {scene.taxels[i].channel for i in (0, scene.n - 1)} == {0, 1}


def test_node_of_another_channel_and_stdout(tmp_path, capsys):
    scene = load_scene("two_buses_200")
    index = next(i for i, t in enumerate(scene.taxels) if t.channel == 1)
    t = scene.taxels[index]
    assert main(["dcf", "--scene", "two_buses_200", "--node", f"1:{t.node_id}", "-o", "-"]) == 0
    text = capsys.readouterr().out
    assert text == dcf_text(scene, index, eds_path().read_text(), file_name(scene, index))
    (tmp_path / "x.dcf").write_text(text)
    check_dcf(tmp_path / "x.dcf", scene, index)


def test_raw_mode_and_other_scenes_differ_where_the_configuration_does():
    decision, raw = load_scene("matrix57"), load_scene("matrix57_raw")
    eds = eds_path().read_text()
    a, b = dcf_text(decision, 0, eds), dcf_text(raw, 0, eds)
    cob = re.compile(r"\[1800sub1\][^\[]*ParameterValue=(0x[0-9A-F]+)")
    assert int(cob.search(a).group(1), 16) & 0x80000000 == 0           # TPDO1 valid: decisions
    assert int(cob.search(b).group(1), 16) & 0x80000000 == 0x80000000  # raw mode: TPDO1 invalid


def test_eds_tools_within_their_documented_dcf_limits(tmp_path):
    """eds-utils reads the DCF and only reports the ParameterValue entries it does not know;
    objdictgen refuses [DeviceComissioning] and loads the rest."""
    from eds_utils.core.file_io.read_eds import read_eds

    scene = load_scene("matrix57")
    path = tmp_path / "n.dcf"
    path.write_text(dcf_text(scene, 0, eds_path().read_text(), "n.dcf"))
    _, errors = read_eds(str(path))
    assert errors and all(re.fullmatch(r'AUTO-FIXED: Unknown entry "ParameterValue" in \[\w+\]', e) for e in errors)
    run = subprocess.run([sys.executable, "-m", "objdictgen", "list", str(path)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "Section '[DeviceComissioning]' is unrecognized" in run.stdout + run.stderr
    stripped = tmp_path / "nc.dcf"
    stripped.write_text(re.sub(r"\[DeviceComissioning\].*?\n\n", "", path.read_text(), flags=re.S))
    run = subprocess.run([sys.executable, "-m", "objdictgen", "list", str(stripped)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "0x2001" in run.stdout, run


@pytest.mark.parametrize("argv, message", [
    (["--node", "99", "-o", "x.dcf"], "--node '99': no node 99 on channel 0 (use C:N for another channel) of scene 'matrix57'"),
    (["--node", "3:1", "-o", "x.dcf"], "--node '3:1': no node 1 on channel 3 of scene 'matrix57'"),
    (["--node", "a", "-o", "x.dcf"], "--node 'a': expected a node-ID N or C:N (scene channel C)"),
    (["--all", "-o", "afile"], "-o 'afile': not a directory (--all writes one DCF per node)"),
    (["--node", "17", "-o", "nodir/x.dcf"], "-o 'nodir/x.dcf': cannot write: No such file or directory"),
])
def test_bad_input_one_line_exit_2(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    assert main(["dcf", "--scene", "matrix57"] + argv) == 2
    err = capsys.readouterr().err
    assert err == f"fusion-center dcf: error: {message}\n"
    assert not (tmp_path / "x.dcf").exists()


@pytest.mark.parametrize("argv", [["--scene", "matrix57", "-o", "x"], ["--scene", "matrix57", "--node", "1"],
                                  ["--scene", "matrix57", "--node", "1", "--all", "-o", "x"],
                                  ["--node", "1", "-o", "x"]])
def test_usage_errors_exit_2(argv, tmp_path, capsys):
    run = run_cli(capsys, "dcf", *argv, cwd=tmp_path)  # main() in this process (tests/cli_inprocess.py)
    assert run.returncode == 2 and run.stdout == "" and len(run.stderr.splitlines()) == 1, run


def test_unknown_scene_exit_2(capsys):
    assert main(["dcf", "--scene", "no-such-scene", "--all", "-o", "x"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fusion-center dcf: error:") and err.count("\n") == 1
