"""``fusion-center demo --slow-down K``: every bus time K times longer, per-cycle results unchanged;
and the warning when a demo falls behind its SYNC."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fusion_center.commands.demo import fell_behind, slowed_down
from cli_inprocess import run_cli
from node_sim import physics
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent


def test_every_bus_time_scales_and_nothing_else():
    scene = load_scene(ROOT / "scenes" / "skin4096.toml")
    slow = slowed_down(scene, 4)
    b, s = scene.bus, slow.bus
    assert s.sync_period_ms == 4 * b.sync_period_ms
    assert s.sync_window == 4 * b.sync_window and s.sync_window < 1000 * s.sync_period_ms
    assert (s.heartbeat_producer_ms, s.heartbeat_consumer_ms) == (4 * b.heartbeat_producer_ms, 4 * b.heartbeat_consumer_ms)
    assert slow.master_heartbeat_ms == 4 * scene.master_heartbeat_ms
    # everything a cycle's result depends on is the scene's own
    assert slow.taxels == scene.taxels and slow.object == scene.object and slow.fusion == scene.fusion
    assert (s.channels, s.mode, s.sync_counter, s.bitrate) == (b.channels, b.mode, b.sync_counter, b.bitrate)
    for cycle in (0, 25, 90):
        assert np.array_equal(physics.sample_readings(slow, cycle), physics.sample_readings(scene, cycle))
    assert slowed_down(scene, 1.0) is scene


@pytest.mark.parametrize("factor", [0.5, 0.0, -2.0, float("nan"), float("inf"), 1001.0])
def test_a_factor_outside_1_to_1000_is_refused(factor):
    with pytest.raises(UsageError, match="--slow-down"):
        slowed_down(load_scene(ROOT / "scenes" / "matrix57.toml"), factor)


def test_a_time_its_object_cannot_hold_is_refused():
    scene = load_scene(ROOT / "scenes" / "matrix57.toml")   # heartbeat consumer 300 ms: x 300 > 65535
    with pytest.raises(UsageError, match="heartbeat"):
        slowed_down(scene, 300)


def test_warning_only_when_most_cycles_are_degraded_with_late_pdos():
    base = {"records": 100, "degraded_cycles": 10, "counters": {"late": 30}, "latency_ms_p99": 25.0}
    assert fell_behind(base, 10.0) is None
    assert fell_behind({**base, "degraded_cycles": 80, "counters": {}}, 10.0) is None  # silent nodes, not late
    warning = fell_behind({**base, "degraded_cycles": 80}, 10.0)
    assert "80 of 100 cycles degraded, 30 PDOs late" in warning and warning.endswith("--slow-down 8")


def test_demo_slowed_down_runs_at_k_times_the_period_with_the_same_records(tmp_path, capsys):
    """matrix57 at --slow-down 3: SYNCs 30 ms apart (the records' bus times), every complete cycle's
    decisions the physics of its cycle, as at the scene's own period, and the summary says so."""
    out = tmp_path / "slow.jsonl"
    # main() in this process (tests/cli_inprocess.py): the test is about the records and the summary
    done = run_cli(capsys, "demo", "--cycles", "30", "--no-live", "--slow-down", "3", "--json-lines", out, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "slow_down:" in done.stdout and "SYNC every 30 ms instead of 10 ms" in done.stdout
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["cycle"] for r in records] == list(range(30))
    spacing = np.median(np.diff([r["t"] for r in records]))
    assert 0.025 < spacing < 0.035, spacing
    scene = load_scene(ROOT / "scenes" / "matrix57.toml")
    zeta = np.array([t.zeta_mv for t in scene.taxels])
    noise = np.array([t.noise_mv for t in scene.taxels])
    complete = [r for r in records if r["closed_by"] == "complete"]
    assert complete
    for r in complete:
        u = (physics.sample_readings(scene, r["cycle"]) - noise) >= zeta
        assert r["present_count"] == int(u.sum())
        assert r["truth"] == ("H1" if physics.object_present(scene, r["cycle"]) else "H0")


@pytest.mark.parametrize("value", ["0.5", "nan", "abc"])
def test_bad_slow_down_is_one_line_exit_2(value, tmp_path, capsys):
    done = run_cli(capsys, "demo", "--cycles", "5", "--no-live", "--slow-down", value, cwd=tmp_path)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "--slow-down" in done.stderr
