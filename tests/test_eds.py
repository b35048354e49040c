"""The taxel node EDS: loads with canopen, has the CiA 301/404 layout the brief fixes, survives
canopen's export/import round trip, and pins canopen 2.4.1's known losses (so these tests
fail, and document it, if canopen changes behaviour)."""

from __future__ import annotations

import configparser
import subprocess
import sys
import io
import math

import canopen
import pytest
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

from taxel_net.errors import ParameterError
from node_sim import od as odx
from taxel_net.resources import gripper_eds_path

EDS = str(odx.EDS_PATH)


def all_variables(od):
    for index in od:
        obj = od[index]
        if isinstance(obj, ODVariable):
            yield obj
        else:
            for sub in obj.subindices:
                yield obj[sub]


@pytest.mark.parametrize("node_id", [1, 5, 127])
def test_loads_with_node_relative_cob_ids(node_id):
    od = canopen.import_od(EDS, node_id)
    assert od[0x1800][1].default == 0x40000180 + node_id      # bit 30: no RTR
    assert od[0x1801][1].default == 0xC0000280 + node_id      # TPDO2 disabled (bit 31), no RTR
    assert od[0x1014].default == 0x80 + node_id
    assert od[0x1200][1].default == 0x600 + node_id and od[0x1200][2].default == 0x580 + node_id


def test_communication_objects():
    od = canopen.import_od(EDS, 5)
    assert od[0x1000].default == 0 and od[0x1000].access_type == "ro"   # no device profile (docs/node-twins.md)
    assert od[0x1001].data_type == datatypes.UNSIGNED8 and od[0x1001].access_type == "ro"
    assert isinstance(od[0x1003], ODArray) and od[0x1003][0].data_type == datatypes.UNSIGNED8
    assert len(od[0x1003].subindices) == 9 and od[0x1003][8].data_type == datatypes.UNSIGNED32
    assert od[0x1005].default == 0x80
    assert od[0x1017].data_type == datatypes.UNSIGNED16
    assert isinstance(od[0x1018], ODRecord) and all(od[0x1018][s].access_type == "ro" for s in range(1, 5))
    for comm in (0x1800, 0x1801):
        assert od[comm][2].default == 1                         # synchronous, every SYNC
        assert sorted(od[comm].subindices) == [0, 1, 2, 3, 5, 6]
        assert od[comm][3].data_type == datatypes.UNSIGNED16 and od[comm][5].data_type == datatypes.UNSIGNED16


def test_manufacturer_and_cia404_objects():
    od = canopen.import_od(EDS, 5)
    u = od[0x2000]
    assert (u.data_type, u.access_type, u.pdo_mappable, u.default) == (datatypes.INTEGER8, "ro", True, -1)
    det = od[0x2001]
    assert isinstance(det, ODRecord)
    assert [det[s].data_type for s in range(1, 6)] == [datatypes.REAL32, datatypes.REAL32, datatypes.UNSIGNED8,
                                                       datatypes.REAL32, datatypes.REAL32]
    assert det[3].default == 1 and (det[3].min, det[3].max) == (1, 6)   # kinds R..IR, default R
    for index in (0x6126, 0x6127, 0x6130):                      # CiA 404: arrays, sub 1 = channel 1
        assert isinstance(od[index], ODArray) and od[index][0].default == 1
        assert od[index][1].data_type == datatypes.REAL32
    assert od[0x6130][1].access_type == "ro" and od[0x6130][1].pdo_mappable
    assert od[0x6126][1].access_type == "rw" and od[0x6127][1].access_type == "rw"


def test_default_mappings():
    od = canopen.import_od(EDS, 5)
    # mapping entry = index << 16 | subindex << 8 | length in bits
    assert od[0x1A00][0].default == 1 and od[0x1A00][1].default == (0x2000 << 16) | (0 << 8) | 8
    assert od[0x1A01][0].default == 1 and od[0x1A01][1].default == (0x6130 << 16) | (1 << 8) | 32


def test_export_import_round_trip_keeps_what_canopen_keeps(tmp_path):
    od = canopen.import_od(EDS, 7)
    out = tmp_path / "round.eds"
    canopen.export_od(od, str(out))
    back = canopen.import_od(str(out), 7)
    assert sorted(back) == sorted(od)
    pairs = 0
    for v in all_variables(od):
        w = back[v.index] if isinstance(back[v.index], ODVariable) else back[v.index][v.subindex]
        for attr in ("name", "data_type", "access_type", "pdo_mappable", "default", "min", "max"):
            a, b = getattr(v, attr), getattr(w, attr)
            assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), (hex(v.index), v.subindex, attr)
        pairs += 1
    assert pairs >= 60
    assert back.device_information.nr_of_TXPDO == 2


def test_real32_limits_written_as_integers_survive_import():
    """canopen 2.4.1 drops a decimal REAL32 limit ("0.0") and objdictgen refuses one, so the
    only REAL32 limit of the EDS (ζ >= 0) is written as an integer, which canopen keeps; full
    scale > 0 (not an integer bound) is the node's own check."""
    parser = configparser.RawConfigParser()
    parser.optionxform = str
    parser.read(EDS)
    real32 = [sec for sec in parser.sections() if parser.get(sec, "DataType", fallback="") == "0x0008"]
    for sec in real32:
        for key in ("LowLimit", "HighLimit"):
            if parser.has_option(sec, key):
                int(parser.get(sec, key), 0)                     # integer syntax only
    assert parser.get("2001sub1", "LowLimit") == "0"
    od = canopen.import_od(EDS, 5)
    assert od[0x2001][1].min == 0                                # kept by canopen
    assert od[0x2000].min == -1 and od[0x2000].max == 1          # integer limits survive
    # the node reads the REAL32 limits itself, from the same file
    limits = odx.real_limits()
    assert limits[(0x2001, 1)] == (0.0, math.inf)
    assert (0x2002, 1) not in limits   # full scale > 0: the node's own check (no EDS limit)


def test_known_loss_negative_default_exported_as_0x_minus(tmp_path):
    od = canopen.import_od(EDS, 5)
    u = od[0x2000]
    assert u.default_raw == "-1"                  # imported from the EDS text: exported verbatim
    u.default_raw = None                          # a default set in code, not read from an EDS
    buf = io.StringIO()
    canopen.export_od(od, buf, doc_type="eds")
    text = buf.getvalue()
    section = text[text.index("[2000]"):].split("\n\n")[0]
    assert "DefaultValue=0x-1" in section
    out = tmp_path / "lossy.eds"
    out.write_text(text)
    assert canopen.import_od(str(out), 5)[0x2000].default is None   # unreadable on re-import


def test_missing_eds_is_a_parameter_error(tmp_path):
    with pytest.raises(ParameterError, match="eds"):
        odx.load_od(3, tmp_path / "nope.eds")
    with pytest.raises(ParameterError, match="node_id"):
        odx.load_od(128)


# ------------------------------------------------------------------------ other EDS tools

# the EDS files the tools below read: the taxel node's and the gripper drive's (issue 22), each with
# two objects ``odg list`` must show
TOOL_EDS = [pytest.param(EDS, ("0x1019", "0x2001"), id="taxel_node"),
            pytest.param(str(gripper_eds_path()), ("0x6041", "0x2100"), id="gripper_drive")]


@pytest.mark.parametrize("eds, listed", TOOL_EDS)
def test_eds_utils_reads_and_validates_the_file_as_shipped(eds, listed):
    """eds-utils (PyPI ``eds-utils``): its reader finds no error and ``eds-validate`` exits 0
    with nothing to report (it splits sections on blank lines and entries on '=', so the file
    has no free comment block and no '=' inside a value)."""
    from eds_utils.core.file_io.read_eds import read_eds

    _, errors = read_eds(str(eds))
    assert errors == []
    run = subprocess.run([sys.executable, "-c", "from eds_utils.eds_validate import eds_validate; eds_validate()",
                          str(eds)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "" and run.stderr == "", run


@pytest.mark.parametrize("eds, listed", TOOL_EDS)
def test_objdictgen_loads_the_file_as_shipped(eds, listed):
    """objdictgen (CanFestival's ``odg``): loads the EDS with every object canopen sees."""
    from objdictgen.node import Node

    node = Node.LoadFile(str(eds))
    od = canopen.import_od(str(eds), 1)
    assert sorted(node.GetIndexes()) == sorted(obj.index for obj in od.values())
    run = subprocess.run([sys.executable, "-m", "objdictgen", "list", str(eds)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and all(token in run.stdout for token in listed), run
