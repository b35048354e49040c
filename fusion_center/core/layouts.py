"""Skin layouts on CAN: exact bits per SYNC cycle, bus load, highest SYNC rate, latency (issue 14).

Numerical core: no CAN, no I/O. The chapter's networks have one node and one TPDO per taxel;
a real tactile skin puts many taxels behind one microcontroller (a patch node) and packs their
values into few frames. This module prices a layout without a scene or a bus:

* **taxels per node**: 1 (the chapter's one-taxel nodes) or N (patch nodes; the last node of
  the skin holds the remainder);
* **payload** per taxel (``PAYLOAD_BITS``): ``decision`` - the local decision u_i (eqs 1-4),
  one bit per taxel, packed; ``raw8`` / ``raw16`` - the reading as INTEGER8 / INTEGER16;
  ``real32`` - the reading as REAL32 (the chapter's TPDO2, one per taxel);
* **classic CAN** (ISO 11898-1:2015 CBFF: up to 8 data bytes, ``bus_timing.frame_bits``) or
  **CAN FD** (FBFF: up to 64 bytes, the data phase at the data bit rate when BRS is set,
  ``bus_timing.fd_frame_bits``);
* **synchronous** (every TPDO every SYNC, CiA 301 transmission type 1) or **event-driven**
  (type 254/255: a TPDO is sent when one of the taxel values it carries changed);
* a **cycle tag** (``tag_bytes=1``): every PDO frame starts with one UNSIGNED8 byte, the
  counter of the SYNC the taxels were sampled at (the centre's patch PDOs when the scene has a
  SYNC counter); it needs a SYNC counter (``sync_counter`` 2..240, CiA 301 0x1019), whose
  SYNC frames then carry the counter byte 1..N too.

PDO packing (CiA 301 PDO mapping, little-endian, the first mapped object in the lowest bits):
a node's taxel values fill frames of the largest size (8 bytes classic, 64 bytes FD; with a
cycle tag one byte less for the taxels) in taxel order; one-bit decisions are bit-mapped (taxel
j of a frame in bit j mod 8 of byte j div 8 after the tag), a reading occupies whole bytes and
never straddles two frames. The last frame of a node holds the rest in whole bytes, rounded up
to a valid FD data length (12, 16, 20, 24, 32, 48, 64) in FD; unused bits are 0. One-taxel
decision nodes therefore send one byte (as the chapter's TPDO1 does, there u_i as INTEGER8
0x01/0xFF).

Channels and identifiers: a CANopen network holds node-IDs 1..127 (CiA 301), so nodes are
split into contiguous, balanced blocks over as many channels as needed (or as asked); on each
channel the PDO frames take consecutive 11-bit COB-IDs from 0x181 in node order, within
0x181..0x57F (the TPDO/RPDO range of the predefined connection set, 1023 identifiers): node k
of a one-taxel layout sends on 0x180 + k, its predefined TPDO1. Every channel carries one
SYNC (0x080, no data, or the counter byte) per cycle and one heartbeat per node (0x700 +
node-ID, one byte 0x05) per heartbeat period, both classic frames at the nominal rate.

Bit counts are exact, frame by frame: each frame's mean over its payloads (taxel bits 1 with
probability ``p_one``) and its worst case over every payload come from ``pdo_frames``
(``pdo_frame_stats``, dynamic programming over the stuffing state). Event-driven traffic is the
expectation over frames: a frame carrying k taxels goes out with probability
1 - (1 - p_change)^k per cycle (each taxel value changes independently with probability
``p_change``), its content priced as above (independent of whether it is sent); its worst case
is every frame at once, the synchronous worst case. **Latency** of a channel: from the start
of its SYNC to the end of its cycle's last PDO when the PDOs follow the SYNC back to back, in
the worst case: the worst-case SYNC and every PDO frame of the channel at their longest, at
the nominal (and data) bit rate - the worst-case cycle time (heartbeats, COB-IDs 0x70x, lose
arbitration to every PDO and can add at most one frame of blocking, not counted).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from taxel_net.errors import ParameterError

from .bus_timing import FD_LENGTHS, frame_bits
from .pdo_frames import (  # noqa: F401 - re-exported: layouts.pdo_frame_stats / FrameStats
    CLASSIC_MAX_BYTES,
    FD_MAX_BYTES,
    FrameStats,
    PhaseBits,
    check_probability,
    pdo_frame_stats,
)

PAYLOAD_BITS = {"decision": 1, "raw8": 8, "raw16": 16, "real32": 32}
MAX_NODES_PER_CHANNEL = 127            # CANopen node-IDs 1..127 (CiA 301)
FIRST_PDO_COB_ID = 0x181
LAST_PDO_COB_ID = 0x57F                 # 0x181..0x57F: the predefined TPDO1-4 / RPDO1-4 range
MAX_PDO_FRAMES_PER_CHANNEL = LAST_PDO_COB_ID - FIRST_PDO_COB_ID + 1
SYNC_COB_ID = 0x080
HEARTBEAT_BASE = 0x700
NMT_OPERATIONAL = 0x05
SYNC_COUNTER_RANGE = (2, 240)           # CiA 301 0x1019 synchronous counter overflow value (0 = none)


# ---------------------------------------------------------------- the layout

@dataclass(frozen=True)
class PdoFrame:
    """One TPDO of a layout: its node, COB-ID, data bytes, the taxels it carries and which data
    bits carry them (``free_mask``, as in ``pdo_frame_stats``)."""

    node_id: int
    cob_id: int
    n_bytes: int
    taxels: int
    free_mask: int


@dataclass(frozen=True)
class Channel:
    """One CAN channel (one CANopen network) of a layout."""

    index: int
    node_ids: tuple[int, ...]
    taxels: int
    frames: tuple[PdoFrame, ...]


@dataclass(frozen=True)
class SkinLayout:
    """Nodes, channels and PDO frames of a skin (``skin_layout``)."""

    n_taxels: int
    taxels_per_node: int
    payload: str
    fd: bool
    brs: bool
    channels: tuple[Channel, ...]
    tag_bytes: int = 0

    @property
    def bits_per_taxel(self) -> int:
        return PAYLOAD_BITS[self.payload]

    @property
    def n_nodes(self) -> int:
        return sum(len(ch.node_ids) for ch in self.channels)

    @property
    def n_frames(self) -> int:
        return sum(len(ch.frames) for ch in self.channels)


def _fd_length(n: int) -> int:
    return next(length for length in FD_LENGTHS if length >= n)


def node_frames(taxels: int, payload: str, fd: bool, tag_bytes: int = 0) -> list[tuple[int, int, int]]:
    """The TPDO frames of one node with ``taxels`` taxel values: [(n_bytes, taxels, free_mask)].

    Full frames of 8 (classic) or 64 (FD) bytes in taxel order, the rest in the last frame
    (whole bytes, FD: rounded up to a valid FD length); with ``tag_bytes=1`` every frame starts
    with the cycle tag byte and the taxels follow it; see the module docstring."""
    bits = PAYLOAD_BITS[payload]
    cap_bytes = (FD_MAX_BYTES if fd else CLASSIC_MAX_BYTES) - tag_bytes
    per_frame = cap_bytes * 8 // bits
    frames = []
    left = taxels
    while left > 0:
        k = min(left, per_frame)
        used_bytes = tag_bytes + -(-k * bits // 8)
        n_bytes = _fd_length(used_bytes) if fd else used_bytes
        if bits == 1:   # taxel j in bit j mod 8 of byte tag + j div 8; on the wire byte 0 first, MSB first
            mask = 0
            for j in range(k):
                mask |= 1 << (8 * n_bytes - 1 - (8 * (tag_bytes + j // 8) + 7 - j % 8))
        else:           # whole bytes tag_bytes .. used_bytes - 1
            mask = ((1 << (8 * (used_bytes - tag_bytes))) - 1) << (8 * (n_bytes - used_bytes))
        frames.append((n_bytes, k, mask))
        left -= k
    return frames


def _check_int(name: str, value, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ParameterError(name, value, f"must be an integer >= {low}")
    return value


def skin_layout(n_taxels: int, *, taxels_per_node: int = 1, payload: str = "decision", fd: bool = False,
                brs: bool = True, channels: int | None = None, tag_bytes: int = 0) -> SkinLayout:
    """Nodes, channels and TPDO frames of a skin (module docstring: packing, COB-IDs).

    ``n_taxels`` taxels in nodes of ``taxels_per_node`` (1: the chapter's one-taxel nodes; the
    last node holds the remainder), each taxel value ``payload`` (``PAYLOAD_BITS``), on classic
    CAN or CAN FD (``fd``, with bit-rate switch ``brs``), over ``channels`` CAN channels (default:
    the fewest that hold the nodes, <= 127 per channel, and their frames, <= 1023 per channel);
    ``tag_bytes``: 0, or 1 for a cycle tag byte leading every PDO frame (module docstring).
    """
    _check_int("n_taxels", n_taxels, 1)
    _check_int("taxels_per_node", taxels_per_node, 1)
    if payload not in PAYLOAD_BITS:
        raise ParameterError("payload", payload, f"must be one of {', '.join(PAYLOAD_BITS)}")
    if not isinstance(fd, bool) or not isinstance(brs, bool):
        raise ParameterError("fd/brs", (fd, brs), "must be True or False")
    if isinstance(tag_bytes, bool) or tag_bytes not in (0, 1):
        raise ParameterError("tag_bytes", tag_bytes, "must be 0 (no cycle tag) or 1 (a leading UNSIGNED8 tag)")
    n_nodes = -(-n_taxels // taxels_per_node)
    node_taxels = [taxels_per_node] * (n_nodes - 1) + [n_taxels - taxels_per_node * (n_nodes - 1)]
    frames_of = {k: node_frames(k, payload, fd, tag_bytes) for k in set(node_taxels)}

    def split(n_channels: int) -> list[list[int]]:
        base, extra = divmod(n_nodes, n_channels)
        blocks, start = [], 0
        for c in range(n_channels):
            size = base + (1 if c < extra else 0)
            blocks.append(list(range(start, start + size)))
            start += size
        return blocks

    def fits(blocks) -> bool:
        return all(len(b) <= MAX_NODES_PER_CHANNEL
                   and sum(len(frames_of[node_taxels[i]]) for i in b) <= MAX_PDO_FRAMES_PER_CHANNEL
                   for b in blocks)

    if channels is None:
        n_channels = -(-n_nodes // MAX_NODES_PER_CHANNEL)
        while not fits(split(n_channels)):
            n_channels += 1
            if n_channels > n_nodes:
                raise ParameterError("taxels_per_node", taxels_per_node,
                                     f"one node needs more than {MAX_PDO_FRAMES_PER_CHANNEL} PDO COB-IDs")
    else:
        n_channels = _check_int("channels", channels, 1)
        if n_channels > n_nodes:
            raise ParameterError("channels", channels, f"must not exceed the number of nodes ({n_nodes})")
        if not fits(split(n_channels)):
            raise ParameterError("channels", channels, f"too few: <= {MAX_NODES_PER_CHANNEL} nodes and "
                                                       f"<= {MAX_PDO_FRAMES_PER_CHANNEL} PDO COB-IDs per channel")
    out = []
    for c, block in enumerate(split(n_channels)):
        frames, cob = [], FIRST_PDO_COB_ID
        for node_id, i in enumerate(block, 1):
            for n_bytes, k, mask in frames_of[node_taxels[i]]:
                frames.append(PdoFrame(node_id, cob, n_bytes, k, mask))
                cob += 1
        out.append(Channel(c, tuple(range(1, len(block) + 1)), sum(node_taxels[i] for i in block), tuple(frames)))
    return SkinLayout(n_taxels, taxels_per_node, payload, fd, brs, tuple(out), tag_bytes)


# ---------------------------------------------------------------- bits per cycle and bus use

@dataclass(frozen=True)
class ChannelBits(PhaseBits):
    """Bits of one channel in one SYNC cycle: its PDOs (mean and worst case) and its SYNC.

    ``frames``: PDO frames of a synchronous cycle; ``expected_frames``: how many go out on
    average (= ``frames`` when synchronous). ``*_nominal`` include the SYNC frame (``sync_bits``
    its mean over the counter values, ``sync_worst_bits`` its longest); ``heartbeat_bits``: one
    heartbeat of every node of the channel (sent once per heartbeat period, not per cycle)."""

    channel: int
    nodes: int
    taxels: int
    frames: int
    expected_frames: float
    sync_bits: float
    mean_nominal: float
    mean_data: float
    worst_nominal: int
    worst_data: int
    heartbeat_bits: int
    sync_worst_bits: int = 0


def _check_sync_counter(sync_counter) -> int:
    low, high = SYNC_COUNTER_RANGE
    if isinstance(sync_counter, bool) or not isinstance(sync_counter, int) \
            or not (sync_counter == 0 or low <= sync_counter <= high):
        raise ParameterError("sync_counter", sync_counter, f"must be 0 (no SYNC counter) or an overflow value "
                                                           f"{low}..{high} (CiA 301 0x1019)")
    return sync_counter


def sync_frame_bits(sync_counter: int = 0) -> tuple[float, int]:
    """(mean, worst) bits of the SYNC frame 0x080: no data without a counter, else one counter
    byte taking the values 1..``sync_counter`` equally often."""
    values = range(1, _check_sync_counter(sync_counter) + 1) if sync_counter else [None]
    bits = [frame_bits(SYNC_COB_ID, b"" if c is None else bytes([c])) for c in values]
    return sum(bits) / len(bits), max(bits)


def layout_cycle_bits(layout: SkinLayout, *, p_one: float = 0.5, p_change: float | None = None,
                      sync_counter: int = 0) -> tuple[ChannelBits, ...]:
    """Exact bits per SYNC cycle of every channel of ``layout`` (``ChannelBits``).

    Synchronous (``p_change=None``): every PDO frame every cycle. Event-driven: a frame carrying
    k taxels is sent with probability 1 - (1 - p_change)^k; the worst case stays every frame.
    ``p_one``: P(taxel bit = 1) for the mean payload (``pdo_frame_stats``). Every cycle adds the
    channel's SYNC (0x080, classic; with ``sync_counter`` N in 2..240 one counter byte 1..N,
    which a layout's cycle tag repeats: ``tag_bytes=1`` needs a counter)."""
    p_one = check_probability("p_one", p_one)
    if p_change is not None:
        p_change = check_probability("p_change", p_change)
    _check_sync_counter(sync_counter)
    if layout.tag_bytes and not sync_counter:
        raise ParameterError("sync_counter", sync_counter, "a layout with a cycle tag (tag_bytes=1) needs a SYNC "
                                                           f"counter {SYNC_COUNTER_RANGE[0]}..{SYNC_COUNTER_RANGE[1]}")
    tags = tuple(range(1, sync_counter + 1)) if layout.tag_bytes else ()
    sync_mean, sync_worst = sync_frame_bits(sync_counter)
    # channels with the same nodes and frames (every full channel of a large skin: the COB-IDs
    # restart at 0x181 on each) have the same bits: priced once, in the same order of sums
    priced: dict[tuple, tuple] = {}
    out = []
    for ch in layout.channels:
        key = (ch.node_ids, ch.frames)
        if key not in priced:
            priced[key] = _channel_bits(ch, layout, p_one, p_change, tags)
        expected, mean_nom, mean_dat, worst_nom, worst_dat, hb = priced[key]
        out.append(ChannelBits(ch.index, len(ch.node_ids), ch.taxels, len(ch.frames), expected, sync_mean,
                               mean_nom + sync_mean, mean_dat, worst_nom + sync_worst, worst_dat, hb, sync_worst))
    return tuple(out)


def _channel_bits(ch: Channel, layout: SkinLayout, p_one: float, p_change: float | None, tags: tuple) -> tuple:
    """(expected frames, mean nominal / data bits, worst nominal / data bits of the PDOs,
    heartbeat bits) of one channel of ``layout_cycle_bits``."""
    mean_nom = mean_dat = 0.0
    worst_nom = worst_dat = 0
    expected = 0.0
    for f in ch.frames:
        st = pdo_frame_stats(f.cob_id, f.n_bytes, f.free_mask, p_one, fd=layout.fd, brs=layout.brs, tag_values=tags)
        sent = 1.0 if p_change is None else 1.0 - (1.0 - p_change) ** f.taxels
        expected += sent
        mean_nom += sent * st.mean_nominal
        mean_dat += sent * st.mean_data
        worst_nom += st.worst_nominal
        worst_dat += st.worst_data
    return expected, mean_nom, mean_dat, worst_nom, worst_dat, _heartbeat_bits(ch.node_ids)


@lru_cache(maxsize=1024)
def _heartbeat_bits(node_ids: tuple[int, ...]) -> int:
    """Bits of one heartbeat (0x700 + node-ID, state 0x05) of every node in ``node_ids``."""
    return sum(frame_bits(HEARTBEAT_BASE + node, bytes([NMT_OPERATIONAL])) for node in node_ids)


def _check_rate(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise ParameterError(name, value, "must be a finite number > 0")
    return float(value)


@dataclass(frozen=True)
class ChannelUse:
    """Bus use of one channel: ``load`` (mean cycle + heartbeats, fraction of the SYNC period),
    ``worst_load`` (worst-case cycle), ``max_sync_hz`` (highest SYNC rate the worst-case cycle
    fits, heartbeats deducted), times in seconds per cycle. ``latency_s``: start of the SYNC to
    the end of the channel's last PDO in the worst case (module docstring) = ``worst_cycle_s``."""

    bits: ChannelBits
    mean_cycle_s: float
    worst_cycle_s: float
    heartbeat_s_per_s: float
    load: float
    worst_load: float
    max_sync_hz: float

    @property
    def latency_s(self) -> float:
        return self.worst_cycle_s


@dataclass(frozen=True)
class LayoutUse:
    """``layout_bus_use`` of every channel of a layout, with totals and the busiest channel."""

    channels: tuple[ChannelUse, ...]

    @property
    def mean_bits(self) -> float:
        return sum(c.bits.mean_bits for c in self.channels)

    @property
    def worst_bits(self) -> int:
        return sum(c.bits.worst_bits for c in self.channels)

    @property
    def mean_cycle_s(self) -> float:
        """Bus time of one cycle summed over the channels (each channel its own bus)."""
        return sum(c.mean_cycle_s for c in self.channels)

    @property
    def busiest(self) -> ChannelUse:
        return max(self.channels, key=lambda c: (c.load, c.worst_load))

    @property
    def max_sync_hz(self) -> float:
        return min(c.max_sync_hz for c in self.channels)

    @property
    def latency_s(self) -> float:
        """The longest channel latency (``ChannelUse.latency_s``)."""
        return max(c.latency_s for c in self.channels)


def layout_bus_use(layout: SkinLayout, *, nominal_bitrate: float, data_bitrate: float | None = None,
                   sync_period_s: float = 0.01, heartbeat_period_s: float | None = None, p_one: float = 0.5,
                   p_change: float | None = None, sync_counter: int = 0) -> LayoutUse:
    """Bus load, highest SYNC rate and latency of every channel (``LayoutUse``).

    A cycle lasts nominal bits / ``nominal_bitrate`` + data-phase bits / ``data_bitrate``
    (CAN FD with BRS; ``None`` = the nominal rate). Heartbeats (every ``heartbeat_period_s``,
    ``None`` = not counted) take heartbeat bits / nominal rate / period of every second.
    load = mean cycle time / SYNC period + heartbeat share; max SYNC rate = (1 - heartbeat
    share) / worst-case cycle time (as ``fusion-center bandwidth`` computes it for a scene);
    latency = worst-case cycle time. ``sync_counter``: as ``layout_cycle_bits``."""
    nb = _check_rate("nominal_bitrate", nominal_bitrate)
    db = nb if data_bitrate is None else _check_rate("data_bitrate", data_bitrate)
    period = _check_rate("sync_period_s", sync_period_s)
    hb_period = None if heartbeat_period_s is None else _check_rate("heartbeat_period_s", heartbeat_period_s)
    out = []
    for bits in layout_cycle_bits(layout, p_one=p_one, p_change=p_change, sync_counter=sync_counter):
        mean_s = bits.mean_nominal / nb + bits.mean_data / db
        worst_s = bits.worst_nominal / nb + bits.worst_data / db
        hb = 0.0 if hb_period is None else bits.heartbeat_bits / nb / hb_period
        out.append(ChannelUse(bits, mean_s, worst_s, hb, mean_s / period + hb, worst_s / period + hb,
                              max(0.0, 1.0 - hb) / worst_s))
    return LayoutUse(tuple(out))


def channels_needed(n_taxels: int, *, nominal_bitrate: float, data_bitrate: float | None = None,
                    sync_period_s: float = 0.01, heartbeat_period_s: float | None = None,
                    max_load: float = 1.0, sync_counter: int = 0, **layout_kwargs) -> int | None:
    """Fewest channels whose every channel fits its worst-case cycle (plus heartbeats) into
    ``max_load`` of the SYNC period; ``None`` if even one node per channel does not fit.
    ``layout_kwargs``: ``taxels_per_node``, ``payload``, ``fd``, ``brs``, ``tag_bytes`` of
    ``skin_layout``."""
    limit = _check_rate("max_load", max_load)
    first = skin_layout(n_taxels, **layout_kwargs)
    for n_channels in range(len(first.channels), first.n_nodes + 1):
        layout = first if n_channels == len(first.channels) else skin_layout(n_taxels, channels=n_channels,
                                                                              **layout_kwargs)
        use = layout_bus_use(layout, nominal_bitrate=nominal_bitrate, data_bitrate=data_bitrate,
                             sync_period_s=sync_period_s, heartbeat_period_s=heartbeat_period_s,
                             sync_counter=sync_counter)
        if max(c.worst_load for c in use.channels) <= limit:
            return n_channels
    return None
