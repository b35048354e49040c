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
