"""Where the suite's CPU goes: a pytest plugin (not loaded by default) that measures each test's
CPU time - its process's user + system time, and that of the child processes it waited for
(``node-sim``, ``fusion-center``, the docs examples' shells) - and prints the costliest files and
tests at the end. CI's 2 cores are the suite's budget (docs/contributing.md): the wall time of
a test that waits on a bus or another process costs the other workers little, its CPU does.

    PYTHONPATH=tests .venv/bin/python -m pytest -q -p cpu_report

Works with pytest-xdist: each worker appends its tests' figures to a file of the run's
directory (``$CPU_REPORT_DIR``, default a new temporary one), the controller sums them.
Threads a test leaves running are charged to the tests after it (there are none today).
"""

from __future__ import annotations

import collections
import json
import os
import resource
import tempfile

import pytest

TOP = 15


def _cpu() -> tuple[float, float]:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


def pytest_configure(config):
    if not hasattr(config, "workerinput"):  # the controller (or a run without xdist)
        os.environ.setdefault("CPU_REPORT_DIR", tempfile.mkdtemp(prefix="cpu-report-"))
    config._cpu_report_dir = os.environ["CPU_REPORT_DIR"]


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    before = _cpu()
    yield
    after = _cpu()
    path = os.path.join(item.config._cpu_report_dir, f"worker-{os.getpid()}.jsonl")
    with open(path, "a", encoding="utf-8") as out:
        out.write(json.dumps([item.nodeid, after[0] - before[0], after[1] - before[1]]) + "\n")


def pytest_terminal_summary(terminalreporter, config):
    if hasattr(config, "workerinput"):
        return
    rows = []
    directory = config._cpu_report_dir
    for name in sorted(os.listdir(directory)):
        with open(os.path.join(directory, name), encoding="utf-8") as lines:
            rows += [json.loads(line) for line in lines]
    if not rows:
        return
    by_file = collections.Counter()
    for nodeid, own, children in rows:
        by_file[nodeid.split("::")[0]] += own + children
    write = terminalreporter.write_line
    own_total, children_total = sum(r[1] for r in rows), sum(r[2] for r in rows)
    terminalreporter.section("CPU time by test (cpu_report)")
    write(f"{len(rows)} tests: {own_total + children_total:.1f} s CPU "
          f"({own_total:.1f} s in the test processes, {children_total:.1f} s in their children)")
    write(f"costliest files ({directory}):")
    for path, seconds in by_file.most_common(TOP):
        write(f"{seconds:8.1f} s  {path}")
    write("costliest tests (own + children):")
    for nodeid, own, children in sorted(rows, key=lambda r: -(r[1] + r[2]))[:TOP]:
        write(f"{own + children:8.1f} s  ({own:.1f} + {children:.1f})  {nodeid}")
