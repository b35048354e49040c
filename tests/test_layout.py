"""The layout is the architecture: core | service | commands | twins by service | shared.

Import rules (docs/architecture.md), checked on the source (ast) and in fresh interpreters:

* ``fusion_center.core`` - pure functions of the method: imports only the standard library's
  pure modules, numpy, scipy, mpmath, itself, ``taxel_net.errors`` and ``taxel_net.grip_params`` (the
  grip law's parameter type, shared with the scene loader so that loading a scene never imports
  the centre); never ``can``, ``canopen``,
  ``rich``, ``matplotlib``; no file, socket or clock I/O.
* ``taxel_net`` - shared by twins and centre: imports neither ``fusion_center`` nor ``node_sim``.
* ``node_sim`` - the firmware twins: imports nothing from ``fusion_center``.
* the centre imports from ``node_sim`` only the physics ground truth, and the rig in ``demo``.
* ``fusion_center.service`` never imports the CLI (``fusion_center.cli``, ``.commands``).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CORE_DIR = ROOT / "fusion_center" / "core"
CORE_MODULES = sorted(p.stem for p in CORE_DIR.glob("*.py") if p.stem != "__init__")

FORBIDDEN_IN_CORE = ("can", "canopen", "rich", "matplotlib", "node_sim", "fusion_center.service",
                     "fusion_center.commands")
# standard-library modules that do or schedule I/O, or read the clock
IO_MODULES = {"os", "io", "pathlib", "socket", "time", "datetime", "logging", "subprocess", "threading",
              "sys", "tempfile", "shutil", "glob", "select", "signal", "asyncio", "urllib", "http",
              "sqlite3", "pickle", "csv", "json", "tomllib", "random"}
IO_BUILTINS = {"open", "print", "input"}
CORE_ALLOWED_TOP = {"__future__", "math", "cmath", "numbers", "dataclasses", "typing", "collections",
                    "functools", "itertools", "enum", "fractions", "decimal", "operator", "bisect",
                    "heapq", "re", "numpy", "scipy", "mpmath", "fusion_center", "taxel_net"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path) -> list[tuple[str, int]]:
    """Absolute names of every module ``path`` imports (relative imports resolved), with lines."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = _module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.append((mod, node.lineno))
            # "from pkg import module" imports pkg.module too
            found += [(f"{mod}.{alias.name}", node.lineno) for alias in node.names]
    return found


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def _sources(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def test_ast_import_scanner_sees_relative_and_lazy_imports(tmp_path, monkeypatch):
    """The scanner itself: a lazy relative import inside a function is found and resolved."""
    pkg = ROOT / "fusion_center" / "core"
    fake = pkg / "rules.py"
    names = {n for n, _ in imports_of(fake)}
    assert "fusion_center.core.encoding" in names
    src = tmp_path / "fusion_center" / "core"
    src.mkdir(parents=True)
    probe = src / "probe.py"
    probe.write_text("def f():\n    from ..service import master\n    import can\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    names = {n for n, _ in imports_of(probe)}
    assert {"fusion_center.service", "fusion_center.service.master", "can"} <= names


@pytest.mark.parametrize("module", CORE_MODULES)
def test_core_module_imports_are_pure(module):
    path = CORE_DIR / f"{module}.py"
    bad = []
    for name, line in imports_of(path):
        top = name.split(".")[0]
        if any(_under(name, f) for f in FORBIDDEN_IN_CORE) or top in IO_MODULES or top not in CORE_ALLOWED_TOP:
            bad.append(f"{path.name}:{line} imports {name}")
        elif top == "fusion_center" and not _under(name, "fusion_center.core"):
            bad.append(f"{path.name}:{line} imports {name} (outside the core)")
        elif top == "taxel_net" and not (_under(name, "taxel_net.errors") or _under(name, "taxel_net.grip_params")):
            bad.append(f"{path.name}:{line} imports {name} (the core needs only taxel_net.errors and "
                       "taxel_net.grip_params)")
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in IO_BUILTINS:
            bad.append(f"{path.name}:{node.lineno} calls {node.func.id}()")
    assert not bad, "\n".join(bad)


# One fresh interpreter probes every module: it imports only numpy, scipy and mpmath (the
# libraries the core may use - checked: none of them loads a forbidden module), then forks a
# child per module that imports it and reports what is loaded then. A child starts from the
# same clean state a new interpreter would reach after those imports, for a tenth of the cost
# (one interpreter start instead of one per module).
PROBE = r"""
import json, os, sys
FORBIDDEN_TOPS, FORBIDDEN_PREFIXES = set(sys.argv[1].split(',')), tuple(sys.argv[2].split(','))
def loaded():
    return sorted(m for m in sys.modules
                  if m.split('.')[0] in FORBIDDEN_TOPS or m.startswith(FORBIDDEN_PREFIXES))
import numpy, scipy.special, scipy.stats, scipy.optimize, mpmath
results = {"<base>": {"loaded": loaded()}}
for module in sys.argv[3:]:
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(read)
        try:
            __import__(module)
            out = {"loaded": loaded()}
        except BaseException as exc:
            out = {"error": f"{type(exc).__name__}: {exc}"}
        os.write(write, json.dumps(out).encode())
        os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as pipe:
        data = pipe.read()
    os.waitpid(pid, 0)
    results[module] = json.loads(data) if data else {"error": "the child wrote nothing"}
print(json.dumps(results))
"""


def probe_imports(modules: list[str]) -> dict[str, dict]:
    """What each module loads of ``FORBIDDEN_IN_CORE`` when imported in a fresh interpreter."""
    tops = ",".join(m for m in FORBIDDEN_IN_CORE if "." not in m)
    prefixes = ",".join(m for m in FORBIDDEN_IN_CORE if "." in m)
    out = subprocess.run([sys.executable, "-c", PROBE, tops, prefixes, *modules],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    results = json.loads(out.stdout)
    assert results.pop("<base>") == {"loaded": []}
    return results


@pytest.fixture(scope="module")
def core_imports() -> dict[str, dict]:
    return probe_imports([f"fusion_center.core.{m}" for m in CORE_MODULES])


@pytest.mark.parametrize("module", CORE_MODULES)
def test_core_module_loads_no_can_rich_or_plotting_in_a_fresh_interpreter(core_imports, module):
    result = core_imports[f"fusion_center.core.{module}"]
    assert "error" not in result, result
    assert result["loaded"] == [], f"importing fusion_center.core.{module} loaded: {','.join(result['loaded'])}"


def test_fresh_interpreter_check_can_fail():
    """The same probe reports a forbidden module when one is loaded (python-can, imported in
    the child only: the next child starts without it), and the import error of a module that
    does not exist."""
    results = probe_imports(["can", "fusion_center.core.no_such_module", "fusion_center.core.rules"])
    assert "can" in results["can"]["loaded"]
    assert "ModuleNotFoundError" in results["fusion_center.core.no_such_module"]["error"]
    assert results["fusion_center.core.rules"] == {"loaded": []}


def test_shared_layer_imports_neither_centre_nor_twins():
    bad = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in _sources("taxel_net")
           for name, line in imports_of(p) if _under(name, "fusion_center") or _under(name, "node_sim")]
    assert not bad, "\n".join(bad)


def test_node_twins_import_nothing_from_the_centre():
    bad = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in _sources("node_sim")
           for name, line in imports_of(p) if _under(name, "fusion_center")]
    assert not bad, "\n".join(bad)


def test_centre_imports_from_node_sim_only_physics_and_the_demo_rig():
    bad = []
    for p in _sources("fusion_center"):
        for name, line in imports_of(p):
            if not _under(name, "node_sim") or name == "node_sim":
                continue
            if _under(name, "node_sim.physics"):
                continue
            if _under(name, "node_sim.rig") and p == ROOT / "fusion_center" / "commands" / "demo.py":
                continue
            bad.append(f"{p.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)


def test_service_does_not_import_the_cli():
    bad = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in _sources("fusion_center/service")
           for name, line in imports_of(p)
           if _under(name, "fusion_center.cli") or _under(name, "fusion_center.commands")]
    assert not bad, "\n".join(bad)


def test_shared_scene_and_errors_load_without_can():
    code = ("import sys, taxel_net, taxel_net.scene, taxel_net.errors\n"
            "print(','.join(sorted(m for m in sys.modules if m.split('.')[0] in ('can', 'canopen'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""
