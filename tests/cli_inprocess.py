"""``fusion-center ARGS`` run in the test's own process, for the tests that check what the
command does with its input (exit status, its stderr, the files it writes) and not the process
boundary: ``fusion_center.cli.main(argv)`` returns the exit code and prints its errors on stderr,
as the installed script does. It saves each call an interpreter start and the imports (~1.3 s of
CPU on CI's machine). A test about signals, a killed process, the installed script or a crash
without a traceback stays a real subprocess (tests/process_helpers.py).

    done = run_cli(capsys, "replay", "--scene", scene, trace)
    assert done.returncode == 2, done.stderr

What differs from a subprocess, and how it is made up for:
- an exception escaping ``main`` (a traceback in a subprocess) is raised into the test: it fails;
- argparse's exit (``SystemExit``) is taken as the exit status, its message is on stderr;
- the log records of WARNING and above go to stderr as in the subprocess (``run``'s
  ``logging.basicConfig`` finds pytest's handlers on the root logger and adds none): a handler of
  this call's writes them there, so a test counting stderr's lines still sees them;
- the working directory is the one asked for (default the repository's), as the subprocesses
  were started in, and the test's again after the call.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

from fusion_center.cli import main

ROOT = Path(__file__).resolve().parent.parent


def run_cli(capsys, *args, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """``fusion-center ARGS`` through ``main``, in the working directory ``cwd`` (the
    repository's unless given): a CompletedProcess with its exit code, stdout and stderr (those
    of this call only: what the test printed before is read off first)."""
    argv = [str(a) for a in args]
    capsys.readouterr()
    handler = logging.StreamHandler(sys.stderr)  # capsys's stderr of this call
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    previous = os.getcwd()
    os.chdir(cwd)
    try:
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse: its usage and error are on stderr
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        os.chdir(previous)
        root.removeHandler(handler)
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(["fusion-center", *argv], code, out, err)
