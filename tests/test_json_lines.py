"""The one reader of JSON-lines files (taxel_net.json_lines.iter_log): the decision log of ``plot``
and ``export``, node-sim's ``--truth-log``. Every bad line is one UsageError naming the file, the
line and what is wrong; what came before it was read."""

import json

import pytest

from taxel_net.errors import UsageError
from taxel_net.json_lines import iter_log


def write(tmp_path, content) -> str:
    path = tmp_path / "log.jsonl"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8")
    return str(path)


def error_of(path, **kw) -> tuple[list, str]:
    """(the values read before the error, the error's text)."""
    seen = []
    with pytest.raises(UsageError) as err:
        for number, value in iter_log(path, **kw):
            seen.append((number, value))
    text = str(err.value)
    assert "\n" not in text and repr(path) in text, text
    return seen, text


def test_values_with_their_line_numbers_blank_lines_counted(tmp_path):
    path = write(tmp_path, '{"cycle": 0}\n\n  \n{"cycle": 1, "t": 0.5}\r\n{"cycle": 2}')
    assert list(iter_log(path)) == [(1, {"cycle": 0}), (4, {"cycle": 1, "t": 0.5}), (5, {"cycle": 2})]


def test_bad_json_in_the_middle_names_its_line_after_the_lines_before(tmp_path):
    path = write(tmp_path, '{"cycle": 0}\n{"cycle": 1}\n{"cycle": 2,, "t": 0}\n{"cycle": 3}\n')
    seen, text = error_of(path)
    assert seen == [(1, {"cycle": 0}), (2, {"cycle": 1})]
    # the second comma: '{"cycle": 2,' is 12 characters
    assert f"decision log {path!r}, line 3: not JSON (" in text and text.endswith("at column 13)")


def test_a_cut_last_line_is_refused_naming_it(tmp_path):
    """A run killed mid-write leaves a last line without its newline and its end: no caller reads
    one today (a record cut short is not a record), so it is one error naming that line."""
    whole = json.dumps({"cycle": 1, "t": 0.01, "decision": "H1"})
    path = write(tmp_path, '{"cycle": 0}\n' + whole[:len(whole) // 2])
    seen, text = error_of(path)
    assert seen == [(1, {"cycle": 0})] and ", line 2: not JSON (" in text


def test_an_empty_file_yields_nothing(tmp_path):
    assert list(iter_log(write(tmp_path, ""))) == []
    assert list(iter_log(write(tmp_path, "\n \n\t\n"))) == []


@pytest.mark.parametrize("line", ["[1, 2]", "3", '"text"', "null", "true"])
def test_a_line_that_is_not_an_object(tmp_path, line):
    seen, text = error_of(write(tmp_path, '{"cycle": 0}\n' + line + "\n"))
    assert seen == [(1, {"cycle": 0})] and text.endswith(", line 2: not a JSON object")


def test_the_callers_check_and_wording(tmp_path):
    path = write(tmp_path, '{"cycle": 0}\n{"cycle": "x"}\n')
    _, text = error_of(path, label="--truth-log",
                       check=lambda v: None if isinstance(v.get("cycle"), int) else f"cycle {v['cycle']!r}")
    assert text == f"--truth-log {path!r}, line 2: cycle 'x'"
    _, text = error_of(write(tmp_path, "{oops\n"), not_json="not a record ({why}); see the docs")
    assert ", line 1: not a record (" in text and text.endswith("); see the docs")


def test_nan_only_where_allowed(tmp_path):
    path = write(tmp_path, '{"x": NaN}\n{"x": -Infinity}\n')
    values = [v["x"] for _, v in iter_log(path)]
    assert values[0] != values[0] and values[1] == float("-inf")
    _, text = error_of(path, allow_nan=False)
    assert text.endswith(", line 1: not JSON (NaN is not JSON)")


def test_a_byte_that_is_not_utf8_names_its_line_and_column(tmp_path):
    path = write(tmp_path, b'{"a": 1}\n{"b": "\xff"}\n')
    seen, text = error_of(path)
    assert seen == [(1, {"a": 1})]
    assert text == f"decision log {path!r}: not a UTF-8 text file (byte 0xFF in line 2, column 8)"


def test_nesting_too_deep_is_a_bad_line_not_a_crash(tmp_path):
    _, text = error_of(write(tmp_path, '{"a": 1}\n' + "[" * 200_000 + "\n"))
    assert text.endswith(", line 2: not JSON (nested too deeply)")


def test_a_file_that_cannot_be_read(tmp_path):
    _, text = error_of(str(tmp_path / "nope.jsonl"))
    assert text.endswith(": cannot be read: No such file or directory")
    _, text = error_of(str(tmp_path))
    assert ": cannot be read: " in text


# ---------------------------------------------------------------------------- fc.read_records on it

def test_read_records_reads_what_the_writer_wrote(tmp_path):
    from fusion_center import read_records
    from fusion_center.service.records import RecordWriter

    records = [{"cycle": 0, "decision": "H0", "t": 0.25, "area": None}, {"cycle": 1, "decision": "H1", "x": [1, 2]}]
    path = tmp_path / "log.jsonl"
    with RecordWriter(path) as writer:
        for record in records:
            writer.write(record)
    with open(path, "a", encoding="utf-8") as f:
        f.write("\n  \n")  # blank lines are no records
    assert read_records(path) == records


@pytest.mark.parametrize("content, words", [
    ('{"cycle": 0}\n{"cycle": 1,, "t": 0}\n', ", line 2: not JSON (Expecting property name"),
    ('{"cycle": 0}\n[1, 2]\n', ", line 2: not a JSON object"),
    ('{"cycle": 0}\n3\n', ", line 2: not a JSON object"),
    ('{"cycle": 0}\n{"cycle": 1, "t"', ", line 2: not JSON"),
    (b'{"cycle": 0}\n{"s": "caf\xe9"}\n', "(byte 0xE9 in line 2, column 11)"),
])
def test_read_records_bad_input_is_one_line_value_error_naming_file_and_line(tmp_path, content, words):
    """fc.read_records raises ValueError on a bad log (its contract), now one line naming the file
    and the line; a line that is a JSON value but no object was returned as a record before."""
    from fusion_center import read_records

    path = write(tmp_path, content)
    with pytest.raises(ValueError) as err:
        read_records(path)
    text = str(err.value)
    assert not isinstance(err.value, UsageError)
    assert "\n" not in text and repr(path) in text and words in text, text


def test_read_records_of_a_file_that_cannot_be_read_raises_the_os_error(tmp_path):
    from fusion_center import read_records

    with pytest.raises(FileNotFoundError):
        read_records(tmp_path / "nope.jsonl")
    with pytest.raises(IsADirectoryError):
        read_records(tmp_path)


def test_node_sims_truth_log_leaves_a_bad_line_out_and_says_so(tmp_path, capsys):
    """node-sim's --truth-log writes through the decision log's writer: a record it cannot write
    (NaN: not JSON, the reader refuses it) is left out, said once; the file stays readable."""
    from node_sim.cli import TruthLog, _truth_line
    from taxel_net.json_lines import JsonLinesWriter

    path = tmp_path / "truth.jsonl"
    log = TruthLog(str(path), JsonLinesWriter(path, _truth_line, option="--truth-log"))
    for k, normal in enumerate([1.0, float("nan"), 2.0, float("nan")]):
        log.write({"cycle": k, "normal_n": normal})
    log.close()
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and "the line is left out" in err[0], err
    assert err[1] == (f"node-sim: --truth-log {str(path)!r}: 2 records left out, not encodable (the first at cycle 1: "
                      "ValueError: Out of range float values are not JSON compliant); 2 records written (the file "
                      "is incomplete)")
    assert [v["cycle"] for _, v in iter_log(path, "--truth-log", allow_nan=False)] == [0, 2]


def test_an_endless_line_is_refused_once_it_is_longer_than_any_record(monkeypatch, tmp_path):
    """/dev/zero (or a file without newlines) is one endless line: read LINE_MAX bytes at a time
    and refused in one line - it was read whole, memory growing without bound (2026-11-30, stop 32)."""
    from taxel_net import json_lines
    from taxel_net.errors import UsageError

    monkeypatch.setattr(json_lines, "LINE_MAX", 2**20)
    for path in ("/dev/zero", tmp_path / "no-newline.jsonl"):
        if path != "/dev/zero":
            path.write_bytes(b'{"cycle": 0}\n' + b" " * (2**20 + 10))
        with pytest.raises(UsageError, match=r"line \d: longer than 1 MiB"):
            list(json_lines.iter_log(path, "--truth-log"))
    ok = tmp_path / "ok.jsonl"
    ok.write_bytes(b'{"cycle": 0, "x": "' + b"a" * (2**20 - 40) + b'"}\n')   # just under the bound: read
    assert [v["cycle"] for _, v in json_lines.iter_log(ok)] == [0]
