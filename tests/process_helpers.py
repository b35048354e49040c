"""node-sim in another process for the multiprocess tests: started, waited for until it says
"ready" (a bounded wait), and stopped whatever happens - SIGTERM, then SIGKILL after a bounded
wait, so no process outlives its test, also when the test fails or node-sim never starts.

    with node_sim("--scene", scene, *udp_loopback(group, port)) as sim:
        ...                                   # sim.ready_line: what node-sim printed
    assert sim.returncode == 0, sim.stderr.read()

A test that must listen before node-sim's boot-ups uses ``node_sim(..., ready=False)`` and calls
``wait_ready(sim)`` itself; another program's ready line (``fusion-center assemble``) is waited for
with ``wait_ready(proc, name=...)``, any other line with :func:`wait_line`. Loopback only:
:func:`udp_loopback` gives hop limit 0.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
NODE_SIM = [sys.executable, "-m", "node_sim.cli"]
READY_S = 60.0  # node-sim imports and builds its nodes: seconds on a loaded 2-core host
STOP_S = 10.0


def multicast_group_port() -> tuple[str, int]:
    """A udp_multicast group and port of this test (another test or run beside it has others)."""
    group = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    port = 47000 + (os.getpid() % 1000) + random.randint(0, 999)
    return group, port


def udp_loopback(group: str, port: int) -> list[str]:
    """The bus options of node-sim and ``fusion-center run`` for udp_multicast on loopback only."""
    return ["--interface", "udp_multicast", "--channel", group, "--bus-option", f"port={port}",
            "--bus-option", "hop_limit=0"]


def start_node_sim(*args: str) -> subprocess.Popen:
    """``node-sim ARGS`` in another process, stdout and stderr piped (text); Python's fault
    handler on, so that :func:`stop` can have a hung process print every thread's stack."""
    return subprocess.Popen([*NODE_SIM, *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONFAULTHANDLER": "1"})


def abort_with_stacks(proc: subprocess.Popen, timeout: float = 5.0) -> int:
    """A process that would not end: SIGABRT (with the fault handler on, it prints the stack of
    every thread on its stderr: what it hung in), SIGKILL if that does not end it either."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGABRT)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait(timeout)


def read_lines(stream, needle: str, timeout: float, limit: int = 200) -> list[str]:
    """Lines of ``stream`` (a text pipe) up to the first holding ``needle``, its end (``""`` last)
    or ``limit`` lines, read within ``timeout`` s; after ``timeout`` s, those read so far (the
    reading thread is left waiting on the pipe: stop its process)."""
    lines: list[str] = []
    done = threading.Event()

    def read() -> None:
        for _ in range(limit):
            line = stream.readline()
            lines.append(line)
            if not line or needle in line:
                break
        done.set()

    threading.Thread(target=read, daemon=True).start()
    done.wait(timeout)
    return list(lines)


def wait_line(proc: subprocess.Popen, stream, needle: str, timeout: float, what: str, limit: int = 200) -> list[str]:
    """The lines of ``stream`` (``proc.stdout`` or ``proc.stderr``) up to one holding ``needle``
    (at most ``limit`` lines), within ``timeout`` s; otherwise ``proc`` is stopped and the
    AssertionError says ``what`` went wrong and holds what the process printed on both pipes."""
    lines = read_lines(stream, needle, timeout, limit)
    if not lines or needle not in lines[-1]:
        stop(proc)
        other = proc.stderr if stream is proc.stdout else proc.stdout
        raise AssertionError(f"{what} within {timeout:.0f} s (exit code {proc.returncode}): "
                             f"read {lines}, "
                             f"the other pipe {other.read() if other is not None else ''!r}")
    return lines


def wait_ready(proc: subprocess.Popen, timeout: float = READY_S, name: str = "node-sim") -> str:
    """The process's first line on stdout, which must say "ready", within ``timeout`` s. If it does
    not come (or says something else) the process is stopped and the AssertionError holds what it
    printed on stdout and stderr (``name``: the program, in the message)."""
    return wait_line(proc, proc.stdout, "ready", timeout, f"{name} did not start", limit=1)[0]


def stop(proc: subprocess.Popen, timeout: float = STOP_S) -> int:
    """SIGTERM, and SIGABRT then SIGKILL (:func:`abort_with_stacks`) if the process has not ended
    ``timeout`` s later; its exit code (the caller asserts a clean exit where it wants one: an
    aborted process has -6, a killed one -9)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return abort_with_stacks(proc)
    return proc.wait(timeout)


@contextmanager
def node_sim(*args: str, ready: bool = True, ready_s: float = READY_S,
             stop_s: float = STOP_S) -> Iterator[subprocess.Popen]:
    """``node-sim ARGS`` running for the block (``ready``: its "ready" line read first, kept as
    ``proc.ready_line``), stopped at its end as :func:`stop` does."""
    proc = start_node_sim(*args)
    try:
        proc.ready_line = wait_ready(proc, ready_s) if ready else None
        yield proc
    finally:
        stop(proc, stop_s)
