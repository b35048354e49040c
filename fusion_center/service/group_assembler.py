"""One channel group's cycles as parts for the fuser (issue 14; :mod:`.assemblers`): a
``CycleAssembler`` over the group's buses, each closed cycle numbered by its SYNC and turned into
a :class:`~.assembler_parts.CyclePart` - pure (feed events, get parts), no link, no process; the
``fusion-center assemble`` process (:mod:`.assembler_process`) sends what it makes.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from taxel_net.patches import devices as scene_devices, node_label
from taxel_net.scene import Scene
from .assembler_parts import NMT_RESETS, CyclePart, group_layout
from .cycle_records import ClosedCycle, EmcyEvent


class GroupAssembler:
    """A ``CycleAssembler`` over one channel group, its cycles numbered by SYNC and turned
    into :class:`CyclePart` (pure: feed events, get parts)."""

    def __init__(self, scene: Scene, channels: Sequence[int]):
        from .cycles import CycleAssembler

        self.scene = scene
        self.layout = group_layout(scene, channels)
        self.assembler = CycleAssembler(self.layout.sub)
        full_labels = {k: node_label(d.channel, d.node_id) for k, d in enumerate(scene_devices(scene))}
        self._label = {sub_label: full_labels[int(self.layout.devices[d])]
                       for d, sub_label in enumerate(self.assembler.labels)}
        self.overflow = int(scene.bus.sync_counter)
        self.reset_at: int | None = None  # first assembler cycle after the master's reset broadcast
        self.heard_reset = False  # numbers count from the master's reset (told the fuser at a reconnect)
        self.last: tuple[int, int, int | None] | None = None  # (assembler cycle, number, counter)

    def note_reset(self) -> None:
        """The master's broadcast reset communication / node was fed: numbers restart."""
        self.reset_at = self.assembler.cycle + 1
        self.heard_reset = True

    def feed(self, timestamp_us: int, channel: int, can_id: int, data: bytes, flags: int = 0) -> list[CyclePart]:
        closed = self.assembler.feed_all(timestamp_us, channel, can_id, data, flags)
        if channel == 0 and can_id == 0 and len(data) == 2 and data[1] == 0 and data[0] in NMT_RESETS:
            self.note_reset()
        return [self.part(c) for c in closed]

    def number(self, closed: ClosedCycle) -> int:
        c, counter = closed.cycle, closed.sync_counter
        if self.reset_at is not None and c >= self.reset_at:
            number = (counter - 1) if counter else c - self.reset_at  # the master counts from 1
            self.reset_at = None
        elif self.last is None:
            number = (counter - 1) if counter else c
        else:
            last_c, last_number, last_counter = self.last
            step = c - last_c
            if counter and last_counter and self.overflow:
                step = (counter - last_counter - 1) % self.overflow + 1  # a jump: lost SYNCs
            number = last_number + step
        self.last = (c, number, counter)
        return number

    def part(self, closed: ClosedCycle) -> CyclePart:
        lay = self.layout
        readings = closed.readings if not np.isnan(closed.readings).all() else None
        held = closed.held_readings if not np.isnan(closed.held_readings).all() else None
        emcy = tuple(EmcyEvent(self._label.get(e.node, e.node), int(lay.taxels[e.taxel]), e.code, e.register,
                               e.manufacturer, e.t_us) for e in closed.emcy)
        dev = closed.devices
        return CyclePart(
            channels=lay.channels, number=self.number(closed), sync_counter=closed.sync_counter,
            closed_by=closed.closed_by, closed_after_us=int(closed.close_us - closed.sync_us),
            decisions=closed.decisions, readings=readings, received=closed.received,
            expected=np.asarray(closed.expected), missing=np.asarray(closed.missing),
            states=np.asarray(closed.states), held_decisions=closed.held_decisions, held_readings=held,
            late_frames=closed.late_frames, bad_frames=closed.bad_frames, emcy=emcy,
            emcy_dropped=closed.emcy_dropped, duplicates=tuple(int(lay.devices[d]) for d in closed.duplicates),
            devices=None if dev is None else (dev.expected, dev.missing, dev.states, dev.complete),
            bootups=tuple((int(lay.devices[d]), int(t_us)) for d, t_us in closed.bootups))
