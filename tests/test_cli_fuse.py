"""``fusion-center fuse`` through fusion_center.cli.main, on the chapter's own examples."""

from __future__ import annotations

import json
import math

import mpmath
import pytest

from fusion_center.cli import main

@pytest.fixture(autouse=True, scope="module")
def _references_at_50_digits():
    """The mpmath references of this module at 50 digits, restored after it (not set at import:
    that leaked into whichever module ran next in the worker)."""
    with mpmath.workdps(50):
        yield

# sec. 6.2 / 6.3.1: 57 taxels, cells 5, 8, 18, 19, 20, 31, 33 present
PRESENT_57 = (5, 8, 18, 19, 20, 31, 33)
U_57 = ",".join("1" if i in PRESENT_57 else "-1" for i in range(1, 58))
# sec. 7.2: the printed {u_i} matrix of the gripper, read row-wise (absent: 4, 6, 10, 17, 18)
U_18 = [1, 1, 1, -1, 1, -1, 1, 1, 1, -1, 1, 1, 1, 1, 1, 1, -1, -1]


def fuse_json(capsys, *argv):
    rc = main(["fuse", *argv, "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 1
    return json.loads(lines[0])


def fuse_error(capsys, *argv):
    rc = main(["fuse", *argv])
    out, err = capsys.readouterr()
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err
    return lines[0]


def eq13_mpmath(u, n, xi):
    xi = mpmath.mpf(xi)
    r = (xi + 1) + mpmath.sqrt(xi * (xi + 2))
    return 0.5 * mpmath.exp(mpmath.log(r) / n * u) + (1 - 0.5 * r) / n * u


def test_additive_57_taxels(capsys):
    rec = fuse_json(capsys, "--rule", "additive", f"--u={U_57}", "--xi", "0.003")
    assert rec["U_G"] == -43 and rec["ln_U_G"] is None
    assert rec["n"] == 57 and rec["present_count"] == 7
    assert rec["rule"] == "additive" and rec["tuple"] == "pm1"
    # eq 13 at U_G = -43, n = 57, xi = 0.003 (printed 0.124835, see chapter-notes)
    assert rec["p_h1"] == pytest.approx(float(eq13_mpmath(-43, 57, 0.003)), rel=1e-12)
    assert rec["decision"] is None and rec["threshold"] is None  # no alpha: no threshold


def test_multiplicative_57_taxels(capsys):
    rec = fuse_json(capsys, "--rule", "multiplicative", "--u", U_57, "--xi", "0.003")
    assert rec["ln_U_G"] == -43
    assert rec["U_G"] == pytest.approx(math.exp(-43), rel=1e-15)
    assert rec["U_G"] == pytest.approx(2.11513e-19, rel=1e-5)  # printed in sec. 6.3.1
    # eqs 10-11: p = a exp(m U_G) with m, a from (e^-n, xi) and (e^n, 1): ~xi at U_G = e^-43
    n, xi = 57, mpmath.mpf("0.003")
    e_n = mpmath.e ** n
    m = e_n * mpmath.log(1 / xi) / (e_n**2 - 1)
    ln_a = -(e_n**2) * mpmath.log(1 / xi) / (e_n**2 - 1)
    ref = mpmath.exp(ln_a + m * mpmath.e ** (-43))
    assert rec["p_h1"] == pytest.approx(float(ref), rel=1e-12)


def test_gripper_18_preferential_u_g(capsys):
    u = ",".join(str(x) for x in U_18)
    rec = fuse_json(capsys, "--rule", "preferential", "--u", u, "--p", "1", "--q", "1")
    # eq 7 by hand on the printed {-1,+1} vector: 14 (the chapter prints 37)
    assert rec["U_G"] == 14
    assert rec["present_count"] == 13
    # the same decisions in the {0,1} tuple give the chapter's 37 (see chapter-notes)
    u01 = ",".join(str((x + 1) // 2) for x in U_18)
    rec01 = fuse_json(capsys, "--rule", "preferential", "--u", u01, "--tuple", "01", "--p", "1", "--q", "1")
    assert rec01["U_G"] == 37


def test_k_of_n_and_its_error_rates(capsys):
    rec = fuse_json(capsys, "--rule", "k-of-n", "--u", U_57, "--k", "7", "--pd", "0.995", "--pf", "0.003")
    assert rec["U_G"] == 1 and rec["decision"] == "H1" and rec["k"] == 7
    ref = mpmath.fsum(mpmath.binomial(57, j) * mpmath.mpf("0.003") ** j * mpmath.mpf("0.997") ** (57 - j) for j in range(7, 58))
    assert rec["p_false_alarm"] == pytest.approx(float(ref), rel=1e-11)
    rec = fuse_json(capsys, "--rule", "k-of-n", "--u", U_57, "--k", "8")
    assert rec["U_G"] == -1 and rec["decision"] == "H0"


def test_llr_and_np_rules(capsys):
    pm = [0.0015, 0.022, 0.030, 0.052]
    pf = [0.0005, 0.0023, 0.0010, 0.0002]
    pd = ",".join(str(1 - m) for m in pm)
    rec = fuse_json(capsys, "--rule", "llr", "--u", "1,-1,-1,-1", "--pd", pd, "--pf", ",".join(map(str, pf)))
    by_hand = (
        math.log(0.9985 / 0.0005) + math.log(0.022 / 0.9977) + math.log(0.030 / 0.9990) + math.log(0.052 / 0.9998)
    )
    assert rec["U_G"] == pytest.approx(by_hand, rel=1e-12)
    assert rec["decision"] == ("H1" if by_hand > 0 else "H0")
    rec = fuse_json(capsys, "--rule", "llr", "--u", "1,-1,-1,-1", "--pd", pd, "--pf", ",".join(map(str, pf)),
                    "--prior-h1", "0.2")
    assert rec["U_G"] == pytest.approx(by_hand + math.log(0.25), rel=1e-12)
    rec = fuse_json(capsys, "--rule", "np", "--u", "0,0,0,1", "--tuple", "01", "--pd", "0.9", "--pf", "0.1",
                    "--false-alarm", "0.05")
    # identical taxels, n = 4: P0(K >= 2) = 0.0523 > 0.05 >= P0(K >= 3) = 0.0037 -> boundary K = 2
    assert rec["count_threshold"] == 2
    assert rec["gamma"] == pytest.approx((0.05 - 0.0037) / 0.0486, rel=1e-10)
    assert rec["decision"] == "H0"  # K = 1 < 2
    assert rec["U_G"] == pytest.approx(math.log(9) + 3 * math.log(1 / 9), rel=1e-12)


def test_table_output(capsys):
    rc = main(["fuse", "--rule", "additive", "--u", U_57])
    out, _ = capsys.readouterr()
    assert rc == 0 and "U_G" in out and "-43" in out


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--rule", "additive", "--u", ""], "u=''"),
        (["--rule", "additive", "--u", "1,-1,0"], "u[2]=0"),
        (["--rule", "additive", "--u", "1,2", "--tuple", "01"], "u[1]=2"),
        (["--rule", "additive", "--u", "1,nan"], "u[1]='nan'"),
        (["--rule", "additive", "--u", "1,,1"], "u[1]=''"),
        (["--rule", "additive", "--u", "1,abc"], "u[1]='abc'"),
        (["--rule", "additive", "--u", "1,-1", "--tuple", "pm2"], "tuple='pm2'"),
        (["--rule", "additive", "--u", "1,-1", "--xi", "1"], "xi='1'"),
        (["--rule", "additive", "--u", "1,-1", "--xi", "nan"], "xi='nan'"),
        (["--rule", "additive", "--u", "1,-1", "--xi", "0.01", "--alpha", "0"], "alpha='0'"),
        (["--rule", "multiplicative", "--u", "1,-1", "--xi", "0.01", "--beta", "1.5"], "beta='1.5'"),
        (["--rule", "preferential", "--u", "1,-1", "--p", "2.5"], "p='2.5'"),
        (["--rule", "preferential", "--u", "1,-1", "--q", "-1"], "q='-1'"),
        (["--rule", "k-of-n", "--u", "1,-1"], "k=None"),
        (["--rule", "k-of-n", "--u", "1,-1", "--k", "3"], "k='3'"),
        (["--rule", "llr", "--u", "1,-1", "--pd", "0.9"], "pf=None"),
        (["--rule", "llr", "--u", "1,-1", "--pd", "0.9,1.0", "--pf", "0.1"], "pd[1]="),
        (["--rule", "np", "--u", "1,-1", "--pd", "0.9", "--pf", "0.1", "--false-alarm", "1"], "false_alarm='1'"),
        (["--rule", "additive", "--u", "1,-1", "--xi", "inf"], "xi='inf'"),
        (["--rule", "additive", "--u", "1,-1", "--xi", "1e-400"], "xi='1e-400'"),
        (["--rule", "additive", "--u", "1,inf"], "u[1]='inf'"),
        (["--rule", "additive", "--u", "1,-1", "--tuple", "foo"], "tuple='foo'"),
        (["--rule", "preferential", "--u", "1,-1", "--p", "nan"], "p='nan'"),
        (["--rule", "k-of-n", "--u", "1,-1", "--k", "1.5"], "k='1.5'"),
        (["--rule", "llr", "--u", "1,-1", "--pd", "0.9", "--pf", "0.1", "--prior-h1", "nan"], "prior_h1='nan'"),
        (["--rule", "np", "--u", "1,-1", "--pd", "0.9,0.8,0.7", "--pf", "0.1"], "pd='3 values'"),
    ],
)
def test_bad_input_exits_2_with_one_line(capsys, argv, fragment):
    line = fuse_error(capsys, *argv)
    assert fragment in line


def test_unknown_rule_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["fuse", "--rule", "bayes", "--u", "1"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--rule" in err[0]


# ------------------------------------------------------------------ HEBTEM thresholds
def _eq17_residual(lam, n, xi, alpha):
    """int_lam^n f(x) dx - (1 - alpha)(n - lam) with f of eq 13, by mpmath quadrature."""
    integral = mpmath.quad(lambda x: eq13_mpmath(x, n, xi), [lam, n])
    return integral - (1 - alpha) * (n - lam)


def test_additive_threshold_side_and_decision(capsys):
    rec = fuse_json(capsys, "--rule", "additive", "--u", U_57, "--xi", "0.003", "--alpha", "0.03")
    lam = rec["threshold"]
    # U_G = -43 < 0: left-hand side (sec. 6.3.1 fn 3); eq 17 has one root (positive), the
    # chapter's symmetric thresholding (sec. 2.2.3.2) uses its mirror -lambda there
    assert rec["threshold_side"] == "negative" and rec["threshold_source"] == "mirror" and lam < 0
    assert abs(_eq17_residual(-lam, 57, 0.003, 0.03)) < 1e-9 * 57
    assert rec["decision"] == "H1"  # -43 >= lambda (the chapter: presence confirmed)
    assert -lam > 43
    pos = fuse_json(capsys, "--rule", "additive", "--u", U_57, "--xi", "0.003", "--alpha", "0.03", "--root", "positive")
    assert pos["threshold"] == pytest.approx(-lam, rel=1e-15)
    assert pos["threshold_source"] == "root" and pos["decision"] == "H0"


def _eq16_residual(scaled_lam, n, xi, beta):
    """[int_lambda^{e^n} a e^(m x) dx - (1 - beta)(e^n - lambda)] / e^n, eqs 10-11, lambda = t e^n."""
    xi = mpmath.mpf(xi)
    e_n = mpmath.e ** n
    m = e_n * mpmath.log(1 / xi) / (e_n**2 - 1)
    ln_a = -(e_n**2) * mpmath.log(1 / xi) / (e_n**2 - 1)
    lam = mpmath.mpf(scaled_lam) * e_n
    integral = mpmath.exp(ln_a) / m * (mpmath.exp(m * e_n) - mpmath.exp(m * lam))
    return (integral - (1 - mpmath.mpf(beta)) * (e_n - lam)) / e_n


def test_multiplicative_threshold_log_domain(capsys):
    rec = fuse_json(capsys, "--rule", "multiplicative", "--u", U_57, "--xi", "0.003", "--beta", "0.5")
    ln_lam = rec["ln_threshold"]
    assert ln_lam is not None
    assert abs(_eq16_residual(rec["scaled_threshold"], 57, 0.003, 0.5)) < 1e-12
    assert rec["scaled_threshold"] == pytest.approx(math.exp(ln_lam - 57), rel=1e-13)
    assert rec["threshold"] == pytest.approx(math.exp(ln_lam), rel=1e-14)
    assert -43 < ln_lam and rec["decision"] == "H0"
    everything = ",".join(["1"] * 57)
    rec = fuse_json(capsys, "--rule", "multiplicative", "--u", everything, "--xi", "0.003", "--beta", "0.5")
    assert rec["ln_U_G"] == 57 and rec["decision"] == "H1"


def test_multiplicative_nonpositive_threshold_accepts_everything(capsys):
    # the chapter's beta = 0.83 (sec. 6.3): the root of eq 16 lies at lambda <= 0, so every
    # U_G > 0 accepts H1 (the chapter prints lambda = e^-45.543; see chapter-notes)
    rec = fuse_json(capsys, "--rule", "multiplicative", "--u", U_57, "--xi", "0.003", "--beta", "0.83")
    assert rec["ln_threshold"] is None and rec["scaled_threshold"] <= 0
    assert abs(_eq16_residual(rec["scaled_threshold"], 57, 0.003, 0.83)) < 1e-12
    assert rec["decision"] == "H1"


def test_preferential_band_decisions(capsys):
    u01 = ",".join(str((x + 1) // 2) for x in U_18)
    rec = fuse_json(capsys, "--rule", "preferential", "--u", u01, "--tuple", "01", "--xi", "0.003", "--alpha", "0.48")
    low, high, mean = rec["threshold_initial"], rec["threshold_final"], rec["threshold"]
    g = 4 * 18 - 4  # eq 15 with p = q = 1: 2 + 2 + 16 * 4
    assert rec["g"] == g
    # eq 18 with eq 14 at the mean: int_mean^g f = (1 - alpha)(g - mean), f = ((1-xi)/g^2) x^2 + xi
    xi, alpha = 0.003, 0.48
    lhs = (1 - xi) / g**2 * (g**3 - mean**3) / 3 + xi * (g - mean)
    assert lhs == pytest.approx((1 - alpha) * (g - mean), rel=1e-12)
    assert high - low == pytest.approx(alpha * g / 4, rel=1e-12)  # eq 20
    expected = "H1" if 37 >= high else ("H0" if 37 < low else "undecided")
    assert rec["decision"] == expected


def test_preferential_undecided_inside_band(capsys):
    # n = 6, {0,1}, p = q = 1: [1,1,1,0,0,0] gives U_G = 2 + 4 + 2 = 8 by eq 7 (hand-worked);
    # g = 4*6 - 4 = 20, eq 18: y^2 + y - 2 + 3*0.48/0.997 = 0 -> mean = 20 y = 7.952,
    # band (eq 20) 0.48*20/4 = 2.4 -> [6.752, 9.152): 8 lies inside
    y = (-1 + math.sqrt(9 - 4 * 3 * 0.48 / 0.997)) / 2
    low, high = 20 * y - 1.2, 20 * y + 1.2
    assert low < 8 < high
    rec = fuse_json(capsys, "--rule", "preferential", "--u", "1,1,1,0,0,0", "--tuple", "01",
                    "--xi", "0.003", "--alpha", "0.48")
    assert rec["U_G"] == 8 and rec["decision"] == "undecided"
    assert rec["threshold_initial"] == pytest.approx(low, rel=1e-12)
    assert rec["threshold_final"] == pytest.approx(high, rel=1e-12)


def test_no_root_is_a_result_not_an_error(capsys):
    # alpha = 0.999 exceeds every mean deficit of eq 13 on [-3, 3]: no threshold, no decision
    rec = fuse_json(capsys, "--rule", "additive", "--u", "1,1,-1", "--xi", "0.1", "--alpha", "0.999")
    assert rec["threshold"] is None and rec["decision"] is None and "eq 17" in rec["no_root"]
    assert rec["U_G"] == 1 and rec["p_h1"] is not None
    rec = fuse_json(capsys, "--rule", "preferential", "--u", "1,1,-1", "--xi", "0.1", "--alpha", "0.99")
    assert rec["threshold"] is None and "eq 18" in rec["no_root"]  # 3*0.99/0.9 > 9/4
    rec = fuse_json(capsys, "--rule", "multiplicative", "--u", "1,1,-1", "--xi", "0.999", "--beta", "0.9")
    assert rec["threshold"] is None and "eq 16" in rec["no_root"]


def test_likelihood_ratio_of_one_is_undecided(capsys):
    # (0.9/0.1)^1 (0.1/0.9)^1 = 1 exactly: the chapter's undefined case (sec. 6.2), although
    # the two logarithms sum to -4.4e-16 in floating point
    for rule in ("np", "llr"):
        rec = fuse_json(capsys, "--rule", rule, "--u", "1,-1", "--pd", "0.9", "--pf", "0.1")
        assert abs(rec["U_G"]) < 1e-15 and rec["decision"] == "undecided"
    rec = fuse_json(capsys, "--rule", "llr", "--u", "1,1", "--pd", "0.9", "--pf", "0.1")
    assert rec["U_G"] == pytest.approx(2 * math.log(9), rel=1e-14) and rec["decision"] == "H1"


def _binomial_tail(n, p, m):
    p = mpmath.mpf(p)
    return mpmath.fsum(mpmath.binomial(n, j) * p**j * (1 - p) ** (n - j) for j in range(m, n + 1))


def test_hebtem_threshold_in_count_form_with_exact_error_rates(capsys):
    # additive, pm1, n = 57: lambda = 50.18 (eq 17, alpha = 0.03) -> 2K - 57 >= 50.18 <=> K >= 54
    rec = fuse_json(capsys, "--rule", "additive", "--u", U_57, "--xi", "0.003", "--alpha", "0.03",
                    "--root", "positive", "--pd", "0.995", "--pf", "0.003")
    assert 50.0 < rec["threshold"] < 50.3 and rec["min_present_count"] == 54
    assert rec["p_false_alarm"] == pytest.approx(float(_binomial_tail(57, "0.003", 54)), rel=1e-11)
    assert rec["p_detect"] == pytest.approx(float(_binomial_tail(57, "0.995", 54)), rel=1e-12)
    assert rec["log_p_false_alarm"] == pytest.approx(float(mpmath.log(_binomial_tail(57, "0.003", 54))), rel=1e-12)
    # multiplicative, beta = 0.5: ln lambda = 56.68 -> 2K - 57 >= 56.68 <=> K >= 57
    rec = fuse_json(capsys, "--rule", "multiplicative", "--u", U_57, "--xi", "0.003", "--beta", "0.5",
                    "--pd", "0.995", "--pf", "0.003")
    assert 56.5 < rec["ln_threshold"] < 57 and rec["min_present_count"] == 57
    assert rec["p_false_alarm"] == pytest.approx(0.003**57, rel=1e-11)  # all 57 false alarms


def test_multiplicative_01_tuple_reports_the_compared_value(capsys):
    # {0,1}: U_G = e^(n-k) = e^4; the curve and eq 16 use the {-1,+1} value e^(2K - n) = e^3
    rec = fuse_json(capsys, "--rule", "multiplicative", "--u", "1,1,1,1,0", "--tuple", "01",
                    "--xi", "0.003", "--beta", "0.3")
    assert rec["ln_U_G"] == 4 and rec["ln_U_G_pm1"] == 3
    assert rec["decision"] == ("H1" if 3 >= rec["ln_threshold"] else "H0")


@pytest.mark.parametrize("argv, flag", [
    (["--rule", "additive", "--u", "1,-1", "--k", "1"], "--k"),
    (["--rule", "additive", "--u", "1,-1", "--p", "1"], "--p"),
    (["--rule", "multiplicative", "--u", "1,-1", "--xi", "0.1", "--alpha", "0.2"], "--alpha"),
    (["--rule", "additive", "--u", "1,-1", "--xi", "0.1", "--beta", "0.2"], "--beta"),
    (["--rule", "preferential", "--u", "1,-1", "--pd", "0.9"], "--pd"),
    (["--rule", "k-of-n", "--u", "1,-1", "--k", "1", "--xi", "0.1"], "--xi"),
    (["--rule", "llr", "--u", "1,-1", "--pd", "0.9", "--pf", "0.1", "--false-alarm", "0.1"], "--false-alarm"),
    (["--rule", "np", "--u", "1,-1", "--pd", "0.9", "--pf", "0.1", "--prior-h1", "0.1"], "--prior-h1"),
    (["--rule", "additive", "--u", "1,-1", "--pd", "0.9", "--pf", "0.1"], "--pd/--pf"),
])
def test_options_of_other_rules_are_rejected(capsys, argv, flag):
    line = fuse_error(capsys, *argv)
    assert flag in line
