"""Where the taxel node's application was: it lives in :mod:`node_sim.taxel.detector` (the taxel
node's package, issue 22); re-exported here so that ``node_sim.detector`` imports keep working."""

from __future__ import annotations

from .taxel.detector import (AI_STATUS_NEGATIVE_OVERLOAD, AI_STATUS_NOT_VALID,  # noqa: F401 - re-exported
                             AI_STATUS_POSITIVE_OVERLOAD, TAG_BITS, TAG_MASK, Detector, local_decision_pm1,
                             tagged_decision)
