"""Command-line bus options both commands share (``node-sim`` and ``fusion-center``).

python-can's ``can.cli.add_bus_arguments`` gives the flags (-i/-c/-b/--fd/--data-bitrate/
--bus-kwargs); these are the two adjustments both commands make to them: bit rates written as
python-can's tools and can-utils users write them (``500k``, ``1M``), and ``-c`` given once per
channel adding up (``-c a -c b`` = ``-c a,b``, one bus per scene channel).
"""

from __future__ import annotations

import argparse

BITRATE_RANGE = (125_000, 1_000_000)  # classic CAN nominal bit rates (CiA 301: 125k..1M)
DATA_BITRATE_MAX = 8_000_000          # CAN FD data phase (--fd --data-bitrate)


def parse_bitrate(text: str) -> int:
    """argparse type of ``-b``: ``500000``, ``500k``, ``1M``, ``1_000_000`` -> bit/s (an int;
    the range is checked later, with the flag's name in the message)."""
    item = str(text).strip().lower().replace("_", "")
    scale = 1000 if item.endswith("k") else 1_000_000 if item.endswith("m") else 1
    try:
        value = float(item.rstrip("km")) * scale
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a bit rate (e.g. 500000, 500k or 1M)") from None
    if value != int(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of bit/s")
    return int(value)


class ChannelsAction(argparse.Action):
    """``-c``: given again, the channels add up (``-c a -c b`` = ``-c a,b``)."""

    def __call__(self, parser, namespace, values, option_string=None):
        before = getattr(namespace, self.dest, None)
        setattr(namespace, self.dest, values if before is None else f"{before},{values}")


def channel_indices(text: str) -> list[int]:
    """Scene channel indices as ``--serve`` takes them: ``0-3``, ``0,2,5`` or a mix (``0-2,7``);
    ``ValueError`` for anything else (node-sim and ``fusion-center assemble`` word the error)."""
    out: list[int] = []
    for part in str(text).split(","):
        lo, _, hi = part.strip().partition("-")
        first, last = int(lo), int(hi) if hi else int(lo)
        if first < 0 or last < first:
            raise ValueError(text)
        out.extend(range(first, last + 1))
    return out
