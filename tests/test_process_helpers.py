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
from process_helpers import node_sim, start_node_sim, stop, wait_line, wait_ready  # noqa: E402


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


@pytest.mark.parametrize("ignored, ends_by", [
    ("SIGTERM", signal.SIGABRT),                 # aborted: with the fault handler on, it tells where it hung
    ("SIGTERM, SIGABRT", signal.SIGKILL),        # and killed if it ignores that too
])
def test_a_process_that_ignores_sigterm_is_aborted_then_killed_after_the_wait(ignored, ends_by):
    deaf = (f"import signal, time; [signal.signal(getattr(signal, s.strip()), signal.SIG_IGN) for s in {ignored!r}.split(',')]; "
            "print('ready', flush=True); time.sleep(120)")
    proc = subprocess.Popen([sys.executable, "-X", "faulthandler", "-c", deaf], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        wait_ready(proc, 60)
    finally:
        rc = stop(proc, 0.5)
    assert rc == -ends_by
    if ends_by == signal.SIGABRT:
        assert "most recent call first" in proc.stderr.read()  # the fault handler's stacks


def _talker(lines: str) -> subprocess.Popen:
    """A process that prints ``lines`` on stderr, then waits (until stopped)."""
    code = f"import sys, time; sys.stderr.write({lines!r}); sys.stderr.flush(); time.sleep(120)"
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_a_line_that_never_comes_is_waited_for_a_bounded_time_and_the_process_stopped():
    """test_assemblers waited for an assembler's "reconnected" line with readline alone: a process
    that said something else and then nothing held the test for ever."""
    proc = _talker("connecting\nretrying\n")
    try:
        with pytest.raises(AssertionError, match="did not say it reconnected within 2 s") as err:
            wait_line(proc, proc.stderr, "reconnected", 2.0, "the assembler did not say it reconnected")
        assert proc.poll() is not None and "retrying" in str(err.value)
    finally:
        stop(proc)


def test_the_lines_up_to_the_one_waited_for():
    proc = _talker("connecting\nreconnected to the fuser\nlater\n")
    try:
        lines = wait_line(proc, proc.stderr, "reconnected", 60.0, "no reconnect")
        assert lines == ["connecting\n", "reconnected to the fuser\n"] and proc.poll() is None
    finally:
        stop(proc)


def test_another_programs_ready_line_names_it_when_it_does_not_come():
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        with pytest.raises(AssertionError, match="fusion-center assemble did not start within"):
            wait_ready(proc, 0.5, name="fusion-center assemble")
        assert proc.poll() is not None
    finally:
        stop(proc)


def test_the_multicast_probe_keeps_to_the_host(monkeypatch):
    """test_service_multiprocess.multicast_works (which every udp_multicast test calls) sent its
    probe frame with python-can's default hop limit 1, out of the host; its buses have hop limit 0."""
    import can

    import test_service_multiprocess

    opened = []

    class Probe:
        def __init__(self, **kwargs):
            opened.append(kwargs)

        def send(self, msg):
            self.sent = msg

        def recv(self, timeout):
            return can.Message(arbitration_id=0x7E5, data=b"\x01", is_extended_id=False)

        def shutdown(self):
            pass

    monkeypatch.setattr(test_service_multiprocess.can, "Bus", Probe)
    assert test_service_multiprocess.multicast_works(45000) is None
    assert len(opened) == 2 and all(kw["interface"] == "udp_multicast" and kw["hop_limit"] == 0 for kw in opened)
