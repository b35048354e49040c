"""Skin layouts on CAN: exact bits per SYNC cycle, bus load and the highest SYNC rate (issue 14).

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
  (type 254/255: a TPDO is sent when one of the taxel values it carries changed).

PDO packing (CiA 301 PDO mapping, little-endian, the first mapped object in the lowest bits):
a node's taxel values fill frames of the largest size (8 bytes classic, 64 bytes FD) in taxel
order; one-bit decisions are bit-mapped (taxel j of a frame in bit j mod 8 of byte j div 8), a
reading occupies whole bytes and never straddles two frames. The last frame of a node holds
the rest in whole bytes, rounded up to a valid FD data length (12, 16, 20, 24, 32, 48, 64) in
FD; unused bits are 0. One-taxel decision nodes therefore send one byte (as the chapter's
TPDO1 does, there u_i as INTEGER8 0x01/0xFF).

Channels and identifiers: a CANopen network holds node-IDs 1..127 (CiA 301), so nodes are
split into contiguous, balanced blocks over as many channels as needed (or as asked); on each
channel the PDO frames take consecutive 11-bit COB-IDs from 0x181 in node order, within
0x181..0x57F (the TPDO/RPDO range of the predefined connection set, 1023 identifiers): node k
of a one-taxel layout sends on 0x180 + k, its predefined TPDO1. Every channel carries one
SYNC (0x080, no data) per cycle and one heartbeat per node (0x700 + node-ID, one byte 0x05)
per heartbeat period, both classic frames at the nominal rate.

Bit counts are exact, frame by frame, from the bit-level frame builders of ``bus_timing``;
what varies with the payload is the number of dynamic stuff bits, so a frame is priced two
ways over its payloads:

* ``worst``: the longest frame over every value of the taxel bits (padding fixed at 0) - the
  exact maximum for that COB-ID and length, never above the Davis et al. bound of
  ``worst_case_frame_bits`` (classic) or ``fd_frame_bits_estimate`` (FD);
* ``mean``: the expectation when every taxel bit is 1 with probability ``p_one``,
  independently (0.5: uniform payloads; 0: all taxels 0, e.g. a quiet skin's decisions).

Both are computed by dynamic programming over the stuffing state (value and length of the
current run, and for classic frames the CRC-15 register, whose bits are stuffed too), checked
in the tests against enumerating every payload with ``frame_bits`` / ``fd_frame_bits``.
Event-driven traffic is the expectation over frames: a frame carrying k taxels goes out with
probability 1 - (1 - p_change)^k per cycle (each taxel value changes independently with
probability ``p_change``), its content priced as above (independent of whether it is sent);
its worst case is every frame at once, the synchronous worst case.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from taxel_net.errors import ParameterError

from .bus_timing import (
    CRC15_POLY,
    FD_LENGTHS,
    INTERMISSION_BITS,
    STUFF_RUN,
    TRAILER_BITS,
    crc15,
    fd_frame_fields,
    frame_bits,
    frame_fields,
)

PAYLOAD_BITS = {"decision": 1, "raw8": 8, "raw16": 16, "real32": 32}
CLASSIC_MAX_BYTES = 8
FD_MAX_BYTES = 64
MAX_NODES_PER_CHANNEL = 127            # CANopen node-IDs 1..127 (CiA 301)
FIRST_PDO_COB_ID = 0x181
LAST_PDO_COB_ID = 0x57F                 # 0x181..0x57F: the predefined TPDO1-4 / RPDO1-4 range
MAX_PDO_FRAMES_PER_CHANNEL = LAST_PDO_COB_ID - FIRST_PDO_COB_ID + 1
SYNC_COB_ID = 0x080
HEARTBEAT_BASE = 0x700
NMT_OPERATIONAL = 0x05
_FD_BRS_INDEX = 16                      # BRS in the FD base format (SOF = 0)
_FD_HEAD = 22                           # SOF..DLC of the FD base format
_CLASSIC_HEAD = 19                      # SOF..DLC of the classic base format


# ---------------------------------------------------------------- one frame over its payloads

@dataclass(frozen=True)
class FrameStats:
    """Bits of one PDO frame over its payloads: (nominal, data) phase, mean and worst case.

    Classic frames and FD frames without BRS have no data phase (``*_data`` = 0). The nominal
    part of an FD frame with BRS does not depend on the payload (SOF..BRS, CRC delimiter, ACK,
    EOF, intermission), so ``mean_nominal == worst_nominal`` there."""

    mean_nominal: float
    mean_data: float
    worst_nominal: int
    worst_data: int

    @property
    def mean_bits(self) -> float:
        return self.mean_nominal + self.mean_data

    @property
    def worst_bits(self) -> int:
        return self.worst_nominal + self.worst_data


def _check_probability(name: str, p) -> float:
    if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 <= p <= 1.0:
        raise ParameterError(name, p, "must be a probability in [0, 1]")
    return float(p)


def _check_frame_args(cob_id, n_bytes, free_mask, fd: bool) -> None:
    if isinstance(cob_id, bool) or not isinstance(cob_id, int) or not 0 <= cob_id <= 0x7FF:
        raise ParameterError("cob_id", cob_id, "must be an 11-bit identifier 0..0x7FF")
    allowed = FD_LENGTHS if fd else tuple(range(CLASSIC_MAX_BYTES + 1))
    if isinstance(n_bytes, bool) or not isinstance(n_bytes, int) or n_bytes not in allowed:
        raise ParameterError("n_bytes", n_bytes, f"must be one of {allowed} for {'CAN FD' if fd else 'classic CAN'}")
    if isinstance(free_mask, bool) or not isinstance(free_mask, int) or not 0 <= free_mask < (1 << (8 * n_bytes)):
        raise ParameterError("free_mask", free_mask, f"must be a bit mask of the {8 * n_bytes} data bits")


FREE = 2     # a bit the payload sets (1 with probability p_one), as opposed to a fixed 0 or 1


def _data_bits(n_bytes: int, free_mask: int) -> tuple[int, ...]:
    """Each data bit in transmission order (byte 0 first, each byte MSB first): FREE for a
    taxel bit, 0 for padding; bit 8n-1-k of ``free_mask`` = the k-th bit on the wire."""
    n = 8 * n_bytes
    return tuple(FREE if (free_mask >> (n - 1 - k)) & 1 else 0 for k in range(n))


def _choices(bit: int, p_one: float) -> tuple[tuple[int, float], ...]:
    """(value, probability) of a fixed or free bit; a free bit takes both values even when
    p_one is 0 or 1 (the worst case is over every payload, the mean weighs them)."""
    if bit == FREE:
        return (0, 1.0 - p_one), (1, p_one)
    return ((bit, 1.0),)


# run state index: value v in {0, 1}, run length n in 1..4 (a fifth equal bit is stuffed)
def _state(v: int, n: int) -> int:
    return 4 * v + n - 1


def _step(v: int, n: int, b: int) -> tuple[int, int, int]:
    """Next run (value, length) after bit b, and whether a stuff bit follows it."""
    n = n + 1 if b == v else 1
    if n == STUFF_RUN:
        return 1 - b, 1, 1
    return b, n, 0


def _run_after(bits) -> tuple[int, int, int]:
    """Deterministic stuffing of fixed bits: (run value, run length, stuff bits)."""
    v, n, s = -1, 0, 0
    for b in bits:
        v, n, st = _step(v, n, b)
        s += st
    return v, n, s


@lru_cache(maxsize=4096)
def _run_dp(v0: int, n0: int, bits: tuple[int, ...], p_one: float, stuff_last: bool) -> tuple[float, int]:
    """Dynamic stuffing (ISO 11898-1:2015 10.5) over ``bits`` (0, 1 or FREE: 1 with
    probability ``p_one``) from run (v0, n0): (expected stuff bits, the most stuff bits over
    every value of the free bits). With ``stuff_last=False`` the condition met at the last bit
    inserts nothing (FD: the end of the data field)."""
    prob = [0.0] * 8
    best = [-1] * 8
    prob[_state(v0, n0)] = 1.0
    best[_state(v0, n0)] = 0
    expected = 0.0
    last = len(bits) - 1
    for k, bit in enumerate(bits):
        nprob = [0.0] * 8
        nbest = [-1] * 8
        for s in range(8):
            if best[s] < 0:
                continue
            v, n = divmod(s, 4)
            n += 1
            for b, w in _choices(bit, p_one):
                v2, n2, st = _step(v, n, b)
                if k == last and not stuff_last:
                    st = 0                       # (the final run state is not used after this)
                t = _state(v2, n2)
                nprob[t] += prob[s] * w
                expected += prob[s] * w * st
                nbest[t] = max(nbest[t], best[s] + st)
        prob, best = nprob, nbest
    return expected, max(best)


def _fd_stats(cob_id: int, n_bytes: int, free_mask: int, p_one: float, brs: bool) -> FrameStats:
    fields = fd_frame_fields(cob_id, bytes(n_bytes), brs=brs)
    head = fields[:_FD_HEAD]
    # SOF..BRS: fixed bits, their stuff bits are nominal (one right after BRS would be data phase)
    v, n, head_stuff = _run_after(head[:_FD_BRS_INDEX])
    v, n, st_brs = _step(v, n, head[_FD_BRS_INDEX])
    bits = tuple(head[_FD_BRS_INDEX + 1:]) + _data_bits(n_bytes, free_mask)
    mean_s, worst_s = _run_dp(v, n, bits, p_one, False)   # ESI, DLC and data; never empty
    width = 17 if n_bytes <= 16 else 21
    fixed = 1 + (4 + width) + (4 + width) // 4          # stuff count, CRC, fixed stuff bits
    tail = TRAILER_BITS + INTERMISSION_BITS
    nominal = _FD_BRS_INDEX + 1 + head_stuff + tail
    data_fixed = (len(fields) - _FD_BRS_INDEX - 1) + fixed + st_brs
    if brs:
        return FrameStats(float(nominal), float(data_fixed + mean_s), nominal, data_fixed + worst_s)
    return FrameStats(float(nominal + data_fixed + mean_s), 0.0, nominal + data_fixed + worst_s, 0)


@lru_cache(maxsize=1)
def _crc_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse CRC-15 register steps for a data bit 0 / 1, and S[state, c]: the stuff bits of
    the 15 CRC bits c (MSB first, one after the last bit included) from each run state."""
    c = np.arange(1 << 15, dtype=np.int64)
    inverse = []
    for b in (0, 1):
        nxt = (b ^ (c >> 14)) & 1
        forward = ((c << 1) & 0x7FFF) ^ np.where(nxt == 1, CRC15_POLY, 0)
        inv = np.empty_like(forward)
        inv[forward] = c
        inverse.append(inv)
    table = np.zeros((8, 1 << 15), dtype=np.int8)
    for s in range(8):
        v = np.full(c.shape, s // 4)
        n = np.full(c.shape, s % 4 + 1)
        count = np.zeros(c.shape, dtype=np.int64)
        for k in range(14, -1, -1):
            b = (c >> k) & 1
            n = np.where(b == v, n + 1, 1)
            v = b
            stuffed = n == STUFF_RUN
            count += stuffed
            v = np.where(stuffed, 1 - b, v)
            n = np.where(stuffed, 1, n)
        table[s] = count
    return inverse[0], inverse[1], table


@lru_cache(maxsize=16)
def _classic_data_dp(v0: int, n0: int, bits: tuple[int, ...], p_one: float):
    """Dense DP over the data bits of a classic frame: state = (run state, CRC-15 register of
    the data bits alone, zero start; ISO 11898-1:2015 10.4.2.6 and 10.5). Returns (expected
    data stuff bits, P[8, 2^15], M[8, 2^15]: the most data stuff bits reaching each state,
    < 0 if unreachable). A data bit b maps register c to T_b(c), a permutation of 0..2^15-1,
    so each step is a gather through T_b's inverse."""
    inv0, inv1, _ = _crc_tables()
    inverse = (inv0, inv1)
    size = 1 << 15
    neg = -30000                                  # unreachable (at most 16 data stuff bits)
    prob = np.zeros((8, size))
    best = np.full((8, size), neg, dtype=np.int16)
    prob[_state(v0, n0), 0] = 1.0
    best[_state(v0, n0), 0] = 0
    live = {_state(v0, n0)}
    expected = 0.0
    for bit in bits:
        nprob = np.zeros((8, size))
        nbest = np.full((8, size), neg, dtype=np.int16)
        nlive = set()
        for s in live:
            v, n = divmod(s, 4)
            n += 1
            mass = prob[s].sum()
            for b, w in _choices(bit, p_one):
                v2, n2, st = _step(v, n, b)
                t = _state(v2, n2)
                nprob[t] += w * prob[s][inverse[b]]
                np.maximum(nbest[t], best[s][inverse[b]] + st, out=nbest[t])
                expected += w * mass * st
                nlive.add(t)
        prob, best, live = nprob, nbest, nlive
    return expected, prob, best


def _classic_stats(cob_id: int, n_bytes: int, free_mask: int, p_one: float) -> FrameStats:
    fields = frame_fields(cob_id, bytes(n_bytes))
    v, n, head_stuff = _run_after(fields[:_CLASSIC_HEAD])
    expected, prob, best = _classic_data_dp(v, n, _data_bits(n_bytes, free_mask), p_one)
    # final CRC = CRC(data alone) XOR CRC(header followed by zeros): the CRC is linear
    offset = crc15(fields)
    _, _, table = _crc_tables()
    crc_stuff = table[:, np.arange(1 << 15) ^ offset]
    mean_crc = float(np.einsum("ij,ij->", prob, crc_stuff))
    worst_tail = int((best + crc_stuff).max())          # unreachable states stay far below 0
    fixed = _CLASSIC_HEAD + 8 * n_bytes + 15 + head_stuff + TRAILER_BITS + INTERMISSION_BITS
    return FrameStats(float(fixed + expected + mean_crc), 0.0, fixed + worst_tail, 0)


@lru_cache(maxsize=65536)
def pdo_frame_stats(cob_id: int, n_bytes: int, free_mask: int, p_one: float = 0.5, *, fd: bool = False,
                    brs: bool = True) -> FrameStats:
    """Exact bits of one base-format data frame over its payloads (``FrameStats``).

    ``free_mask``: which of the 8 * ``n_bytes`` data bits carry taxel values (bit 8n-1 of the
    mask = the first data bit on the wire, byte 0's most significant bit); the other bits are 0.
    ``mean``: each free bit is 1 with probability ``p_one``, independently; ``worst``: the
    longest frame over every value of the free bits. Classic CAN (``fd=False``, ISO 11898-1:2015
    CBFF, as ``bus_timing.frame_bits``): all bits nominal; CAN FD (FBFF, as
    ``bus_timing.fd_frame_bits``): (nominal, data) phases, all nominal with ``brs=False``.
    """
    if not isinstance(fd, bool) or not isinstance(brs, bool):
        raise ParameterError("fd/brs", (fd, brs), "must be True or False")
    _check_frame_args(cob_id, n_bytes, free_mask, fd)
    p_one = _check_probability("p_one", p_one)
    if fd:
        return _fd_stats(cob_id, n_bytes, free_mask, p_one, brs)
    return _classic_stats(cob_id, n_bytes, free_mask, p_one)


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


def node_frames(taxels: int, payload: str, fd: bool) -> list[tuple[int, int, int]]:
    """The TPDO frames of one node with ``taxels`` taxel values: [(n_bytes, taxels, free_mask)].

    Full frames of 8 (classic) or 64 (FD) bytes in taxel order, the rest in the last frame
    (whole bytes, FD: rounded up to a valid FD length); see the module docstring."""
    bits = PAYLOAD_BITS[payload]
    cap_bytes = FD_MAX_BYTES if fd else CLASSIC_MAX_BYTES
    per_frame = cap_bytes * 8 // bits
    frames = []
    left = taxels
    while left > 0:
        k = min(left, per_frame)
        used_bytes = -(-k * bits // 8)
        n_bytes = _fd_length(used_bytes) if fd else used_bytes
        if bits == 1:   # taxel j in bit j mod 8 of byte j div 8; on the wire byte 0 first, MSB first
            mask = 0
            for j in range(k):
                mask |= 1 << (8 * n_bytes - 1 - (8 * (j // 8) + 7 - j % 8))
        else:           # whole bytes 0 .. used_bytes - 1
            mask = ((1 << (8 * used_bytes)) - 1) << (8 * (n_bytes - used_bytes))
        frames.append((n_bytes, k, mask))
        left -= k
    return frames


def _check_int(name: str, value, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ParameterError(name, value, f"must be an integer >= {low}")
    return value


def skin_layout(n_taxels: int, *, taxels_per_node: int = 1, payload: str = "decision", fd: bool = False,
                brs: bool = True, channels: int | None = None) -> SkinLayout:
    """Nodes, channels and TPDO frames of a skin (module docstring: packing, COB-IDs).

    ``n_taxels`` taxels in nodes of ``taxels_per_node`` (1: the chapter's one-taxel nodes; the
    last node holds the remainder), each taxel value ``payload`` (``PAYLOAD_BITS``), on classic
    CAN or CAN FD (``fd``, with bit-rate switch ``brs``), over ``channels`` CAN channels (default:
    the fewest that hold the nodes, <= 127 per channel, and their frames, <= 1023 per channel).
    """
    _check_int("n_taxels", n_taxels, 1)
    _check_int("taxels_per_node", taxels_per_node, 1)
    if payload not in PAYLOAD_BITS:
        raise ParameterError("payload", payload, f"must be one of {', '.join(PAYLOAD_BITS)}")
    if not isinstance(fd, bool) or not isinstance(brs, bool):
        raise ParameterError("fd/brs", (fd, brs), "must be True or False")
    n_nodes = -(-n_taxels // taxels_per_node)
    node_taxels = [taxels_per_node] * (n_nodes - 1) + [n_taxels - taxels_per_node * (n_nodes - 1)]
    frames_of = {k: node_frames(k, payload, fd) for k in set(node_taxels)}

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
    return SkinLayout(n_taxels, taxels_per_node, payload, fd, brs, tuple(out))


# ---------------------------------------------------------------- bits per cycle and bus use

@dataclass(frozen=True)
class ChannelBits:
    """Bits of one channel in one SYNC cycle: its PDOs (mean and worst case) and its SYNC.

    ``frames``: PDO frames of a synchronous cycle; ``expected_frames``: how many go out on
    average (= ``frames`` when synchronous). ``*_nominal`` include the SYNC frame;
    ``heartbeat_bits``: one heartbeat of every node of the channel (sent once per heartbeat
    period, not per cycle)."""

    channel: int
    nodes: int
    taxels: int
    frames: int
    expected_frames: float
    sync_bits: int
    mean_nominal: float
    mean_data: float
    worst_nominal: int
    worst_data: int
    heartbeat_bits: int

    @property
    def mean_bits(self) -> float:
        return self.mean_nominal + self.mean_data

    @property
    def worst_bits(self) -> int:
        return self.worst_nominal + self.worst_data


def layout_cycle_bits(layout: SkinLayout, *, p_one: float = 0.5,
                      p_change: float | None = None) -> tuple[ChannelBits, ...]:
    """Exact bits per SYNC cycle of every channel of ``layout`` (``ChannelBits``).

    Synchronous (``p_change=None``): every PDO frame every cycle. Event-driven: a frame carrying
    k taxels is sent with probability 1 - (1 - p_change)^k; the worst case stays every frame.
    ``p_one``: P(taxel bit = 1) for the mean payload (``pdo_frame_stats``). Every cycle adds the
    channel's SYNC (0x080, no data, classic)."""
    p_one = _check_probability("p_one", p_one)
    if p_change is not None:
        p_change = _check_probability("p_change", p_change)
    sync = frame_bits(SYNC_COB_ID, b"")
    out = []
    for ch in layout.channels:
        mean_nom = mean_dat = 0.0
        worst_nom = worst_dat = 0
        expected = 0.0
        for f in ch.frames:
            st = pdo_frame_stats(f.cob_id, f.n_bytes, f.free_mask, p_one, fd=layout.fd, brs=layout.brs)
            sent = 1.0 if p_change is None else 1.0 - (1.0 - p_change) ** f.taxels
            expected += sent
            mean_nom += sent * st.mean_nominal
            mean_dat += sent * st.mean_data
            worst_nom += st.worst_nominal
            worst_dat += st.worst_data
        hb = sum(frame_bits(HEARTBEAT_BASE + node, bytes([NMT_OPERATIONAL])) for node in ch.node_ids)
        out.append(ChannelBits(ch.index, len(ch.node_ids), ch.taxels, len(ch.frames), expected, sync,
                               mean_nom + sync, mean_dat, worst_nom + sync, worst_dat, hb))
    return tuple(out)


def _check_rate(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise ParameterError(name, value, "must be a finite number > 0")
    return float(value)


@dataclass(frozen=True)
class ChannelUse:
    """Bus use of one channel: ``load`` (mean cycle + heartbeats, fraction of the SYNC period),
    ``worst_load`` (worst-case cycle), ``max_sync_hz`` (highest SYNC rate the worst-case cycle
    fits, heartbeats deducted), times in seconds per cycle."""

    bits: ChannelBits
    mean_cycle_s: float
    worst_cycle_s: float
    heartbeat_s_per_s: float
    load: float
    worst_load: float
    max_sync_hz: float


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


def layout_bus_use(layout: SkinLayout, *, nominal_bitrate: float, data_bitrate: float | None = None,
            sync_period_s: float = 0.01, heartbeat_period_s: float | None = None, p_one: float = 0.5,
            p_change: float | None = None) -> LayoutUse:
    """Bus load and highest SYNC rate of every channel (``LayoutUse``).

    A cycle lasts nominal bits / ``nominal_bitrate`` + data-phase bits / ``data_bitrate``
    (CAN FD with BRS; ``None`` = the nominal rate). Heartbeats (every ``heartbeat_period_s``,
    ``None`` = not counted) take heartbeat bits / nominal rate / period of every second.
    load = mean cycle time / SYNC period + heartbeat share; max SYNC rate = (1 - heartbeat
    share) / worst-case cycle time (as ``fusion-center bandwidth`` computes it for a scene)."""
    nb = _check_rate("nominal_bitrate", nominal_bitrate)
    db = nb if data_bitrate is None else _check_rate("data_bitrate", data_bitrate)
    period = _check_rate("sync_period_s", sync_period_s)
    hb_period = None if heartbeat_period_s is None else _check_rate("heartbeat_period_s", heartbeat_period_s)
    out = []
    for bits in layout_cycle_bits(layout, p_one=p_one, p_change=p_change):
        mean_s = bits.mean_nominal / nb + bits.mean_data / db
        worst_s = bits.worst_nominal / nb + bits.worst_data / db
        hb = 0.0 if hb_period is None else bits.heartbeat_bits / nb / hb_period
        out.append(ChannelUse(bits, mean_s, worst_s, hb, mean_s / period + hb, worst_s / period + hb,
                              max(0.0, 1.0 - hb) / worst_s))
    return LayoutUse(tuple(out))


def channels_needed(n_taxels: int, *, nominal_bitrate: float, data_bitrate: float | None = None,
                    sync_period_s: float = 0.01, heartbeat_period_s: float | None = None,
                    max_load: float = 1.0, **layout_kwargs) -> int | None:
    """Fewest channels whose every channel fits its worst-case cycle (plus heartbeats) into
    ``max_load`` of the SYNC period; ``None`` if even one node per channel does not fit.
    ``layout_kwargs``: ``taxels_per_node``, ``payload``, ``fd``, ``brs`` of ``skin_layout``."""
    limit = _check_rate("max_load", max_load)
    first = skin_layout(n_taxels, **layout_kwargs)
    for n_channels in range(len(first.channels), first.n_nodes + 1):
        layout = first if n_channels == len(first.channels) else skin_layout(n_taxels, channels=n_channels,
                                                                              **layout_kwargs)
        use = layout_bus_use(layout, nominal_bitrate=nominal_bitrate, data_bitrate=data_bitrate,
                      sync_period_s=sync_period_s, heartbeat_period_s=heartbeat_period_s)
        if max(c.worst_load for c in use.channels) <= limit:
            return n_channels
    return None
