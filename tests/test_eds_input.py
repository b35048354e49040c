"""A user's EDS (node-sim --eds, fusion-center dcf --eds, the centre's EDS): any malformed file -
cut anywhere, a mandatory key missing, a value of the wrong kind, binary junk, empty - is one
line naming the file and what is missing or wrong (exit 2), never a traceback
(taxel_net/eds_file.py, node_sim.od.check_eds). Before: node-sim printed canopen's 26-line
traceback (configparser.ParsingError / NoOptionError inside rig.start) and exited 1."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from node_sim import od as odx
from taxel_net.eds_file import check_objects, import_eds
from taxel_net.errors import EdsError, ParameterError
from taxel_net.resources import eds_path, patch_eds_path

ROOT = Path(__file__).resolve().parent.parent
MATRIX = ROOT / "scenes" / "matrix57.toml"
SOURCE = eds_path().read_bytes()
CONTENT_END = len(SOURCE.rstrip())  # a cut at or after it keeps every key and value
LINE_ENDS = [i + 1 for i, b in enumerate(SOURCE) if b == ord("\n")]


def assert_one_line(exc: BaseException, path: Path, *needles: str) -> None:
    message = str(exc)
    assert "\n" not in message and str(path) in message, message
    for needle in needles:
        assert needle in message, message


def cut_file(tmp_path: Path, length: int) -> Path:
    path = tmp_path / f"cut{length}.eds"
    path.write_bytes(SOURCE[:length])
    return path


def test_the_shipped_eds_files_pass():
    for path in (eds_path(), patch_eds_path()):
        od = import_eds(path, 1)
        check_objects(od, od, path, "itself")
    assert import_eds(eds_path())[0x1800][1].default is None  # $NODEID+0x180 needs a node-ID


# every line of the EDS cut at its end, in its middle and one byte into it: a cut file lacks at
# least its last section's remaining keys or the sections after it
@pytest.mark.parametrize("length", sorted({n for end in LINE_ENDS for n in (end, end - 2, end + 1)
                                           if 0 <= n < CONTENT_END})[::4])
def test_eds_cut_at_a_line_is_one_line(tmp_path, length):
    path = cut_file(tmp_path, length)
    with pytest.raises(EdsError) as info:
        odx.check_eds(path)
    assert_one_line(info.value, path)
    assert isinstance(info.value, ParameterError)  # the CLIs' exit 2


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(length=st.integers(min_value=0, max_value=CONTENT_END - 1))
def test_eds_cut_anywhere_is_one_line(tmp_path, length):
    path = cut_file(tmp_path, length)
    with pytest.raises(EdsError) as info:
        odx.check_eds(path)
    assert_one_line(info.value, path)


def test_eds_cut_after_its_content_loads(tmp_path):
    """The trailing newline alone cut: the same keys and values, loaded as the shipped file."""
    path = cut_file(tmp_path, CONTENT_END)
    assert odx.check_eds(path) == path
    assert odx.load_od(5, path)[0x1800][1].default == 0x40000185


def _edit(old: str, new: str, count: int = 1) -> bytes:
    text = SOURCE.decode()
    assert old in text
    return text.replace(old, new, count).encode()


@pytest.mark.parametrize("content, needles", [
    (b"", ["empty file"]),
    (b"\n \n", ["empty file"]),
    (bytes(range(256)) * 4, ["not a text file", "NUL byte at offset 0"]),
    (bytes(range(128, 256)) * 4, ["not a text file", "offset 0"]),
    (b"hello\nworld\n", ["line 1", "'hello'", "before any [section]"]),
    (b"[FileInfo]\nFileName=x.eds\n", ["no [DeviceInfo] section"]),
    (_edit("[DeviceInfo]", "[DeviceInfo2]"), ["no [DeviceInfo] section"]),
    (_edit("DataType=0x0008\n", ""), ["[2001sub1] has no DataType"]),
    (_edit("AccessType=ro\n", ""), ["[1000] has no AccessType"]),
    (_edit("DataType=0x0008", "DataType=real"), ["[2001sub1] DataType='real' is not a number"]),
    (_edit("DataType=0x0008", "DataType=0x0040"), ["[2001sub1] DataType='0x0040'", "CiA 301 basic data type"]),
    (_edit("DataType=0x0008", "DataType=0"), ["[2001sub1] DataType='0'", "CiA 301 basic data type"]),
    (_edit("DefaultValue=0.0", "DefaultValue=zero"), ["DefaultValue='zero' is not a REAL32 value"]),
    (_edit("DefaultValue=0\n", "DefaultValue=0x1FF\n"), ["[1001] DefaultValue='0x1FF' does not fit UNSIGNED8"]),
    (_edit("AccessType=ro", "AccessType=read"), ["[1000] AccessType='read'", "ro, wo, rw"]),
    (_edit("ObjectType=0x7", "ObjectType=0x3"), ["[1000] ObjectType='0x3'", "0x7 VAR"]),  # canopen left it out
    (_edit("ObjectType=0x7", "ObjectType=var"), ["[1000] ObjectType='var' is not a number"]),
    (_edit("PDOMapping=1", "PDOMapping=yes"), ["PDOMapping='yes' is not a number"]),
    (_edit("LowLimit=", "LowLimit=low"), ["LowLimit='low", "is not a"]),
    (_edit("BaudRate_500=1", "BaudRate_500=on"), ["[DeviceInfo] BaudRate_500='on' is not a number"]),
    (SOURCE + b"\n[1000]\nParameterName=again\n", ["section [1000] appears twice"]),
    (_edit("PDOMapping=0\n", "PDOMapping=0\nPDOMapping=0\n"), ["key PDOMapping appears twice in [1000]"]),
    (_edit("ParameterName=AI status 1\n", "ParameterName=AI status 1\nGarbage\n"), ["'Garbage' is not a Key=Value line"]),
])
def test_malformed_eds_is_one_line_naming_what(tmp_path, content, needles):
    path = tmp_path / "bad.eds"
    path.write_bytes(content)
    with pytest.raises(EdsError) as info:
        odx.check_eds(path)
    assert_one_line(info.value, path, *needles)


@pytest.mark.parametrize("old, new, needle", [
    ("[6150sub1]", "[6150subX]", "object 0x6150:1 is missing"),
    ("[2000]\n", "[2F00]\n", "object 0x2000 is missing"),
    ("DataType=0x0008", "DataType=0x0011", "object 0x2001:1 has DataType=0x0011 (REAL64), not 0x0008 (REAL32)"),
    ("PDOMapping=1", "PDOMapping=0", "PDOMapping=0, not 1"),
])
def test_eds_without_an_object_of_the_twin_is_one_line(tmp_path, old, new, needle):
    """A valid EDS that lacks an object the twin implements (or declares it otherwise): the twin
    would fail on it later, in a thread - refused at the start, naming the object."""
    path = tmp_path / "other.eds"
    path.write_bytes(_edit(old, new))
    import_eds(path, 1)  # a valid CiA 306 file
    with pytest.raises(EdsError) as info:
        odx.check_eds(path)
    assert_one_line(info.value, path, needle, "taxel_node.eds")


def test_eds_with_other_values_and_more_objects_loads(tmp_path):
    path = tmp_path / "mine.eds"
    path.write_bytes(_edit("[1017]\n", "[1017]\n") + b"\n[2FFF]\nParameterName=extra\nObjectType=0x7\n"
                     b"DataType=0x0007\nAccessType=rw\nDefaultValue=7\nPDOMapping=0\n")
    text = path.read_text()
    heartbeat = text.index("[1017]")
    default = text.index("DefaultValue=", heartbeat)
    end = text.index("\n", default)
    path.write_text(text[:default] + "DefaultValue=250" + text[end:])
    od = odx.load_od(3, path)
    assert od[0x1017].default == 250 and od[0x2FFF].default == 7


def test_a_cut_patch_eds_is_one_line(tmp_path):
    from node_sim.patch import load_patch_od

    source = patch_eds_path().read_bytes()
    path = tmp_path / "patch.eds"
    path.write_bytes(source[:len(source) // 2])
    with pytest.raises(EdsError) as info:
        load_patch_od(1, path)
    assert_one_line(info.value, path)


def run_cli(*args):
    return subprocess.run([sys.executable, "-c", *args], cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_node_sim_with_a_cut_eds_exits_2_with_one_line(tmp_path):
    path = cut_file(tmp_path, len(SOURCE) // 2)
    done = run_cli("import sys; from node_sim.cli import main; sys.exit(main())",
                   "--scene", str(MATRIX), "-i", "virtual", "--eds", str(path))
    assert done.returncode == 2, done.stderr[-3000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and "Traceback" not in done.stderr, done.stderr[-3000:]


def test_dcf_with_a_cut_eds_exits_2_with_one_line(tmp_path):
    path = cut_file(tmp_path, 5000)
    done = run_cli("import sys; from fusion_center.cli import main; sys.exit(main())",
                   "dcf", "--scene", str(MATRIX), "--node", "1", "-o", str(tmp_path / "n.dcf"), "--eds", str(path))
    assert done.returncode == 2, done.stderr[-3000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and "Traceback" not in done.stderr, done.stderr[-3000:]
