"""SYNC consumer of the taxel node twin (CiA 301): the COB-ID SYNC object 0x1005."""

from __future__ import annotations

SYNC_GENERATE = 0x40000000    # 0x1005 bit 30: this node would produce SYNC (refused)
