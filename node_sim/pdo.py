"""TPDO engine of the taxel node twin (CiA 301): configuration and run-time state of a TPDO."""

from __future__ import annotations

import math
from dataclasses import dataclass

MAX_MAPPED = 8


@dataclass
class _TpdoConfig:
    valid: bool
    can_id: int
    transmission_type: int
    inhibit_s: float
    event_timer_s: float
    sync_start: int
    mapping: list[tuple[int, int, int]]  # (index, subindex, bits)


@dataclass
class _TpdoRuntime:
    sync_count: int = 0
    started: bool = False            # SYNC start value reached (or not used)
    last_sent: bytes | None = None
    last_tx_time: float = -math.inf  # monotonic
    pending: object | None = None    # scheduler handle of an inhibited event transmission
    event_timer: object | None = None
