"""A cycle whose taxel frames were lost or late is no "contact ended" for the slip stage.

Found under load (the CI's `test_grip_patch_scenes`, reproduced with spinning processes): the
demo's centre closed one cycle of the lift with none of the pads' frames in (the twins stalled),
the slip stage read "no taxel present" as the contact's end, took its reference again three
cycles later wherever the sliding contact had got to, and the grip stage's slip cue started over
too - the whole slide went unseen, the command was never raised, the part slid 30 mm off the pads
(PART_LOST). The same with a replay of a demo trace from which one cycle's taxel TPDOs were cut
(``grasp_lift_patch``: no slip flag in the whole episode, the law probing down instead of
raising). Now such a cycle is ``observed`` False and the episode goes on
(``SlipTracker.unobserved``); the grip stage holds its slip flag through it."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_center.service.grip_stage import GripStage
from fusion_center.service.pipeline import CyclePipeline
from taxel_net.scene import load_scene

from test_pipeline_fastpath import closed_cycle

SCENE = load_scene("slipping")          # matrix57's 57 taxels, the slip stage on
XY = np.array([[t.x, t.y] for t in SCENE.taxels])
START, SPEED, RADIUS, ONSET = np.array([31.0, 41.0]), 2.0, 16.0, 20


def footprint(cycle: int) -> np.ndarray:
    """The taxels under a contact at rest until ONSET, then sliding along +x by SPEED a cycle."""
    centre = START + [SPEED * max(0, cycle - ONSET), 0.0]
    return np.hypot(*(XY - centre).T) <= RADIUS


def wires(cycles: int = 45) -> list[np.ndarray]:
    return [np.where(footprint(k), 1, -1).astype(np.int8) for k in range(cycles)]


def slip_records(ws) -> list[dict]:
    pipe = CyclePipeline(SCENE, truth=False)
    return [pipe.evaluate(closed_cycle(w, k))["slip"] for k, w in enumerate(ws)]


def test_the_contact_slides_and_is_flagged_without_losses():
    base = slip_records(wires())
    assert all(s["contact"] and s["observed"] for s in base)
    flagged = next(k for k, s in enumerate(base) if s["slipping"])
    assert ONSET < flagged <= ONSET + 6 and all(s["slipping"] for s in base[flagged:])


@pytest.mark.parametrize("offset", [-1, 0, 1, 2, 5, 10])
def test_a_lost_cycle_in_a_slide_neither_ends_the_contact_nor_hides_the_slip(offset):
    base = slip_records(wires())
    flagged = next(k for k, s in enumerate(base) if s["slipping"])
    lost = flagged + offset
    ws = wires()
    ws[lost] = np.zeros(SCENE.n, dtype=np.int8)            # no taxel frame of that cycle in
    got = slip_records(ws)
    assert got[lost]["contact"] and not got[lost]["observed"] and got[lost]["displacement"] is None
    assert got[lost]["slipping"] == got[lost - 1]["slipping"]
    # flagged where it was, or one cycle later when the lost cycle was one of the run that flags it;
    # from then on every cycle slipping (before: the reference taken again mid-slide, no flag for cycles)
    again = next(k for k, s in enumerate(got) if s["slipping"])
    assert again == flagged + (offset in (-1, 0))
    assert all(s["slipping"] for s in got[again:]), [k for k, s in enumerate(got) if not s["slipping"]]
    assert [s["onset_cycle"] for s in got[again:]] == [got[again]["onset_cycle"]] * (len(got) - again)
    assert all(s["observed"] for k, s in enumerate(got) if k != lost)


def test_a_cycle_that_heard_the_contact_absent_ends_it_one_that_did_not_hear_it_does_not():
    ws = wires(30)
    contact = footprint(29)
    ws.append(np.where(contact, 0, -1).astype(np.int8))    # only taxels off the contact heard
    ws.append(np.where(contact, -1, 0).astype(np.int8))    # the contact's taxels heard: absent
    got = slip_records(ws)
    assert got[30]["contact"] and not got[30]["observed"]
    assert not got[31]["contact"] and got[31]["observed"] and not got[31]["slipping"]


def test_the_grip_stage_holds_its_slip_flag_through_an_unobserved_cycle():
    """The grip stage's per-cycle slip cue (a new farthest displacement in this cycle or the
    ``slip_hold`` - 1 before) goes on through a cycle that measured nothing of the contact, and
    only then: a cycle taking the reference (displacement None, observed) gives no flag."""
    stage = GripStage(load_scene("grasp_lift_patch"), noise_band=1.0, slip_hold=3)

    def cue(cycle, displacement, observed=True):
        slip = {"contact": True, "observed": observed, "displacement": displacement, "force_ratio": None}
        return stage.slip_now({"cycle": cycle, "t": cycle * 0.01, "slip": slip})

    assert [cue(0, 0.2), cue(1, 0.3), cue(2, 1.6)] == [False, False, True]
    assert [cue(3, None, observed=False), cue(4, None, observed=False), cue(5, None, observed=False)] == \
        [True, True, False]
    assert cue(6, 3.1) and not cue(9, 3.1)
    assert not cue(10, None, observed=True) and not cue(11, None, observed=False)  # no peak in 3 cycles


def test_a_lost_cycle_right_after_the_reference_is_taken_again_keeps_the_contact():
    """The grip stage has the tracker take its reference again (``reset``) once the footprint has
    formed; a lost cycle right after must not read as the contact's end (the stage would wait
    ``settle_s`` and take the reference again, mid-slide)."""
    pipe = CyclePipeline(SCENE, truth=False)
    ws = wires(30)
    got = []
    for k, w in enumerate(ws):
        if k == 12:
            pipe.physical.slip.reset()                      # what GripStage's rebase does
        if k == 13:
            w = np.zeros(SCENE.n, dtype=np.int8)
        got.append(pipe.evaluate(closed_cycle(w, k))["slip"])
    assert got[13]["contact"] and not got[13]["observed"]
    assert all(s["contact"] for s in got)
    assert got[-1]["slipping"]


def test_a_part_of_the_footprint_is_no_motion_and_a_contact_unseen_too_long_ends():
    ws = wires(60)
    contact = np.flatnonzero(footprint(8))
    ws[8] = ws[8].copy()
    ws[8][contact[0]] = 0                                   # one taxel of the contact not heard
    got = slip_records(ws[:20])
    assert not got[8]["observed"] and got[8]["displacement"] is None and got[8]["contact"]
    assert all(s["displacement"] == 0.0 for s in got[3:8] + got[9:20])   # at rest: no motion at all
    lost = [np.zeros(SCENE.n, dtype=np.int8)] * 15          # the contact's node gone for good
    got = slip_records(wires(25) + lost)
    unseen = [s["contact"] for s in got[25:]]
    assert unseen == [True] * 10 + [False] * 5              # max_unobserved: 10 cycles
