"""The fusion centre as a long-running service (issue 10): nothing on the cycle path that grows,
imports or stalls; clean exits on a closed stdout; bounded state over many cycles."""

import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
MATRIX = ROOT / "scenes" / "matrix57.toml"
CLI = [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())"]


def test_first_cycle_with_a_reading_missing_imports_nothing():
    """The per-missing-set threshold of ``centralised_known`` needs scipy.optimize/special: they
    are imported when the tests are built, never in the cycle (it cost ~150 ms, a late SYNC)."""
    code = r"""
import sys, numpy as np
from taxel_net.scene import load_scene
from fusion_center.commands.run import apply_mode
from fusion_center.service.centralised_tests import CentralisedTests
scene = apply_mode(load_scene(sys.argv[1]), "raw")
tests = CentralisedTests(scene, ["centralised_glrt", "centralised_known"])
before = set(sys.modules)
available = np.ones(scene.n, dtype=bool); available[17] = False
out = tests.results(np.zeros(scene.n), available)
new = sorted(set(sys.modules) - before)
assert out["centralised_known"]["n"] == scene.n - 1, out
print(",".join(new))
"""
    done = subprocess.run([sys.executable, "-c", code, str(MATRIX)], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "", f"imported on the cycle path: {done.stdout.strip()}"


def test_closed_stdout_ends_quietly():
    """``fusion-center demo | head``: the reader goes away -> no traceback, exit 141 (SIGPIPE)."""
    proc = subprocess.Popen(CLI + ["demo", "--cycles", "3", "--no-live"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # nobody reads the summary
    _, err = proc.communicate(timeout=120)
    assert b"Traceback" not in err, err.decode()
    assert b"BrokenPipe" not in err, err.decode()
    assert proc.returncode == 141
