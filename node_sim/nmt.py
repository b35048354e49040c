"""NMT slave of the taxel node twin (CiA 301): states and command specifiers."""

from __future__ import annotations

# NMT states (heartbeat state byte, CiA 301)
INITIALISING = 0x00
STOPPED = 0x04
OPERATIONAL = 0x05
PRE_OPERATIONAL = 0x7F
STATE_NAMES = {INITIALISING: "INITIALISING", STOPPED: "STOPPED", OPERATIONAL: "OPERATIONAL",
               PRE_OPERATIONAL: "PRE-OPERATIONAL"}

# NMT command specifiers
NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
