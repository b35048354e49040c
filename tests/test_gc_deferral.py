"""taxel_net.gcfreeze.defer / collect_due: while the centre runs, the cyclic collector's work is
done by its SYNC producer half a period after each SYNC, never by its receive thread between a
cycle's answers and its grip command (issue 23, docs/grip-control.md "SYNC -> command")."""

from __future__ import annotations

import gc
import threading

import pytest

from taxel_net import gcfreeze


@pytest.fixture
def collections():
    """(generation, thread name, deferred) of every collection made while the test runs."""
    seen: list[tuple[int, str, bool]] = []
    usual = gc.get_threshold()[0]

    def callback(phase, info):
        if phase == "start":
            seen.append((info["generation"], threading.current_thread().name, gc.get_threshold()[0] > usual))

    gc.callbacks.append(callback)
    try:
        yield seen
    finally:
        gc.callbacks.remove(callback)


def test_deferred_collections_wait_for_collect_due_which_follows_cpythons_rule(collections):
    assert gc.isenabled()
    before = gc.get_threshold()
    gc.collect()
    collections.clear()
    gcfreeze.defer()
    gcfreeze.defer()                                    # a second holder
    resumed = 0
    try:
        assert gc.get_threshold() == (before[0] * gcfreeze.BACKSTOP, before[1], before[2])
        kept = [[] for _ in range(3 * before[0])]      # containers: 3x the usual threshold
        assert collections == [] and gc.get_count()[0] > before[0]
        assert gcfreeze.collect_due() == 0              # what the collector would have done
        assert collections == [(0, threading.current_thread().name, True)]
        assert gcfreeze.collect_due() is None           # nothing due any more
        gen0 = []
        for _ in range(3 * (before[1] + 1)):            # generation 1 due once its count passed its threshold
            kept += [[] for _ in range(before[0] + 1)]
            ones = gc.get_count()[1]
            if gcfreeze.collect_due() == 1:
                break
            gen0.append(ones)
        assert [g for g, _, _ in collections].count(1) == 1 and ones > before[1] and max(gen0) <= before[1]
        gcfreeze.resume()
        resumed += 1
        assert gc.get_threshold() != before             # one holder left
    finally:
        for _ in range(2 - resumed):
            gcfreeze.resume()
    assert gc.get_threshold() == before
    assert gcfreeze.collect_due() is None               # not deferred: the collector's own rule
    gcfreeze.resume()                                    # one too many: nothing
    assert gc.get_threshold() == before


def test_cyclic_garbage_that_outlived_generation_1_is_still_collected_while_deferred(collections):
    """Cycles that lived through a generation-1 collection (now in the oldest generation) and
    died then: collect_due makes the full collection once generation 2's count passed its
    threshold, as the collector would - without it they piled up for the whole run (a review's
    finding: 28,050 dead objects kept after 1,000 periods, 242,150 after 9,000)."""
    import weakref

    class Cyclic:
        def __init__(self):
            self.me = self

    before = gc.get_threshold()
    gc.collect()
    gcfreeze.defer()
    try:
        old = Cyclic()
        alive = weakref.ref(old)
        promoted, kept = False, []
        for _ in range(3 * (before[1] + 1)):             # until a generation-1 collection promotes it
            kept.append([[] for _ in range(before[0] + 1)])  # allocations for generation 0's count
            if gcfreeze.collect_due() == 1:
                promoted = True
                break
        assert promoted
        del old                                          # dead now, in the oldest generation
        generations = []
        for _ in range(3 * (before[1] + 1) * (before[2] + 1)):
            kept.append([[] for _ in range(before[0] + 1)])
            generations.append(gcfreeze.collect_due())
            if generations[-1] == 2:
                break
        assert generations[-1] == 2, generations[-20:]
        assert alive() is None
        assert (2, threading.current_thread().name, True) in collections
    finally:
        gcfreeze.resume()
    assert gc.get_threshold() == before


def test_the_centre_s_receive_thread_does_not_collect_during_a_run(collections):
    """A demo run (the twins and the centre in one process): while the SYNC producer runs the
    collector runs (the run allocates), but never in the centre's receive thread, where a cycle's
    answers become its command; the SYNC producer does it. (During the boot before, it may.)"""
    from fusion_center.commands.demo import run_demo
    from taxel_net.resources import resolve_scene
    from taxel_net.scene import load_scene

    scene = load_scene(resolve_scene("grasp_lift_patch"))
    before = gc.get_threshold()
    service, _ = run_demo(scene, 150, keep_records=True)
    assert len(service.records) == 150
    during = {name for _, name, deferred in collections if deferred}
    assert "sync-producer" in during, collections
    assert "centre-receive" not in during, collections
    assert gc.get_threshold() == before                  # given back after the run
