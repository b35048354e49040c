"""node_sim is laid out by CANopen service, imports nothing from the centre, and loads lazily.

* one module per service, each with its service class; ``TaxelNode`` composes them and keeps
  no service state of its own;
* ``import node_sim.physics`` (what the fusion centre imports for its ground truth) loads
  neither python-can nor canopen, in a fresh interpreter; ``node_sim.Rig`` /
  ``node_sim.TaxelNode`` / ``node_sim.physics`` resolve on first use;
* no node_sim module imports ``fusion_center`` - checked on the parsed source (ast: lazy
  imports inside functions and relative imports count, docstrings that name the centre do not);
* the services work on their own (NMT transitions and hooks, SYNC gating), without a rig.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "node_sim"
MODULES = sorted(p.stem for p in PACKAGE.glob("*.py"))

# module -> its service class (the layout is the protocol)
SERVICES = {
    "nmt": "NmtSlave",
    "heartbeat": "HeartbeatProducer",
    "sdo": "SdoServer",
    "pdo": "TpdoEngine",
    "sync": "SyncConsumer",
    "emcy": "EmcyProducer",
    "taxel.detector": "Detector",   # the taxel node's application, in its device kind's package (issue 22)
    "od": "NodeObjects",
}


def imported_modules(path: Path, package: str = "node_sim") -> set[str]:
    """Absolute names of every module ``path`` (a module of ``package``) imports anywhere in
    its code: relative imports resolved, ``from a import b`` counts ``a`` and ``a.b``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    base = package.split(".")
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parent = base[: len(base) - node.level + 1]
                module = ".".join(parent + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            names.add(module)
            names.update(f"{module}.{alias.name}" for alias in node.names)
    return names


def _is_centre(name: str) -> bool:
    return name == "fusion_center" or name.startswith("fusion_center.")


# --------------------------------------------------------------------------- import rules

@pytest.mark.parametrize("module", MODULES)
def test_node_sim_module_imports_nothing_from_the_centre(module):
    names = imported_modules(PACKAGE / f"{module}.py")
    assert names, f"node_sim/{module}.py: the scanner found no import at all"
    assert not [n for n in names if _is_centre(n)], sorted(n for n in names if _is_centre(n))


def test_import_scanner_sees_code_not_docstrings(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text('"""Equal to fusion_center.core.encoding.local_decision; from fusion_center import x."""\n'
                     "import math\n"
                     "from . import od\n"
                     "def f():\n"
                     "    from fusion_center.core import encoding\n")
    names = imported_modules(probe)
    assert {"math", "node_sim", "node_sim.od", "fusion_center.core", "fusion_center.core.encoding"} <= names
    probe.write_text('"""Equal to fusion_center.core.encoding.local_decision."""\nimport math\n')
    assert not [n for n in imported_modules(probe) if _is_centre(n)]


def _fresh(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_physics_loads_no_can_library_in_a_fresh_interpreter():
    loaded = _fresh("import sys\nimport node_sim.physics\n"
                    "print(','.join(sorted(m for m in sys.modules if m.split('.')[0] in ('can', 'canopen'))))")
    assert loaded == ""
    loaded = _fresh("import sys\nimport node_sim\nnode_sim.physics.sample_readings\n"
                    "print(','.join(sorted(m for m in sys.modules if m.split('.')[0] in ('can', 'canopen'))))")
    assert loaded == ""


def test_public_names_resolve_lazily_in_a_fresh_interpreter():
    out = _fresh("import sys, node_sim\n"
                 "before = 'canopen' in sys.modules or 'node_sim.rig' in sys.modules\n"
                 "from node_sim.rig import Rig\nfrom node_sim.node import TaxelNode\nimport node_sim.physics as ph\n"
                 "print(before, node_sim.Rig is Rig, node_sim.TaxelNode is TaxelNode, node_sim.physics is ph)")
    assert out == "False True True True"


def test_public_api():
    import node_sim
    from node_sim import node, physics, rig

    assert node_sim.__all__ == ["Rig", "TaxelNode", "physics"]
    assert node_sim.Rig is rig.Rig and node_sim.TaxelNode is node.TaxelNode and node_sim.physics is physics
    assert set(node_sim.__all__) <= set(dir(node_sim))
    with pytest.raises(AttributeError):
        node_sim.no_such_name  # noqa: B018
    # what the channel side imports from node_sim.node
    from node_sim.node import COB_INVALID, NodeLink, Scheduler, TaxelNode  # noqa: F401


# --------------------------------------------------------------------------- one module per service

@pytest.mark.parametrize("module, cls", sorted(SERVICES.items()))
def test_one_module_per_service(module, cls):
    import importlib

    mod = importlib.import_module(f"node_sim.{module}")
    service = getattr(mod, cls)
    assert service.__module__ == mod.__name__
    assert mod.__doc__ and service.__doc__


def test_taxel_node_composes_the_services_and_keeps_no_service_state():
    from node_sim.detector import Detector
    from node_sim.emcy import EmcyProducer
    from node_sim.heartbeat import HeartbeatConsumer, HeartbeatProducer
    from node_sim.link import NodeLink, Scheduler
    from node_sim.nmt import NmtSlave
    from node_sim.node import TaxelNode
    from node_sim.od import NodeObjects
    from node_sim.pdo import TpdoEngine
    from node_sim.sdo import SdoServer
    from node_sim.sync import SyncConsumer

    scheduler = Scheduler(threading.RLock(), name="test-layout")
    try:
        node = TaxelNode(5, NodeLink(lambda can_id, data: None, scheduler))
        kinds = {"objects": NodeObjects, "nmt": NmtSlave, "heartbeat": HeartbeatProducer,
                 "heartbeat_consumer": HeartbeatConsumer, "sdo": SdoServer,
                 "pdo": TpdoEngine, "sync": SyncConsumer, "emcy": EmcyProducer, "detector": Detector}
        for name, kind in kinds.items():
            assert type(getattr(node, name)) is kind, name
        # the node's own attributes: its identity, its channel, "silent", the services
        # (and od/local, the objects' views), the device's LSS slave (it outlives the node:
        # node_sim.lss) and the owner's hook for a new node-ID; the services' state lives in
        # the services
        own = set(vars(node)) - set(kinds)
        assert own == {"node_id", "link", "silent", "_frames_sent", "od", "local", "lss", "_renumber"}, own
        assert node.lss is None  # no LSS unless the owner gives the device one (the rig does)
        assert node.od is node.objects.od and node.local is node.objects.local
    finally:
        scheduler.stop()


# --------------------------------------------------------------------------- services on their own

def test_nmt_slave_transitions_and_hooks():
    from node_sim import nmt

    sent, calls = [], []
    hooks = {name: (lambda name=name: calls.append(name)) for name in
             ("before_boot", "after_boot", "enter_operational", "leave_operational", "reset_node",
              "reset_communication")}
    slave = nmt.NmtSlave(9, lambda can_id, data: sent.append((can_id, data)), **hooks)
    assert slave.state == nmt.INITIALISING
    slave.on_command(nmt.NMT_START)                  # nothing while INITIALISING
    assert slave.state == nmt.INITIALISING and calls == []
    slave.boot()
    assert sent == [(0x709, b"\x00")] and slave.state == nmt.PRE_OPERATIONAL
    assert calls == ["before_boot", "after_boot"]
    calls.clear()
    slave.on_command(nmt.NMT_START)
    slave.on_command(nmt.NMT_START)                  # already operational: no second start
    assert slave.state == nmt.OPERATIONAL and calls == ["enter_operational"]
    slave.on_command(nmt.NMT_STOP)
    assert slave.state == nmt.STOPPED and slave.state_name == "STOPPED"
    slave.on_command(nmt.NMT_ENTER_PRE_OPERATIONAL)
    slave.on_command(0x42)                           # unknown: ignored
    assert slave.state == nmt.PRE_OPERATIONAL
    assert calls == ["enter_operational", "leave_operational", "leave_operational"]
    calls.clear()
    sent.clear()
    slave.on_command(nmt.NMT_RESET_NODE)
    slave.on_command(nmt.NMT_RESET_COMMUNICATION)
    assert calls == ["reset_node", "before_boot", "after_boot", "reset_communication", "before_boot", "after_boot"]
    assert sent == [(0x709, b"\x00")] * 2 and slave.state == nmt.PRE_OPERATIONAL


def test_sync_consumer_gates_on_silence_and_nmt_state():
    from types import SimpleNamespace

    from node_sim import nmt
    from node_sim.sync import SyncConsumer

    node = SimpleNamespace(silent=False)
    slave = nmt.NmtSlave(3, lambda can_id, data: None)
    samples, tpdos = [], []
    consumer = SyncConsumer(node, slave, None, lambda x, counter: samples.append((x, counter)), tpdos.append)
    consumer.on_sync(0, 1.0, None)                   # INITIALISING: nothing
    slave.boot()
    consumer.on_sync(1, 2, 7)                        # pre-operational: sample, no TPDO
    slave.on_command(nmt.NMT_START)
    consumer.on_sync(2, 3.0, 8)
    node.silent = True
    consumer.on_sync(3, 4.0, 9)                      # dead node: nothing
    assert samples == [(2.0, 7), (3.0, 8)] and type(samples[0][0]) is float  # the counter goes to 0x2003
    assert tpdos == [8]
    assert (consumer.last_cycle, consumer.last_counter) == (2, 8)
