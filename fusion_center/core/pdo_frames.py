"""Exact bits of one PDO frame over its payloads: mean and worst case (issue 14).

Numerical core: no CAN, no I/O. A PDO frame of a skin layout (``layouts``) has a fixed COB-ID
and length; what varies from cycle to cycle is its payload, and with it the number of dynamic
stuff bits. This module prices such a frame exactly, two ways over its payloads:

* ``worst``: the longest frame over every value of the taxel bits (padding fixed at 0) - the
  exact maximum for that COB-ID and length, never above the Davis et al. bound of
  ``bus_timing.worst_case_frame_bits`` (classic) or ``fd_frame_bits_estimate`` (FD);
* ``mean``: the expectation when every taxel bit is 1 with probability ``p_one``,
  independently (0.5: uniform payloads; 0: all taxels 0, e.g. a quiet skin's decisions).

A frame may start with a **cycle tag**: one leading byte (data byte 0, the first 8 data bits
on the wire) holding the counter of the SYNC the taxels were sampled at. The tag takes each of
``tag_values`` equally often (a SYNC counter with overflow value N runs 1..N, CiA 301 0x1019),
independently of the taxel bits; the mean averages over the tag values, the worst case is the
maximum over them.

Both are computed by dynamic programming over the stuffing state (value and length of the
current run, and for classic frames the CRC-15 register, whose bits are stuffed too), checked
in the tests against enumerating every payload (and tag value) with ``bus_timing.frame_bits``
/ ``fd_frame_bits``. Classic frames: ISO 11898-1:2015 CBFF, all bits at the nominal rate; CAN
FD: FBFF, (nominal, data) phases as ``fd_frame_bits``, all nominal without bit-rate switch.
"""

from __future__ import annotations

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
    frame_fields,
)

CLASSIC_MAX_BYTES = 8
FD_MAX_BYTES = 64
TAG_BITS = 8                            # the cycle tag: one leading UNSIGNED8 data byte
_FD_BRS_INDEX = 16                      # BRS in the FD base format (SOF = 0)
_FD_HEAD = 22                           # SOF..DLC of the FD base format
_CLASSIC_HEAD = 19                      # SOF..DLC of the classic base format


class PhaseBits:
    """Mean and worst-case bits split into the nominal and the data phase (CAN FD with BRS);
    a classic frame or cycle has no data phase. Shared by ``FrameStats`` (one frame) and
    ``layouts.ChannelBits`` (one channel's cycle): ``mean_bits`` / ``worst_bits`` are the sums."""

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


@dataclass(frozen=True)
class FrameStats(PhaseBits):
    """Bits of one PDO frame over its payloads: (nominal, data) phase, mean and worst case.

    Classic frames and FD frames without BRS have no data phase (``*_data`` = 0). The nominal
    part of an FD frame with BRS does not depend on the payload (SOF..BRS, CRC delimiter, ACK,
    EOF, intermission), so ``mean_nominal == worst_nominal`` there."""

    mean_nominal: float
    mean_data: float
    worst_nominal: int
    worst_data: int


def check_probability(name: str, p) -> float:
    if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 <= p <= 1.0:
        raise ParameterError(name, p, "must be a probability in [0, 1]")
    return float(p)


def _check_frame_args(cob_id, n_bytes, free_mask, fd: bool, tag_values) -> tuple[int, ...]:
    if isinstance(cob_id, bool) or not isinstance(cob_id, int) or not 0 <= cob_id <= 0x7FF:
        raise ParameterError("cob_id", cob_id, "must be an 11-bit identifier 0..0x7FF")
    allowed = FD_LENGTHS if fd else tuple(range(CLASSIC_MAX_BYTES + 1))
    if isinstance(n_bytes, bool) or not isinstance(n_bytes, int) or n_bytes not in allowed:
        raise ParameterError("n_bytes", n_bytes, f"must be one of {allowed} for {'CAN FD' if fd else 'classic CAN'}")
    if isinstance(free_mask, bool) or not isinstance(free_mask, int) or not 0 <= free_mask < (1 << (8 * n_bytes)):
        raise ParameterError("free_mask", free_mask, f"must be a bit mask of the {8 * n_bytes} data bits")
    tags = tuple(tag_values)
    if tags:
        if n_bytes < 1 or any(isinstance(t, bool) or not isinstance(t, int) or not 0 <= t <= 0xFF for t in tags):
            raise ParameterError("tag_values", tag_values, "must be byte values 0..255 of a frame with >= 1 data byte")
        if free_mask >> (8 * n_bytes - TAG_BITS):
            raise ParameterError("free_mask", free_mask, "must leave data byte 0 (the cycle tag) to the tag")
    return tags


FREE = 2     # a bit the payload sets (1 with probability p_one), as opposed to a fixed 0 or 1


def _data_bits(n_bytes: int, free_mask: int, skip: int = 0) -> tuple[int, ...]:
    """Each data bit in transmission order (byte 0 first, each byte MSB first) from bit
    ``skip`` on: FREE for a taxel bit, 0 for padding; bit 8n-1-k of ``free_mask`` = the k-th
    bit on the wire."""
    n = 8 * n_bytes
    return tuple(FREE if (free_mask >> (n - 1 - k)) & 1 else 0 for k in range(skip, n))


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


def _run_after(bits, v: int = -1, n: int = 0) -> tuple[int, int, int]:
    """Deterministic stuffing of fixed bits from run (v, n): (run value, run length, stuff bits)."""
    s = 0
    for b in bits:
        v, n, st = _step(v, n, b)
        s += st
    return v, n, s


def _crc_step(reg: int, b: int) -> int:
    nxt = (b ^ (reg >> 14)) & 1
    return ((reg << 1) & 0x7FFF) ^ (CRC15_POLY if nxt else 0)


def _tag_start(v0: int, n0: int, tags: tuple[int, ...], stuff_last: bool = True):
    """The stuffing state after the cycle tag, one entry per (run state, CRC-15 register of the
    tag bits from 0): (entries ((state, register, probability, most stuff bits), ...), expected
    stuff bits). Each tag value has weight 1 / len(tags); without tags the start state itself.
    ``stuff_last=False``: a stuff condition met at the tag's last bit inserts nothing (the tag
    ends the FD data field)."""
    if not tags:
        return ((_state(v0, n0), 0, 1.0, 0),), 0.0
    w = 1.0 / len(tags)
    merged: dict[tuple[int, int], list] = {}
    expected = 0.0
    for t in tags:
        v, n, s, reg = v0, n0, 0, 0
        for k in range(TAG_BITS):
            b = (t >> (TAG_BITS - 1 - k)) & 1
            v, n, st = _step(v, n, b)
            if k == TAG_BITS - 1 and not stuff_last:
                st = 0
            s += st
            reg = _crc_step(reg, b)
        expected += w * s
        entry = merged.setdefault((_state(v, n), reg), [0.0, -1])
        entry[0] += w
        entry[1] = max(entry[1], s)
    return tuple((st, reg, p, b) for (st, reg), (p, b) in sorted(merged.items())), expected


@lru_cache(maxsize=4096)
def _run_dp(start, bits: tuple[int, ...], p_one: float, stuff_last: bool) -> tuple[float, int]:
    """Dynamic stuffing (ISO 11898-1:2015 10.5) over ``bits`` (0, 1 or FREE: 1 with
    probability ``p_one``) from the run states of ``start`` (``_tag_start`` entries; the CRC
    register is not needed here): (expected stuff bits, the most stuff bits over every value
    of the free bits). With ``stuff_last=False`` the condition met at the last bit inserts
    nothing (FD: the end of the data field)."""
    prob = [0.0] * 8
    best = [-1] * 8
    for s, _, p, b in start:
        prob[s] += p
        best[s] = max(best[s], b)
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


def _fd_stats(cob_id: int, n_bytes: int, free_mask: int, p_one: float, brs: bool, tags) -> FrameStats:
    fields = fd_frame_fields(cob_id, bytes(n_bytes), brs=brs)
    head = fields[:_FD_HEAD]
    # SOF..BRS: fixed bits, their stuff bits are nominal (one right after BRS would be data phase)
    v, n, head_stuff = _run_after(head[:_FD_BRS_INDEX])
    v, n, st_brs = _step(v, n, head[_FD_BRS_INDEX])
    if tags:   # ESI, DLC fixed (the tag follows them), then the tag, then the taxel bits
        v, n, st_fixed = _run_after(head[_FD_BRS_INDEX + 1:], v, n)
        rest = _data_bits(n_bytes, free_mask, TAG_BITS)
        start, mean_s = _tag_start(v, n, tags, stuff_last=bool(rest))
        worst_s = max(b for *_, b in start)
        if rest:
            m, worst_s = _run_dp(start, rest, p_one, False)
            mean_s += m
    else:      # ESI, DLC and data; never empty
        st_fixed = 0
        start, _ = _tag_start(v, n, ())
        mean_s, worst_s = _run_dp(start, tuple(head[_FD_BRS_INDEX + 1:]) + _data_bits(n_bytes, free_mask), p_one,
                                  False)
    width = 17 if n_bytes <= 16 else 21
    fixed = 1 + (4 + width) + (4 + width) // 4          # stuff count, CRC, fixed stuff bits
    tail = TRAILER_BITS + INTERMISSION_BITS
    nominal = _FD_BRS_INDEX + 1 + head_stuff + tail
    data_fixed = (len(fields) - _FD_BRS_INDEX - 1) + fixed + st_brs + st_fixed
    if brs:
        return FrameStats(float(nominal), float(data_fixed + mean_s), nominal, data_fixed + worst_s)
    return FrameStats(float(nominal + data_fixed + mean_s), 0.0, nominal + data_fixed + worst_s, 0)


_REGISTERS = np.arange(1 << 15)              # every CRC-15 register value


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
def _classic_data_dp(start, bits: tuple[int, ...], p_one: float):
    """Dense DP over the data bits of a classic frame: state = (run state, CRC-15 register of
    the data bits alone, zero start; ISO 11898-1:2015 10.4.2.6 and 10.5), from the entries of
    ``start`` (``_tag_start``: after the cycle tag, or the state after the DLC). Returns
    (expected data stuff bits after ``start``, P[8, 2^15], M[8, 2^15]: the most data stuff bits
    reaching each state, the tag's included, < 0 if unreachable). A data bit b maps register c
    to T_b(c), a permutation of 0..2^15-1, so each step is a gather through T_b's inverse."""
    inv0, inv1, _ = _crc_tables()
    inverse = (inv0, inv1)
    size = 1 << 15
    neg = -30000                                  # unreachable (at most 16 data stuff bits)
    prob = np.zeros((8, size))
    best = np.full((8, size), neg, dtype=np.int16)
    for s, reg, p, b in start:
        prob[s, reg] += p
        best[s, reg] = max(int(best[s, reg]), b)
    live = {s for s, *_ in start}
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


def _classic_stats(cob_id: int, n_bytes: int, free_mask: int, p_one: float, tags) -> FrameStats:
    fields = frame_fields(cob_id, bytes(n_bytes))
    v, n, head_stuff = _run_after(fields[:_CLASSIC_HEAD])
    start, tag_stuff = _tag_start(v, n, tags)
    bits = _data_bits(n_bytes, free_mask, TAG_BITS if tags else 0)
    expected, prob, best = _classic_data_dp(start, bits, p_one)
    # final CRC = CRC(data alone) XOR CRC(header followed by zeros): the CRC is linear
    offset = crc15(fields)
    _, _, table = _crc_tables()
    crc_stuff = table.take(_REGISTERS ^ offset, axis=1)    # column c ^ offset (take: 2.5x a fancy index)
    mean_crc = float(np.einsum("ij,ij->", prob, crc_stuff))
    worst_tail = int((best + crc_stuff).max())          # unreachable states stay far below 0
    fixed = _CLASSIC_HEAD + 8 * n_bytes + 15 + head_stuff + TRAILER_BITS + INTERMISSION_BITS
    return FrameStats(float(fixed + tag_stuff + expected + mean_crc), 0.0, fixed + worst_tail, 0)


def pdo_frame_stats(cob_id: int, n_bytes: int, free_mask: int, p_one: float = 0.5, *, fd: bool = False,
                    brs: bool = True, tag_values=()) -> FrameStats:
    """Exact bits of one base-format data frame over its payloads (``FrameStats``).

    ``free_mask``: which of the 8 * ``n_bytes`` data bits carry taxel values (bit 8n-1 of the
    mask = the first data bit on the wire, byte 0's most significant bit); the other bits are 0.
    ``mean``: each free bit is 1 with probability ``p_one``, independently; ``worst``: the
    longest frame over every value of the free bits. ``tag_values``: data byte 0 is a cycle
    tag taking each of these values equally often (module docstring; empty: no tag). Classic
    CAN (``fd=False``, ISO 11898-1:2015 CBFF, as ``bus_timing.frame_bits``): all bits nominal;
    CAN FD (FBFF, as ``bus_timing.fd_frame_bits``): (nominal, data) phases, all nominal with
    ``brs=False``.
    """
    if not isinstance(fd, bool) or not isinstance(brs, bool):
        raise ParameterError("fd/brs", (fd, brs), "must be True or False")
    try:
        tags = tuple(tag_values)
    except TypeError:
        raise ParameterError("tag_values", tag_values, "must be a sequence of byte values 0..255") from None
    return _pdo_frame_stats(cob_id, n_bytes, free_mask, p_one, fd, brs, tags)


@lru_cache(maxsize=65536)
def _pdo_frame_stats(cob_id, n_bytes, free_mask, p_one, fd: bool, brs: bool, tags: tuple) -> FrameStats:
    tags = _check_frame_args(cob_id, n_bytes, free_mask, fd, tags)
    p_one = check_probability("p_one", p_one)
    if fd:
        return _fd_stats(cob_id, n_bytes, free_mask, p_one, brs, tags)
    return _classic_stats(cob_id, n_bytes, free_mask, p_one, tags)
