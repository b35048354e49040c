"""tests/conftest.py's mpmath precision guards, run on small suites of their own (a pytest
subprocess in a temporary directory with a copy of the conftest): a module that sets the
precision at import or in a module fixture it does not restore is an error naming that module;
a module that takes it with mp.workdps passes."""

from __future__ import annotations

import pathlib
import subprocess
import sys

CONFTEST = pathlib.Path(__file__).with_name("conftest.py")

CLEAN = '''
import mpmath, pytest

@pytest.fixture(scope="module", autouse=True)
def digits():
    with mpmath.mp.workdps(40):
        yield

def test_clean():
    assert mpmath.mp.dps == 40
'''


def run_suite(tmp_path, files: dict) -> subprocess.CompletedProcess:
    (tmp_path / "conftest.py").write_text(CONFTEST.read_text())
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider", "-s"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)


def test_a_module_setting_mpmaths_precision_at_import_is_a_collection_error(tmp_path):
    leak = "import mpmath\nmpmath.mp.dps = 50\n\ndef test_a():\n    pass\n"
    victim = "import mpmath\n\ndef test_b():\n    print('prec in test_b:', mpmath.mp.prec)\n"
    r = run_suite(tmp_path, {"test_a_leak.py": leak, "test_b_victim.py": victim, "test_c_clean.py": CLEAN})
    assert r.returncode == 2, r.stdout      # interrupted: an error during collection
    assert ("test_a_leak.py: importing it left mpmath at 169 bits of precision (default 53): "
            "take it with mp.workdps(n), not mp.dps = n") in r.stdout, r.stdout
    assert "test_c_clean.py" not in r.stdout.split("short test summary info")[-1], r.stdout   # only the cause named


def test_a_module_fixture_that_leaves_another_precision_is_an_error_at_its_teardown(tmp_path):
    leak = ("import mpmath, pytest\n\n@pytest.fixture(scope='module', autouse=True)\ndef digits():\n"
            "    mpmath.mp.dps = 40\n\ndef test_c():\n    assert mpmath.mp.dps == 40\n")
    victim = "import mpmath\n\ndef test_d():\n    assert mpmath.mp.prec == 53\n"
    r = run_suite(tmp_path, {"test_a_clean.py": CLEAN, "test_c_leak.py": leak, "test_d_victim.py": victim})
    assert r.returncode == 1, r.stdout
    assert "test_c_leak.py left mpmath at 136 bits of precision after its tests (default 53)" in r.stdout, r.stdout
    assert "3 passed, 1 error" in r.stdout, r.stdout   # the victim ran at the default again
