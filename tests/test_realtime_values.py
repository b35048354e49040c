"""taxel_net.realtime.check_priority (FusionService(rt_priority=...)): every non-priority is the
one-line ValueError naming the option - infinity raised OverflowError, and True passed as 1."""

from __future__ import annotations

import pytest

from fusion_center.service.fusion_service import check_rt_priority
from taxel_net import realtime
from taxel_net.errors import UsageError


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), True, False])
def test_infinity_and_booleans_are_refused_naming_the_option(value):
    with pytest.raises(ValueError, match=r"^--rt-priority .*not an integer \(allowed: 1-99"):
        realtime.check_priority(value)
    with pytest.raises(UsageError, match=r"^--rt-priority "):
        check_rt_priority(value)


@pytest.mark.parametrize("text", [" 5", "1_0", "５", "+5", "5.0", "0", "100"])
def test_the_run_option_takes_ascii_digits_1_to_99_only(text, capsys):
    """``fusion-center run --rt-priority``: argparse's int took ' 5', '1_0' and full-width digits
    (2026-11-30, stop 32); now ASCII digits 1-99, else exit 2 in one line naming the option."""
    from fusion_center.cli import main

    with pytest.raises(SystemExit) as info:
        main(["run", "--scene", "grasp_lift", "-i", "virtual", "-c", "rt-values", "--rt-priority", text])
    assert info.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "argument --rt-priority" in last and "1-99" in last
