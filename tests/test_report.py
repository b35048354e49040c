"""fusion-center report on a small scene with few trials: every promised file, the keys of
report.json, valid PNGs, and the stage plan recorded."""

from __future__ import annotations

import json

import pytest

from fusion_center import cli
from fusion_center.commands import report
from fusion_center.report.build import PNG_FILES

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def gripper_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    assert cli.main(["report", "--scene", "scenes/gripper18.toml", "--out", str(out), "--trials", "2000",
                     "--seed", "3", "--bitrate", "500k,1000000"]) == 0
    return out


def test_every_file_written_and_png_valid(gripper_report):
    for name in ("report.json", *PNG_FILES):
        assert (gripper_report / name).stat().st_size > 0
    for name in PNG_FILES:
        head = (gripper_report / name).read_bytes()[:8]
        assert head == PNG_SIGNATURE, name


def test_report_json_keys(gripper_report):
    data = json.loads((gripper_report / "report.json").read_text())
    for key in ("stage_plan", "rules", "bandwidth", "cpu_time_per_decision_s", "error_vs_runtime", "roc",
                "achieved_vs_requested", "work_precision", "taxel_map", "files", "thresholds"):
        assert key in data, key
    assert data["trials_per_hypothesis"] == 2000
    assert set(data["bandwidth"]["modes"]) == {"raw", "decision_sync", "decision_event"}
    rules_in = {p["rule"] for p in data["error_vs_runtime"]}
    # gripper18 runs preferential and k-of-n; the centralised raw tests are always there (sigma > 0)
    assert {"preferential", "k-of-n", "centralised_known", "centralised_glrt", "centralised_bayes"} <= rules_in
    for p in data["error_vs_runtime"]:
        lo, hi = p["total_error"]["ci95"]
        assert lo <= p["total_error"]["estimate"] <= hi
        assert p["cpu_time_per_decision_us"] > 0 and p["bus_time_per_cycle_ms"] > 0
        assert p["mode"] == ("raw" if p["rule"].startswith("centralised") else "decision_sync")
    kofn = data["rules"]["k-of-n"]
    assert kofn["pf"]["exact"] is not None and kofn["pd"]["exact"] is not None
    for row in data["work_precision"]:
        assert row["relative_error"] < 1e-10


def test_stage_plan_recorded(gripper_report):
    plan = json.loads((gripper_report / "report.json").read_text())["stage_plan"]
    assert plan["mode"] == "decision" and plan["run"] == ["fusion"]
    assert plan["skipped"]["forces"].startswith("forces: decision mode carries only u_i")
    assert plan["skipped"]["area"] == "not requested in [outputs] stages"
    assert plan["rules_run"] == ["preferential", "k-of-n"]
    assert plan["rules_skipped"]["llr"] == "not requested in [fusion] rules"
    data = json.loads((gripper_report / "report.json").read_text())
    assert data["stages_skipped"] == plan["skipped"]
    assert data["rules_skipped"]["llr"] == "not requested in [fusion] rules"
    assert not any(name.startswith("centralised") for name in data["rules_skipped"])


def test_several_bitrates(gripper_report):
    data = json.loads((gripper_report / "report.json").read_text())
    assert list(data["bandwidth_by_bitrate"]) == ["500000", "1000000"]
    assert data["bandwidth"]["bitrate"] == 500000
    for p in data["error_vs_runtime"]:
        by = p["bus_time_per_cycle_ms_by_bitrate"]
        # the same bits on the wire: bus time is inversely proportional to the bit rate
        assert by["500000"] == pytest.approx(2 * by["1000000"], rel=1e-12)
        assert by["500000"] == p["bus_time_per_cycle_ms"]


@pytest.mark.parametrize("text,expected", [("125000,500k,1M", [125000, 500000, 1000000]), ("250k", [250000])])
def test_parse_bitrates(text, expected):
    assert report.parse_bitrates(text) == expected


def test_bad_bitrate_exits_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["report", "--scene", "scenes/gripper18.toml", "--out", str(tmp_path), "--bitrate", "2M"])
    assert exc.value.code == 2
    assert "2M" in capsys.readouterr().err


def test_bad_trials_exit_2(tmp_path, capsys):
    assert cli.main(["report", "--scene", "scenes/gripper18.toml", "--out", str(tmp_path), "--trials", "5"]) == 2
    assert "trials=5" in capsys.readouterr().err
