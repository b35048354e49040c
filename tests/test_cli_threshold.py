"""``fusion-center threshold``: JSON contract, readable table, one-line errors with exit 2."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from fusion_center.cli import main

ROOT = Path(__file__).resolve().parents[1]


def _json(capsys, *argv):
    assert main(["threshold", *argv, "--json"]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1  # one JSON object on one line
    return json.loads(out)


def test_additive_json(capsys):
    res = _json(capsys, "--rule", "additive", "--n", "57", "--xi", "0.003", "--alpha", "0.03")
    assert res["rule"] == "additive" and res["n"] == 57 and res["xi"] == 0.003 and res["alpha"] == 0.03
    assert len(res["thresholds"]) == 1 and 50.0 < res["thresholds"][0] < 50.3
    # U_G = 2j - n of the smallest accepted present count is >= lambda, one fewer is below
    j = res["present_counts"][0]
    assert 2 * j - 57 >= res["thresholds"][0] > 2 * (j - 1) - 57


def test_additive_01_tuple_and_no_root(capsys):
    res = _json(capsys, "--rule", "additive", "--n", "57", "--xi", "0.003", "--alpha", "0.99", "--tuple", "01")
    assert res["tuple"] == "01" and res["thresholds"] == [] and res["present_counts"] == []


def test_multiplicative_json_null_for_nonpositive_lambda(capsys):
    res = _json(capsys, "--rule", "multiplicative", "--n", "57", "--xi", "0.003", "--beta", "0.83")
    assert set(res) >= {"scaled_thresholds", "ln_thresholds", "present_counts", "beta"}
    t = res["scaled_thresholds"][0]
    assert t < 0 and res["ln_thresholds"] == [None] and res["present_counts"] == [0]
    res = _json(capsys, "--rule", "multiplicative", "--n", "1000000", "--xi", "0.003", "--beta", "0.05")
    t, ln_lam = res["scaled_thresholds"][0], res["ln_thresholds"][0]
    assert 0 < t < 1 and ln_lam == pytest.approx(1e6 + math.log(t), rel=1e-15)


def test_preferential_json_chapter_case(capsys):
    res = _json(capsys, "--rule", "preferential", "--n", "18", "--xi", "0.003", "--alpha", "0.48", "--p", "1", "--q", "1")
    assert res["g_max"] == 68 and res["band_width"] == pytest.approx(8.16)
    assert res["threshold_mean"] == pytest.approx(27.036, abs=1e-3)
    assert res["threshold_initial"] == pytest.approx(res["threshold_mean"] - 4.08)
    assert res["threshold_final"] == pytest.approx(res["threshold_mean"] + 4.08)
    assert {"p", "q", "present_count"} <= set(res)


def test_preferential_second_root_in_json_and_table(capsys):
    # a = 3 alpha/(1 - xi) = 2.16: eq 18 has roots y = (-1 +- sqrt(9 - 4a))/2 = (-1 +- 0.6)/2, g = 68
    argv = ["--rule", "preferential", "--n", "18", "--xi", "0.3", "--alpha", "0.504"]
    res = _json(capsys, *argv)
    assert res["threshold_means"] == pytest.approx([-0.8 * 68, -0.2 * 68], rel=1e-12)
    assert res["threshold_mean"] == res["threshold_means"][-1]
    assert main(["threshold", *argv]) == 0
    assert "threshold_means" in capsys.readouterr().out


def test_table_output(capsys):
    assert main(["threshold", "--rule", "preferential", "--n", "18", "--xi", "0.003", "--alpha", "0.48"]) == 0
    out = capsys.readouterr().out
    assert "threshold_mean" in out and "27.036" in out and "8.16" in out
    assert main(["threshold", "--rule", "multiplicative", "--n", "57", "--xi", "0.5", "--beta", "0.9"]) == 0
    assert "no root" in capsys.readouterr().out


@pytest.mark.parametrize("argv,words", [
    (["--rule", "additive", "--n", "57", "--xi", "0.003"], ["--alpha"]),
    (["--rule", "additive", "--n", "57", "--xi", "0.003", "--beta", "0.1"], ["--beta"]),
    (["--rule", "multiplicative", "--n", "57", "--xi", "0.003", "--alpha", "0.1"], ["--beta"]),
    (["--rule", "multiplicative", "--n", "57", "--xi", "0.003", "--beta", "0.1", "--tuple", "01"], ["pm1"]),
    (["--rule", "additive", "--n", "57", "--xi", "0.003", "--alpha", "0.1", "--p", "1"], ["--p"]),
    (["--rule", "additive", "--n", "0", "--xi", "0.003", "--alpha", "0.1"], ["n=", ">= 1"]),
    (["--rule", "additive", "--n", "abc", "--xi", "0.003", "--alpha", "0.1"], ["n=", "'abc'"]),
    (["--rule", "additive", "--n", "57", "--xi", "1.5", "--alpha", "0.1"], ["xi='1.5'", "(0, 1)"]),
    (["--rule", "additive", "--n", "57", "--xi", "nan", "--alpha", "0.1"], ["xi=", "(0, 1)"]),
    (["--rule", "additive", "--n", "57", "--xi", "0.1", "--alpha", "1"], ["alpha='1'", "(0, 1)"]),
    (["--rule", "multiplicative", "--n", "57", "--xi", "0.1", "--beta", "-2"], ["beta='-2'", "(0, 1)"]),
    (["--rule", "preferential", "--n", "18", "--xi", "0.1", "--alpha", "0.3", "--p", "3"], ["p='3'", "[0, 2]"]),
    (["--rule", "preferential", "--n", "18", "--xi", "0.1", "--alpha", "0.3", "--q", "inf"], ["q=", "[0, 2]"]),
    (["--rule", "additive", "--n", "57", "--xi", "0.1", "--alpha", "0.1", "--beta", "0.1"], ["not allowed"]),
    (["--rule", "bogus", "--n", "57", "--xi", "0.1", "--alpha", "0.1"], ["--rule"]),
    # the value is quoted as typed, not as parsed (1e-400 parses to 0.0, 1_0 to 10.0)
    (["--rule", "additive", "--n", "57", "--xi", "0.1", "--alpha", "1e-400"], ["alpha='1e-400'", "(0, 1)"]),
    (["--rule", "additive", "--n", "57", "--xi", "0.1", "--alpha", "1_0"], ["alpha='1_0'", "(0, 1)"]),
    (["--rule", "additive", "--n", "57", "--xi", "inf", "--alpha", "0.1"], ["xi='inf'", "(0, 1)"]),
    (["--rule", "additive", "--n", "57.5", "--xi", "0.1", "--alpha", "0.1"], ["n='57.5'", "integer"]),
    (["--rule", "additive", "--n", "1e400", "--xi", "0.1", "--alpha", "0.1"], ["n='1e400'", "integer"]),
    (["--rule", "additive", "--n", "", "--xi", "0.1", "--alpha", "0.1"], ["n=''", "integer"]),
    (["--rule", "preferential", "--n", "18", "--xi", "0.1", "--alpha", "0.3", "--p", "nan"], ["p='nan'", "[0, 2]"]),
    (["--rule", "preferential", "--n", "18", "--xi", "0.1", "--alpha", "0.3", "--p", "2.5"], ["p='2.5'", "[0, 2]"]),
    (["--rule", "preferential", "--n", "18", "--xi", "0.1", "--alpha", "0.3", "--tuple", "foo"], ["--tuple", "foo"]),
    (["--rule", "preferential", "--n", "18", "--xi", "0.1", "--alpha", "0.3", "--alpha", "x"], ["alpha='x'"]),
])
def test_bad_input_one_line_exit_2(capsys, argv, words):
    try:
        rc = main(["threshold", *argv])
    except SystemExit as exc:  # argparse's own errors
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    for word in words:
        assert word in err


def test_console_script_subprocess():
    exe = ROOT / ".venv" / "bin" / "fusion-center"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "fusion_center.cli"]
    ok = subprocess.run([*cmd, "threshold", "--rule", "additive", "--n", "57", "--xi", "0.003",
                         "--alpha", "0.473", "--json"], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
    res = json.loads(ok.stdout)
    assert len(res["thresholds"]) == 1 and -51.1 < res["thresholds"][0] < -50.8
    bad = subprocess.run([*cmd, "threshold", "--rule", "additive", "--n", "57", "--xi", "2", "--alpha", "0.1"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "xi=" in bad.stderr
