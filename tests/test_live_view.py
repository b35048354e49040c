"""The live view (issue 12) fits 80 columns with labelled quantities, and counts the nodes by
NMT state; rendered with rich's ``Console(width=80, record=True)`` from records as the
service writes them (no bus needed)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
from rich.cells import cell_len
from rich.console import Console

from fusion_center.service.live import LiveView
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent


def service(scene_name: str, counters: dict | None = None):
    scene = load_scene(ROOT / "scenes" / f"{scene_name}.toml")
    labels = [t.node_id if t.channel == 0 else f"{t.channel}:{t.node_id}" for t in scene.taxels]  # as the service
    counters = counters or {"sync": 40, "tpdo1": 2203, "late": 3, "heartbeat": 406, "bootup": 114, "nmt": 3,
                            "sdo": 1890}
    return SimpleNamespace(scene=scene, bitrate=None, labels=labels,
                           stream=SimpleNamespace(counters_snapshot=lambda: counters))


def record(cycle=39, **extra):
    base = {
        "cycle": cycle, "closed_by": "window", "n_expected": 57, "n_received": 54, "present_count": 5,
        "present_nodes": [14, 19, 20, 21, 27], "mode": "decision", "U_G": -46, "threshold": -50.03537810239257,
        "decision": "H1", "p_h1": 0.09154015503888915, "decide_with": "additive", "degraded": True,
        "missing_nodes": [33], "silent_nodes": [18],
        "nodes_by_state": {"missing": [33], "silent": [18], "pre-operational": [40], "stopped": [41]},
        "rules": {
            "additive": {"U_G": -46, "threshold": -50.03537810239257, "decision": "H1", "p_h1": 0.0915},
            "multiplicative": {"U_G": 1.0530617357553812e-20, "threshold": 0.0, "decision": "H1", "p_h1": 0.003},
            "k-of-n": {"U_G": -46, "threshold": -48, "decision": "H1", "p_h1": None},
            "llr": {"U_G": -243.40993615840497, "threshold": 0.0, "decision": "H0", "p_h1": 1.94e-106},
            "np": {"U_G": -243.40993615840497, "threshold": -279.87730956068765, "decision": "H1"},
        },
        "area": 250.0, "contact_type": "small_object", "truth": "H1",
    }
    base.update(extra)
    return base


def render(view) -> list[str]:
    console = Console(width=80, record=True, color_system=None, force_terminal=False)
    console.print(view)
    return console.export_text().splitlines()


@pytest.mark.parametrize("bus", [None, "udp_multicast 239.74.163.2 (command line)",
                                 "socketcan can0, 500 kbit/s (CAN_INTERFACE)"])
def test_fits_80_columns_uncut(bus):
    view = LiveView(service("matrix57"), cycles=200, bus=bus)
    for k in range(120):  # more decisions than the strip shows
        view.update(record(cycle=k, decision="H1" if k % 3 else "H0"))
    lines = render(view)
    assert max(cell_len(line) for line in lines) <= 80, "\n".join(lines)
    assert not any("…" in line for line in lines), "\n".join(lines)  # nothing cut to "cyc…"
    text = "\n".join(lines)
    if bus:
        assert bus.split(" (")[0].split(",")[0] in text


def test_quantities_are_labelled():
    view = LiveView(service("matrix57"), cycles=200)
    view.update(record())
    text = "\n".join(render(view))
    for label in ("decision", "truth", "U_G", "threshold", "P(H1)", "closed by", "taxels present", "received",
                  "contact type", "area", "rule", "statistic"):
        assert label in text, label
    assert "54 of 57" in text and "window (degraded)" in text
    # one row per rule: name, decision, statistic, threshold (no unlabelled "(2.86e-20 vs 0)")
    row = next(line for line in text.splitlines() if line.startswith("multiplicative"))
    assert row.split()[:4] == ["multiplicative", "H1", "1.053e-20", "0"]
    assert " vs " not in text


def test_nodes_by_nmt_state():
    view = LiveView(service("matrix57"), cycles=200)
    view.update(record())
    text = "\n".join(render(view))
    # 57 nodes: 1 missing, 1 pre-operational, 1 stopped -> 54 operational, of which 1 silent
    assert "operational 54 (1 silent: no PDO)" in text
    assert "pre-operational 1" in text and "stopped 1" in text and "missing 1" in text
    strip = next(line.strip() for line in text.splitlines() if set(line.strip()) <= set("█·sxp-r?"))
    assert len(strip) == 57
    labels = service("matrix57").labels
    assert strip[labels.index(33)] == "x" and strip[labels.index(18)] == "s"
    assert strip[labels.index(40)] == "p" and strip[labels.index(41)] == "-"
    assert strip[labels.index(14)] == "█" and strip[labels.index(1)] == "·"


def test_all_operational_and_raw_mode_forces():
    view = LiveView(service("matrix57_raw"), cycles=200)
    rec = record(mode="raw", nodes_by_state={}, missing_nodes=[], silent_nodes=[], degraded=False,
                 closed_by="complete", n_received=57,
                 forces={"total_tangential": 1.234, "unit": "kgf"})
    rec["rules"]["centralised_glrt"] = {"U_G": 812.5, "threshold": 93.2, "decision": "H1", "p_h1": None}
    view.update(rec)
    lines = render(view)
    text = "\n".join(lines)
    assert max(cell_len(line) for line in lines) <= 80
    assert "operational 57, pre-operational 0, stopped 0" in text and "missing 0" in text
    assert "tangential force" in text and "1.23 kgf" in text and "centralised_glrt" in text


def test_two_hundred_nodes_wrap_within_80_columns():
    svc = service("two_buses_200")
    view = LiveView(svc, cycles=200)
    view.update(record(n_expected=200, n_received=200, nodes_by_state={}, missing_nodes=[], silent_nodes=[],
                       present_nodes=[]))
    lines = render(view)
    assert max(cell_len(line) for line in lines) <= 80
    assert sum(line.count("·") for line in lines if set(line.strip()) <= {"·"}) == 200


def test_before_the_first_record_and_malformed_frames():
    view = LiveView(service("matrix57", {"sync": 1, "bad_dlc": 4, "unknown_cob_id": 7}), cycles=10)
    text = "\n".join(render(view))
    assert "waiting for the first record" in text
    assert "malformed: 11, bad_dlc 4, unknown_cob_id 7" in text


class _RecordingLock:
    """A stream lock that records every acquisition by the thread that asks (the test's own)."""

    def __init__(self, lock):
        self.lock = lock
        self.taken = 0

    def acquire(self, *args, **kwargs):
        self.taken += 1
        return self.lock.acquire(*args, **kwargs)

    def release(self):
        self.lock.release()

    def __enter__(self):
        self.acquire()
        return self

    def __exit__(self, *exc):
        self.release()


def _view_counters(view) -> dict:
    """The counters a render of ``view`` shows (what its header and counters lines are made from)."""
    shown = []
    counters_line = view._counters
    view._counters = lambda counters, width: (shown.append(dict(counters)), counters_line(counters, width))[1]
    render(view)
    (counters,) = shown
    return counters


def test_after_a_run_the_view_shows_the_streams_counters_and_its_refresh_takes_no_lock():
    """The view reads the counters the stream published at its last closed cycle (and at its
    end) - never the stream lock, which the receive thread may need under SCHED_FIFO
    (--rt-priority): the numbers are those of ``stream.counters()`` all the same."""
    from fusion_center.commands.demo import run_demo

    service_, _ = run_demo(load_scene("matrix57"), 20, keep_records=False)
    view = LiveView(service_, cycles=20)
    view.update(record())
    stream = service_.stream
    stream.lock = _RecordingLock(stream.lock)
    shown = _view_counters(view)
    assert stream.lock.taken == 0  # the refresh took no stream lock
    assert shown == stream.counters() and shown["sync"] >= 20 and shown["tpdo1"] > 0
    assert stream.lock.taken == 1


def test_the_counters_snapshot_follows_the_closed_cycles_not_every_frame():
    """Published under the lock by the thread that feeds: at every turn before the first closed
    cycle (the boot's frames as they come), then at each turn that closes a cycle; a frame
    between two closes is shown at the next (or at counters(), which publishes what it returns)."""
    import can

    from fusion_center.service.cycles import CycleAssembler
    from fusion_center.service.stream import EventStream

    scene = load_scene(ROOT / "scenes" / "matrix57.toml")
    closed = []
    stream = EventStream(CycleAssembler(scene), on_closed=closed.append)
    assert stream.counters_snapshot() == stream.counters()

    def frame(t, can_id, data=b""):
        stream.receive(can.Message(timestamp=t, arbitration_id=can_id, data=data, is_extended_id=False), 0)

    frame(0.001, 0x700 + 1, b"\x00")  # a boot-up: no cycle closed yet, shown at once
    assert stream.counters_snapshot()["bootup"] == 1
    frame(0.010, 0x80, b"\x01")       # SYNC 1 opens cycle 0
    frame(0.011, 0x700 + 1, b"\x05")
    assert stream.counters_snapshot()["heartbeat"] == 1  # still no cycle closed: every turn
    frame(0.020, 0x80, b"\x02")       # SYNC 2 (held until the window's end) ...
    frame(0.021, 0x700 + 1, b"\x05")  # ... the next frame closes cycle 0
    assert len(closed) == 1
    at_close = stream.counters_snapshot()
    assert at_close["heartbeat"] == 2 and at_close["sync"] == 2
    frame(0.022, 0x700 + 1, b"\x05")  # between two closes: not published
    frame(0.030, 0x80, b"\x03")
    assert len(closed) == 1 and stream.counters_snapshot() == at_close
    frame(0.031, 0x700 + 1, b"\x05")  # closes cycle 1: published
    assert len(closed) == 2
    assert stream.counters_snapshot()["heartbeat"] == 4 and stream.counters_snapshot()["sync"] == 3
    assert stream.counters_snapshot() == stream.counters()
    frame(0.032, 0x700 + 1, b"\x05")
    assert stream.counters() == stream.counters_snapshot()  # counters() publishes what it gives
