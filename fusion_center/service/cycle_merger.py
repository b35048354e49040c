"""The fuser's merge of the assemblers' parts (issue 14; :mod:`.assemblers`, *Merge*): per SYNC
the fuser sent, one :class:`~.assembler_parts.CyclePart` per channel group, merged into one
``ClosedCycle`` over every taxel. Pure: the caller passes the time.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field

import numpy as np

from taxel_net.patches import devices as scene_devices
from taxel_net.scene import Scene
from .aggregates import LatencyHistogram
from .assembler_parts import CyclePart, GroupLayout, group_layout
from .cycle_records import EMCY_PER_CYCLE, STATE_UNKNOWN, ClosedCycle, DeviceCycle, EmcyEvent

logger = logging.getLogger("fusion_center.service.assemblers")

# ---------------------------------------------------------------------------- the merge

@dataclass
class MergeStats:
    parts: int = 0
    complete: int = 0         # cycles with every group's part
    degraded: int = 0         # cycles with a missing part
    parts_missing: int = 0    # (cycle, group) pairs without a part
    late_parts: int = 0       # parts for a cycle already evaluated
    late_bootups: int = 0     # boot-ups of late parts carried on to the next cycle closed (CycleMerger.add_part)
    late_emcy: int = 0        # EMCYs of late parts carried on likewise, counted as they land in a record (first in it)
    unmatched_parts: int = 0  # parts for no SYNC this fuser sent
    duplicate_parts: int = 0
    by_group: dict = field(default_factory=dict)  # group -> parts received
    reconnects: dict = field(default_factory=dict)  # group -> times it came back during the run
    # messages refused by kind (assemblers._refuse): key (not signed with the run's key), message (no
    # message of the protocol, or over its size), hello (a hello refused), link (a part of a link not welcomed)
    refused: dict = field(default_factory=dict)
    # where a part's time goes (same-host clocks; across hosts only as good as their sync):
    to_send: LatencyHistogram = field(default_factory=LatencyHistogram)    # SYNC sent -> part sent
    transport: LatencyHistogram = field(default_factory=LatencyHistogram)  # part sent -> received

    def as_dict(self) -> dict:
        out = {k: v for k, v in vars(self).items() if not isinstance(v, LatencyHistogram)}
        out["by_group"] = dict(self.by_group)
        out["reconnects"] = dict(self.reconnects)
        out["refused"] = dict(self.refused)
        for name in ("to_send", "transport"):
            h = getattr(self, name)
            out[f"{name}_ms"] = {f"p{q}": None if h.percentile(q) is None else round(h.percentile(q), 3)
                                 for q in (50, 99)}
        return out


class CycleMerger:
    """Merges the groups' parts per SYNC into one :class:`ClosedCycle` over every taxel (module
    docstring, *Merge*). Pure: the caller passes the time; thread-safe (one lock)."""

    def __init__(self, scene: Scene, *, part_deadline_s: float):
        self.scene = scene
        self.n = scene.n
        self.n_devices = len(scene_devices(scene))
        self.patch = bool(scene.bus.patch_nodes)
        self.overflow = int(scene.bus.sync_counter)
        self.deadline_s = float(part_deadline_s)
        self.lock = threading.Lock()
        self.groups: dict[str, GroupLayout] = {}   # connected groups
        self.gone: set[str] = set()                # disconnected groups (their parts are missing)
        self.last_k: dict[str, int] = {}           # latest cycle a group sent a part for
        self.syncs: dict[int, tuple] = {}  # k -> (counter, sync_us, monotonic sent, time.time() sent)
        self.last_sync: tuple[int, int | None] | None = None
        self.parts: dict[int, dict[str, CyclePart]] = {}
        self.next_k: int | None = None
        self.sent = 0
        self.held_decisions = np.zeros(self.n, dtype=np.int8)
        self.held_readings = np.full(self.n, np.nan)
        self.stats = MergeStats()
        self.info: dict[int, dict] = {}  # k -> record fields of the merge (parts_missing, ...)
        # scene device -> t_us of its boot-up heard in a late part: an event, not the late cycle's data -
        # merged into the next cycle closed (the over-range tracker orders it by t_us against the EMCYs)
        self.carried_bootups: dict[int, int] = {}
        # a late part's EMCYs (in bus order, at most EMCY_PER_CYCLE) and the EMCYs it could not carry
        # (its own emcy_dropped and those beyond the bound): into the next cycle closed with the boot-ups
        self.carried_emcy: list[EmcyEvent] = []
        self.carried_emcy_dropped = 0

    # -- groups
    def add_group(self, layout: GroupLayout) -> str | None:
        """Register a group; a reason string when refused. A group of this run that
        disconnected comes back with the same channels (a reconnect, counted); channels that
        a connected group serves are refused, and so - once a SYNC went out - are channels
        of a disconnected group in another grouping."""
        with self.lock:
            name = layout.name
            connected = {c: g for g, lay in self.groups.items() for c in lay.channels}
            overlap = sorted(set(connected) & set(layout.channels))
            if overlap:
                served = sorted({connected[c] for c in overlap})
                return (f"scene channel(s) {overlap} are already served by another assembler (connected, "
                        f"group {', '.join(served)})")
            if name in self.gone:
                self.stats.reconnects[name] = self.stats.reconnects.get(name, 0) + 1
            else:
                clash = sorted(g for g in self.gone if set(self._channels(g)) & set(layout.channels))
                if clash and self.sent:
                    return (f"scene channel(s) {sorted(layout.channels)} differ from group(s) {', '.join(clash)} "
                            f"of this run: an assembler comes back with --serve {clash[0]}")
                self.gone.difference_update(clash)  # before the first SYNC: regrouped, nothing was missed
            self.groups[name] = layout
            self.gone.discard(name)
            self.stats.by_group.setdefault(name, 0)
            return None

    @staticmethod
    def _channels(name: str) -> list[int]:
        """The channels of a group name (``0-3`` / ``0,2,5``)."""
        out: list[int] = []
        for piece in name.split(","):
            first, _, last = piece.partition("-")
            out.extend(range(int(first), int(last or first) + 1))
        return out

    def remove_group(self, name: str) -> None:
        with self.lock:
            if self.groups.pop(name, None) is not None:
                self.gone.add(name)

    def count_refused(self, kind: str) -> None:
        with self.lock:
            self.stats.refused[kind] = self.stats.refused.get(kind, 0) + 1

    def covered(self) -> set[int]:
        with self.lock:
            return {c for g in self.groups.values() for c in g.channels}

    # -- SYNCs and parts
    def opened(self, counter: int | None, sync_us: int, now: float, wall: float | None = None) -> int:
        """The fuser sent a SYNC (called before it goes on the bus): its cycle number."""
        with self.lock:
            k = self.sent
            self.sent += 1
            self.syncs[k] = (counter, sync_us, now, wall)
            self.last_sync = (k, counter)
            if self.next_k is None:
                self.next_k = k
            return k

    def cycle_of(self, part: CyclePart) -> int | None:
        """The SYNC (cycle number) a part answers (lock held)."""
        if self.last_sync is None:
            return None
        last_k, last_counter = self.last_sync
        if self.overflow and part.sync_counter is not None and last_counter is not None:
            return last_k - (last_counter - part.sync_counter) % self.overflow
        return part.number

    def add_part(self, name: str, part: CyclePart, received_at: float | None = None) -> None:
        with self.lock:
            stats = self.stats
            stats.parts += 1
            stats.by_group[name] = stats.by_group.get(name, 0) + 1
            k = self.cycle_of(part)
            if received_at is not None and part.sent_at:
                stats.transport.add((received_at - part.sent_at) * 1e3)
                wall = self.syncs[k][3] if k in self.syncs else None
                if wall is not None:
                    stats.to_send.add((part.sent_at - wall) * 1e3)
            if k is None or k not in self.syncs:
                if k is not None and self.next_k is not None and k < self.next_k:
                    self._late(name, k, part)
                else:
                    stats.unmatched_parts += 1
                return
            if self.next_k is not None and k < self.next_k:
                self._late(name, k, part)
                return
            got = self.parts.setdefault(k, {})
            if name in got:
                stats.duplicate_parts += 1
                return
            got[name] = part
            self.last_k[name] = max(k, self.last_k.get(name, -1))

    def _late(self, name: str, k: int, part: CyclePart) -> None:
        """A part for a cycle already evaluated (lock held): counted, never mixed in - but its
        boot-ups and EMCYs are events the cycle's record did not get (a node that restarted by
        itself would stay flagged over range for good; one over range again after its restart
        would be cleared while clipped: it sends EMCY 0x3000 on the rising edge only): they go
        into the next cycle closed, with their t_us. Only a part newer than every part this group
        sent before (``k`` above ``last_k``: a part held up on an in-order link) - a duplicate or a
        replayed part would re-apply an old boot-up after the EMCY that came since."""
        self.stats.late_parts += 1
        if k <= self.last_k.get(name, -1):
            return
        self.last_k[name] = k
        for device, t_us in part.bootups:
            self.stats.late_bootups += 1
            self.carried_bootups[device] = max(t_us, self.carried_bootups.get(device, t_us))
        kept = part.emcy[:max(EMCY_PER_CYCLE - len(self.carried_emcy), 0)]
        self.carried_emcy.extend(kept)  # counted late_emcy when they land in a record (_merge)
        self.carried_emcy_dropped += part.emcy_dropped + len(part.emcy) - len(kept)

    def emit(self, now: float, *, final: bool = False) -> list[ClosedCycle]:
        """The cycles now decided, in SYNC order (``final``: every cycle sent, missing parts missing)."""
        out = []
        with self.lock:
            while self.next_k is not None and self.next_k in self.syncs:
                k = self.next_k
                counter, sync_us, sent, _ = self.syncs[k]
                got = self.parts.get(k, {})
                names = sorted(set(self.groups) | self.gone)
                missing = []
                wait = False
                for name in names:
                    if name in got:
                        continue
                    if final or name in self.gone or self.last_k.get(name, -1) > k or now - sent > self.deadline_s:
                        missing.append(name)
                    else:
                        wait = True
                        break
                if wait or not names:
                    break
                out.append(self._merge(k, counter, sync_us, got, missing))
                self.parts.pop(k, None)
                del self.syncs[k]
                self.next_k = k + 1
        return out

    def pending(self) -> int:
        with self.lock:
            return len(self.syncs)

    def _merge(self, k: int, counter, sync_us: int, got: dict[str, CyclePart], missing: list[str]) -> ClosedCycle:
        n = self.n
        decisions = np.zeros(n, dtype=np.int8)
        readings = np.full(n, np.nan)
        received = np.zeros(n, dtype=bool)
        expected = np.ones(n, dtype=bool)    # a missing group's taxels: silent (expected, not received)
        missing_t = np.zeros(n, dtype=bool)
        states = np.full(n, STATE_UNKNOWN, dtype=np.int16)
        device = None
        if self.patch:
            nd = self.n_devices
            d_exp, d_miss = np.ones(nd, dtype=bool), np.zeros(nd, dtype=bool)
            d_states, d_complete = np.full(nd, STATE_UNKNOWN, dtype=np.int16), np.zeros(nd, dtype=bool)
        late = bad = 0
        # a late part's EMCYs (_late) first: they came before every EMCY of this cycle's parts
        carried = self.carried_emcy
        emcy: list[EmcyEvent] = list(carried)
        dropped = self.carried_emcy_dropped
        self.carried_emcy, self.carried_emcy_dropped = [], 0
        duplicates: set[int] = set()
        bootups: list = []
        close_after = 0
        by = []
        for name, part in got.items():
            layout = self.groups.get(name)
            if layout is None:  # disconnected since: its layout is still valid (by channels)
                layout = group_layout(self.scene, part.channels)
            idx = layout.taxels
            decisions[idx] = part.decisions
            if part.readings is not None:
                readings[idx] = part.readings
            received[idx] = part.received
            expected[idx] = part.expected
            missing_t[idx] = part.missing
            states[idx] = part.states
            self.held_decisions[idx] = part.held_decisions
            if part.held_readings is not None:
                self.held_readings[idx] = part.held_readings
            if self.patch and part.devices is not None:
                dv = layout.devices
                d_exp[dv], d_miss[dv], d_states[dv], d_complete[dv] = part.devices
            late += part.late_frames
            bad += part.bad_frames
            dropped += part.emcy_dropped
            emcy.extend(part.emcy)
            duplicates.update(part.duplicates)
            bootups.extend(part.bootups)
            close_after = max(close_after, part.closed_after_us)
            by.append(part.closed_by)
        if self.carried_bootups:  # a late part's (add_part): a device's latest boot-up is the one that counts
            bootups.extend(self.carried_bootups.items())
            self.carried_bootups = {}
        if len(bootups) > 1:
            latest: dict[int, int] = {}
            for booted, t_us in bootups:   # (not `device`: this function's DeviceCycle)
                latest[booted] = max(t_us, latest.get(booted, t_us))
            bootups = list(latest.items())
        if len(emcy) > EMCY_PER_CYCLE:
            # the carried ones (at most EMCY_PER_CYCLE: _late) kept whole, the cycle's own cut from the end;
            # never sorted by t_us: each assembler process stamps from its own first frame, so stamps of
            # different groups are not comparable (a group's own EMCYs keep their bus order)
            dropped += len(emcy) - EMCY_PER_CYCLE
            emcy = emcy[:EMCY_PER_CYCLE]
        self.stats.late_emcy += min(len(carried), EMCY_PER_CYCLE)  # the carried EMCYs that landed here
        if self.patch:
            device = DeviceCycle.make(expected=d_exp, missing=d_miss, states=d_states, complete=d_complete)
        if missing:
            closed_by = "part_missing"
            self.stats.degraded += 1
            self.stats.parts_missing += len(missing)
        else:
            self.stats.complete += 1
            closed_by = next((b for b in by if b != "complete"), "complete")
        self.info[k] = {"parts_missing": missing}
        if len(self.info) > 4096:
            self.info.pop(next(iter(self.info)))
        return ClosedCycle.make(
            cycle=k, sync_us=sync_us, close_us=sync_us + close_after, sync_counter=counter, closed_by=closed_by,
            decisions=decisions, readings=readings, received=received, expected=expected, missing=missing_t,
            held_decisions=self.held_decisions.copy(), held_readings=self.held_readings.copy(),
            late_frames=late, bad_frames=bad, emcy=tuple(emcy), states=states,
            duplicates=tuple(sorted(duplicates)), emcy_dropped=dropped, devices=device,
            bootups=tuple(sorted(bootups)))

