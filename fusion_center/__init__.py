"""taxel-can fusion centre: HEBTEM decision fusion for a CANopen taxel network.

Public API (``docs/api.md``); internal module paths are free to change, these names are not.
The node twins on a private virtual bus, the centre fusing 20 SYNC cycles, the core directly::

    import numpy as np

    import fusion_center as fc
    import node_sim

    scene = fc.load_scene("scenes/matrix57.toml")                       # -> fc.Scene
    channels = [f"api-example-{name}" for name in scene.bus.channels]   # python-can virtual channels
    rig = node_sim.Rig(scene, interface="virtual", channel=channels)    # 57 CANopen node twins
    with fc.FusionService(scene, interface="virtual", channels=channels) as centre:
        rig.start()
        centre.boot()                                                   # NMT, SDO configuration
        summary = centre.run(20)                                        # -> fc.RunSummary
    rig.stop()
    decisions = [record["decision"] for record in centre.records]       # "H1", "H0" or "undecided"
    threshold = fc.core.additive_threshold(57, 0.9, 0.03)               # eq 17
    mc = fc.simulate(scene, 2_000, np.random.default_rng(1), central=False)  # Monte Carlo, every rule

Layout: :mod:`.core` (pure functions of the method), :mod:`.service` (the CANopen master on
python-can), :mod:`.commands` (the ``fusion-center`` CLI), :mod:`.evaluation` (the core
applied to a scene), :mod:`.stages` (what a scene needs and supports), :mod:`.report` (bandwidth, report, plots).
Shared with the node twins: the package ``taxel_net`` (scene, errors, CAN frame helper).
Names are imported on first use: ``import fusion_center.core.rules`` stays free of CAN.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# public name -> (module, attribute); attribute None: the module itself
_EXPORTS: dict[str, tuple[str, str | None]] = {
    "load_scene": ("taxel_net.scene", "load_scene"),
    "Scene": ("taxel_net.scene", "Scene"),
    "ParameterError": ("taxel_net.errors", "ParameterError"),
    "SceneError": ("taxel_net.errors", "SceneError"),
    "UsageError": ("taxel_net.errors", "UsageError"),
    "FusionService": ("fusion_center.service", "FusionService"),
    "RunSummary": ("fusion_center.service", "RunSummary"),
    "replay_trace": ("fusion_center.service", "replay_trace"),
    "read_records": ("fusion_center.service", "read_records"),
    "plan_stages": ("fusion_center.stages", "plan_stages"),
    "StagePlan": ("fusion_center.stages", "StagePlan"),
    "simulate": ("fusion_center.evaluation", "simulate"),
    "core": ("fusion_center.core", None),
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module_name, attribute = _EXPORTS[name]
    module = importlib.import_module(module_name)
    value = module if attribute is None else getattr(module, attribute)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
