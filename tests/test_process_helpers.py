"""The shared start/stop of node-sim in the multiprocess tests (tests/process_helpers.py): every
wait is bounded and no process outlives a failure - one that never says "ready" is stopped and
the error holds what it printed; one that ignores SIGTERM is killed."""

import signal
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from process_helpers import node_sim, start_node_sim, stop, wait_ready  # noqa: E402


def test_node_sim_that_fails_to_start_is_an_assertion_with_its_error(tmp_path):
    proc = start_node_sim("--scene", str(tmp_path / "missing.toml"), "-i", "virtual", "-c", "x")
    with pytest.raises(AssertionError) as err:
        wait_ready(proc, 60)
    assert proc.returncode == 2 and "missing.toml" in str(err.value)


def test_no_ready_line_within_the_wait_stops_the_process():
    proc = start_node_sim("--scene", "matrix57", "-i", "virtual", "-c", f"ph-{uuid.uuid4().hex[:8]}")
    try:
        with pytest.raises(AssertionError, match="did not start within"):
            wait_ready(proc, 0.001)  # (the interpreter alone takes longer to start)
        assert proc.poll() is not None
    finally:
        stop(proc)


def test_the_block_ends_with_node_sim_stopped_also_on_failure():
    with pytest.raises(RuntimeError):
        with node_sim("--scene", "matrix57", "-i", "virtual", "-c", f"ph-{uuid.uuid4().hex[:8]}") as proc:
            assert "ready" in proc.ready_line and proc.poll() is None
            raise RuntimeError("the test failed")
    assert proc.returncode == 0  # SIGTERM: node-sim ends cleanly


def test_a_process_that_ignores_sigterm_is_killed_after_the_wait():
    deaf = ("import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('ready', flush=True); "
            "time.sleep(120)")
    proc = subprocess.Popen([sys.executable, "-c", deaf], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_ready(proc, 60)
    finally:
        rc = stop(proc, 0.5)
    assert rc == -signal.SIGKILL
